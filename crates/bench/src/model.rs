//! Model benchmarks for `osrt bench model`: train-step time of a job preset and render
//! speed of each decoder at several slot counts. Figures are medians over repeats; the
//! thread count is whatever this process runs with (the CLI runs one process per count).

use crate::median;
use candle_core::{DType, Device, Tensor};
use osrt_dataset::generator::GeneratorConfig;
use osrt_dataset::{
    Batch, BatchConfig, InputSelection, Scene, TargetViews, build_batch, generator::generate_scene,
};
use osrt_model::{Config, Osrt, Params};
use osrt_trainer::staging::{Staging, ring_buckets};
use osrt_trainer::{BatchTensors, CONTROL_FLOATS, JobConfig, Result, Trainer};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// What one `osrt bench model` child measures (one thread count): the train steps, the
/// renders, or the per-op profiles.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct ModelReport {
    #[serde(default)]
    pub steps: Vec<StepFigures>,
    #[serde(default)]
    pub renders: Vec<RenderFigures>,
    #[serde(default)]
    pub profiles: Vec<ProfileFigures>,
    #[serde(default)]
    pub ledgers: Vec<LedgerFigures>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StepFigures {
    pub preset: String,
    pub parameters: usize,
    pub batch_size: usize,
    /// Scenes per forward and backward pass (`train.micro_batch_size`; `None`: the whole
    /// batch in one).
    pub micro_batch_size: Option<usize>,
    pub input_views: usize,
    pub rays_per_scene: usize,
    pub image_size: u32,
    /// `cpu` or `cuda:N`.
    pub device: String,
    /// The matrix products' precision.
    pub precision: String,
    /// Whether the fused ops (osrt_kernels, CPU only) ran.
    pub fused: bool,
    /// The job's kernels (`fused`, `composed`, `device`).
    pub kernels: String,
    /// Whether the backward pass made the segments' activations again
    /// (`train.recompute`).
    pub recompute: bool,
    pub median_step_s: f64,
    pub median_forward_backward_s: f64,
    /// On a GPU: a gradient's round trip device → host → device through the staging of a
    /// ring all-reduce (`osrt_trainer::staging`, bucket by bucket through page-locked memory,
    /// without the ring), as each of two or more workers pays it (median; 0 on the CPU).
    pub median_gradient_transfer_s: f64,
    /// Where that round trip failed or did not give back the gradient's bits: the first
    /// such error (the step's own figures stand; a bench is not ended by it).
    pub gradient_transfer_error: Option<String>,
    /// Median time of [`Trainer::apply`]: the optimiser step with its clipping and checks.
    pub median_optimizer_s: f64,
    pub scenes_per_s: f64,
    /// The most heap bytes live at once during a timed step, weights and optimiser state
    /// included (the CPU counterpart of `torch.cuda.max_memory_allocated`); `None` where
    /// the process does not count its allocations ([`osrt_trainer::memory::CountingAlloc`]).
    pub peak_heap_gib: Option<f64>,
    /// The process's peak resident memory during the timed steps (the figure
    /// `bench/torch_step.py` reports for PyTorch on the CPU).
    pub peak_rss_gib: Option<f64>,
    /// Timed steps the trainer skipped (a non-finite loss, gradient or update), and the
    /// first reason: a step that skips is not a step to compare with.
    pub skipped_steps: usize,
    pub skip_reason: Option<String>,
    /// On a GPU: the most device memory the step's tensors held at once, weights and
    /// optimiser state included (the memory pool's high-water mark, the counterpart of
    /// `torch.cuda.max_memory_allocated`); `None` on the CPU.
    pub peak_gib: Option<f64>,
    /// The step's peak as `osrt train` estimates it before a job starts
    /// ([`osrt_trainer::footprint::estimate`]): host RAM on the CPU (beside `peak_heap_gib`),
    /// device memory on a GPU (beside `peak_gib`); `None` for a model it cannot count.
    pub estimated_peak_gib: Option<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RenderFigures {
    pub decoder: String,
    pub slots: usize,
    pub image_size: u32,
    pub median_frame_s: f64,
    pub fps: f64,
}

/// `n` scenes of `size`² pixels with at least `views` views.
fn bench_scenes(n: u64, size: u32, views: usize) -> Result<Vec<Scene>> {
    let base = GeneratorConfig::clevr_lite();
    let cameras = base.cameras.clone().with_views(views.max(3));
    let cfg = GeneratorConfig {
        image_size: size,
        cameras,
        ..base
    };
    Ok((0..n)
        .map(|i| generate_scene(&cfg, 0, "bench", i))
        .collect::<osrt_dataset::Result<_>>()?)
}

/// Distinct scenes a benchmark batch cycles through (rendering big scenes is slow, and
/// the step's time does not depend on which scenes fill the batch).
const DISTINCT_SCENES: usize = 16;

/// Scenes for a benchmark batch of `job` (cycled to the batch size) and how batches are
/// drawn from them.
fn bench_data(job: &JobConfig, image_size: u32) -> Result<(Vec<Scene>, BatchConfig)> {
    let scenes = bench_scenes(
        job.train.batch_size.min(DISTINCT_SCENES) as u64,
        image_size,
        job.train.input_views + 1,
    )?;
    let cfg = BatchConfig {
        input_views: job.train.input_views,
        input_selection: InputSelection::Random,
        target_views: TargetViews::All,
        rays_per_scene: Some(job.train.rays_per_scene),
        with_masks: false,
        salient_fraction: 0.0,
        ray_frame: osrt_trainer::ray_frame(&job.model),
        input_stride: 1,
    };
    Ok((scenes, cfg))
}

/// One batch of `job`'s shape from generated scenes.
pub fn bench_batch(job: &JobConfig, image_size: u32, rng: &mut ChaCha8Rng) -> Result<Batch> {
    let (scenes, cfg) = bench_data(job, image_size)?;
    let refs: Vec<&Scene> = scenes.iter().cycle().take(job.train.batch_size).collect();
    Ok(build_batch(&refs, &cfg, rng)?)
}

/// Median time of a full optimiser step (batch build excluded) over `steps` after the
/// warm-up steps (one on the CPU; two on a GPU, whose first step loads its kernels), with
/// the job's kernels (`train.kernels`), on `device`.
pub fn bench_step(
    preset: &str,
    job: &JobConfig,
    image_size: u32,
    steps: usize,
    device: &Device,
) -> Result<StepFigures> {
    let b = job.train.batch_size;
    let (scenes, cfg) = bench_data(job, image_size)?;
    let refs: Vec<&Scene> = scenes.iter().cycle().take(b).collect();
    let mut trainer = Trainer::new(job.clone(), device.clone())?;
    let warmup = if device.is_cpu() { 1 } else { 2 };
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut step_s = Vec::new();
    let mut fb_s = Vec::new();
    let mut transfer_s = Vec::new();
    let mut optimizer_s = Vec::new();
    let mut peak_heap: Option<usize> = None;
    let mut peak_device: Option<u64> = None;
    let (mut skipped_steps, mut skip_reason) = (0, None);
    // A single worker's step: on a GPU the gradient stays there (the round trip that
    // several workers pay is timed apart, `median_gradient_transfer_s`).
    let keep = !device.is_cpu();
    let (mut staging, mut transfer_error) = (None, None);
    for i in 0..steps + warmup {
        let batch = build_batch(&refs, &cfg, &mut rng)?;
        if i == warmup {
            // The peaks of the timed steps only (the warm-up's first allocations of
            // optimiser state are not a step's).
            osrt_trainer::memory::reset_peak_rss();
        }
        osrt_trainer::memory::reset_peak_heap();
        osrt_trainer::device::reset_device_peak(device);
        // Both halves end synchronised, so the clock reads finished work on a GPU too.
        let t0 = Instant::now();
        let g = trainer.gradients_kept(&batch, &mut rng, keep)?;
        device.synchronize()?;
        let t1 = Instant::now();
        let gradients_peak = step_peak(device);
        let outcome = trainer.apply(g.loss, g.grads)?;
        device.synchronize()?;
        log_apply(t1, gradients_peak, device);
        if let osrt_trainer::ApplyOutcome::Skipped { reason } = outcome
            && i >= warmup
        {
            skipped_steps += 1;
            skip_reason.get_or_insert_with(|| format!("{reason} (loss {})", g.loss));
        }
        if i >= warmup {
            step_s.push(t0.elapsed().as_secs_f64());
            fb_s.push((t1 - t0).as_secs_f64());
            optimizer_s.push(t1.elapsed().as_secs_f64());
            peak_heap = osrt_trainer::memory::peak_heap_bytes().max(peak_heap);
            peak_device = osrt_trainer::device::device_peak_bytes(device).max(peak_device);
            if !device.is_cpu() && transfer_error.is_none() {
                let n = trainer.num_parameters();
                transfer_error = time_round_trip(&mut staging, n, device, &mut transfer_s);
            }
        }
    }
    let m = median(step_s);
    Ok(StepFigures {
        preset: preset.to_string(),
        parameters: trainer.num_parameters(),
        batch_size: b,
        micro_batch_size: job.train.micro_batch_size,
        input_views: job.train.input_views,
        rays_per_scene: job.train.rays_per_scene,
        image_size,
        device: osrt_trainer::device::DeviceSpec::from_device(device).to_string(),
        precision: job.train.precision.to_string(),
        fused: job.train.kernels == osrt_kernels::Kernels::Fused && device.is_cpu(),
        kernels: job.train.kernels.to_string(),
        recompute: job.train.recompute,
        median_step_s: m,
        median_forward_backward_s: median(fb_s),
        median_gradient_transfer_s: if transfer_s.is_empty() {
            0.0
        } else {
            median(transfer_s)
        },
        gradient_transfer_error: transfer_error,
        median_optimizer_s: median(optimizer_s),
        scenes_per_s: b as f64 / m,
        peak_heap_gib: peak_heap.map(gib),
        peak_rss_gib: osrt_trainer::memory::peak_rss_mb().map(|mb| mb / 1024.0),
        peak_gib: peak_device.map(|b| gib(b as usize)),
        estimated_peak_gib: osrt_trainer::footprint::estimate(
            job,
            [image_size, image_size],
            1,
            rayon::current_num_threads(),
        )
        .map(|m| m.total() / (1u64 << 30) as f64),
        skipped_steps,
        skip_reason,
    })
}

/// The time of each op kind in one preset's train step (`osrt bench model --profile`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ProfileFigures {
    pub preset: String,
    pub batch_size: usize,
    pub input_views: usize,
    pub rays_per_scene: usize,
    pub image_size: u32,
    pub device: String,
    pub precision: String,
    pub kernels: String,
    /// Medians of the step's own forward and backward passes (synchronised), over the
    /// timed steps.
    pub forward_s: f64,
    pub backward_s: f64,
    /// What the last timed step's forward pass left held (its graph) and the passes'
    /// peak, beyond what was held before it (`Phases`): the ops' kept bytes against it
    /// say how much of the graph's memory the ops account for.
    pub step_kept_bytes: Option<u64>,
    pub step_peak_bytes: Option<u64>,
    /// Each distinct op call of one step, timed alone (`osrt_kernels::profile`).
    pub ops: Vec<osrt_kernels::profile::CallTime>,
    /// The same per op kind, largest total time first.
    pub kinds: Vec<osrt_kernels::profile::KindTime>,
}

/// Profiles `job`'s train step on `device`: `steps` whole steps (after the warm-up) for
/// the forward and backward passes' medians, then one step's op calls recorded and each
/// distinct call timed alone (median of `repeats` runs), with the job's kernels and
/// precision.
pub fn profile_step(
    preset: &str,
    job: &JobConfig,
    image_size: u32,
    steps: usize,
    repeats: usize,
    device: &Device,
) -> Result<ProfileFigures> {
    use osrt_kernels::profile;
    let (scenes, cfg) = bench_data(job, image_size)?;
    let refs: Vec<&Scene> = scenes.iter().cycle().take(job.train.batch_size).collect();
    let mut trainer = Trainer::new(job.clone(), device.clone())?;
    trainer.time_phases = true;
    let warmup = if device.is_cpu() { 1 } else { 2 };
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let keep = !device.is_cpu();
    let (mut fwd, mut bwd, mut last) = (Vec::new(), Vec::new(), None);
    for i in 0..steps.max(1) + warmup {
        let batch = build_batch(&refs, &cfg, &mut rng)?;
        let g = trainer.gradients_kept(&batch, &mut rng, keep)?;
        if let (true, Some(p)) = (i >= warmup, g.phases) {
            fwd.push(p.forward_s);
            bwd.push(p.backward_s);
            last = Some(p);
        }
        trainer.apply(g.loss, g.grads)?;
    }
    let rec = profile::Recorder::default();
    let batch = build_batch(&refs, &cfg, &mut rng)?;
    profile::recording(Some(rec.clone()), || {
        trainer.gradients_kept(&batch, &mut rng, keep).map(drop)
    })?;
    let calls = rec.take();
    let (kernels, precision) = (job.train.kernels, job.train.precision);
    let ops = osrt_kernels::with_kernels(kernels, || {
        osrt_kernels::with_precision(precision, || {
            osrt_kernels::on_device_pool(device, || {
                let meter = osrt_trainer::device::Meter(device.clone());
                profile::time_calls(calls, device, repeats, &meter)
            })
        })
    })?;
    Ok(ProfileFigures {
        preset: preset.to_string(),
        batch_size: job.train.batch_size,
        input_views: job.train.input_views,
        rays_per_scene: job.train.rays_per_scene,
        image_size,
        device: osrt_trainer::device::DeviceSpec::from_device(device).to_string(),
        precision: precision.to_string(),
        kernels: kernels.to_string(),
        forward_s: median(fwd),
        backward_s: median(bwd),
        step_kept_bytes: last.and_then(|p| p.forward_kept_bytes),
        step_peak_bytes: last.and_then(|p| p.peak_bytes),
        kinds: profile::by_kind(&ops),
        ops,
    })
}

/// One train step's ledger (`osrt bench model --ledger`): its products, casts, copies and
/// other ops' bytes (`osrt_kernels::ledger`), and their totals per op kind with the time
/// they would take at an H200's rates.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LedgerFigures {
    pub preset: String,
    pub batch_size: usize,
    pub input_views: usize,
    pub rays_per_scene: usize,
    pub image_size: u32,
    pub device: String,
    pub precision: String,
    pub kernels: String,
    pub recompute: bool,
    pub parameters: usize,
    pub rates: osrt_kernels::ledger::Rates,
    pub entries: osrt_kernels::ledger::Entries,
    /// Per op kind, largest predicted time first, then the step's.
    pub totals: Vec<osrt_kernels::ledger::Totals>,
}

/// The ledger of one of `job`'s train steps on `device` (after one step, so that
/// whatever a first step does once is not counted), with the job's kernels and precision.
/// The optimiser's update is entered from the parameter count: AdamW reads each
/// parameter, its gradient and both moments and writes the parameter and the moments
/// (f32, no products).
pub fn ledger_step(
    preset: &str,
    job: &JobConfig,
    image_size: u32,
    device: &Device,
) -> Result<LedgerFigures> {
    use osrt_kernels::ledger::{self, H200, Ledger, Moved, Movement, Phase};
    let (scenes, cfg) = bench_data(job, image_size)?;
    let refs: Vec<&Scene> = scenes.iter().cycle().take(job.train.batch_size).collect();
    let mut trainer = Trainer::new(job.clone(), device.clone())?;
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let batch = build_batch(&refs, &cfg, &mut rng)?;
    let g = trainer.gradients(&batch, &mut rng)?;
    trainer.apply(g.loss, g.grads)?;
    let book = Ledger::default();
    let batch = build_batch(&refs, &cfg, &mut rng)?;
    ledger::recording(Some(book.clone()), || {
        trainer.gradients(&batch, &mut rng).map(drop)
    })?;
    let mut entries = book.take();
    let parameters = trainer.num_parameters();
    let f32_bytes = 4 * parameters as u64;
    entries.movements.push((
        Movement {
            kind: "optimiser".into(),
            phase: Phase::Backward,
            moved: Moved::Op,
            what: "AdamW".into(),
            read: 4 * f32_bytes,
            written: 3 * f32_bytes,
        },
        1,
    ));
    let totals = entries.totals(&H200);
    Ok(LedgerFigures {
        preset: preset.to_string(),
        batch_size: job.train.batch_size,
        input_views: job.train.input_views,
        rays_per_scene: job.train.rays_per_scene,
        image_size,
        device: osrt_trainer::device::DeviceSpec::from_device(device).to_string(),
        precision: job.train.precision.to_string(),
        kernels: job.train.kernels.to_string(),
        recompute: job.train.recompute,
        parameters,
        rates: H200,
        entries,
        totals,
    })
}

/// The update's time, and the step's peak before the update and with it (GiB: which of
/// the two holds it), in the debug log.
fn log_apply(started: Instant, gradients_peak: Option<u64>, device: &Device) {
    let gib = |b: Option<u64>| b.map_or(f64::NAN, |b| b as f64 / (1u64 << 30) as f64);
    tracing::debug!(
        apply_s = started.elapsed().as_secs_f64(),
        gradients_peak_gib = gib(gradients_peak),
        step_peak_gib = gib(step_peak(device)),
        "apply and drop"
    );
}

/// The most bytes held at once since the step began: the heap on the CPU (where the
/// binary counts it), the memory pool on a GPU.
fn step_peak(device: &Device) -> Option<u64> {
    match device.is_cpu() {
        true => osrt_trainer::memory::peak_heap_bytes().map(|b| b as u64),
        false => osrt_trainer::device::device_peak_bytes(device),
    }
}

fn gib(bytes: usize) -> f64 {
    bytes as f64 / (1u64 << 30) as f64
}

/// Times one [`gradient_round_trip`] into `times`; its error, if it fails.
fn time_round_trip(
    staging: &mut Option<Staging>,
    n: usize,
    device: &Device,
    times: &mut Vec<f64>,
) -> Option<String> {
    match gradient_round_trip(staging, n, device) {
        Ok(s) => {
            times.push(s);
            None
        }
        Err(e) => {
            tracing::error!(error = %e, "the staged gradient round trip failed");
            Some(e.to_string())
        }
    }
}

/// Seconds for an `n`-float gradient to go device → host → device the way two or more
/// workers' steps move it (`Staging::round_trip`: bucket by bucket through page-locked
/// memory), synchronised at the end; an error where it does not come back bit for bit.
fn gradient_round_trip(staging: &mut Option<Staging>, n: usize, device: &Device) -> Result<f64> {
    // Distinct values, so that a bucket copied to the wrong place shows.
    let g = (Tensor::arange(0u32, n as u32, device)?.to_dtype(DType::F32)? * 1e-3)?;
    let staging = match staging {
        Some(s) => s,
        None => {
            // The job's bucket size; the page-locked memory is made once, as a worker does.
            let bucket = osrt_run::cluster_config::ClusterConfig::default().bucket_floats;
            let buckets = ring_buckets(n + CONTROL_FLOATS, bucket);
            staging.insert(Staging::new(device, n, buckets)?)
        }
    };
    device.synchronize()?;
    let t0 = Instant::now();
    let back = staging.round_trip(&g)?;
    device.synchronize()?;
    let s = t0.elapsed().as_secs_f64();
    // Weight 1 and one scene: the gradient must come back with its own bits.
    let back = back.into_host()?;
    let sent = g.to_vec1::<f32>()?;
    if let Some(i) = (0..n).find(|&i| back[i].to_bits() != sent[i].to_bits()) {
        return Err(osrt_trainer::TrainError::Device(format!(
            "the staged round trip of the gradient changed float {i} of {n}: {} came back as {}",
            sent[i], back[i]
        )));
    }
    Ok(s)
}

/// The decoders `osrt bench model` renders with: the paper's three, and the volumetric
/// decoder with and without its box culling.
pub const RENDER_DECODERS: [&str; 5] = [
    "slot_mixer",
    "spatial_broadcast",
    "transformer",
    "volumetric",
    "volumetric_no_cull",
];

/// Median time to decode one whole `image_size²` view from `slots` slots (encoding
/// excluded: rendering novel views reuses the slots). `decoder` is one of
/// [`RENDER_DECODERS`]; the volumetric ones sample inside the bench scenes' box.
pub fn bench_render(
    model_cfg: &Config,
    decoder: &str,
    slots: usize,
    image_size: u32,
    repeats: usize,
    device: &Device,
) -> Result<RenderFigures> {
    let (kind, cull) = match decoder {
        "volumetric_no_cull" => ("volumetric", false),
        other => (other, true),
    };
    let mut cfg =
        model_cfg
            .clone()
            .with_decoder(kind)
            .ok_or_else(|| osrt_trainer::TrainError::Config {
                path: "bench".into(),
                reason: format!("unknown decoder `{decoder}`: expected one of {RENDER_DECODERS:?}"),
            })?;
    if let osrt_model::decoder::Config::Volumetric(v) = &mut cfg.decoder {
        v.bounds = Some(GeneratorConfig::clevr_lite().scene_bounds());
        v.cull = cull;
    }
    cfg.slot_attention.num_slots = slots;
    let params = Params::new(0);
    let model = Osrt::new(&cfg, params.var_builder(device))?;
    let scenes = bench_scenes(1, image_size, 2)?;
    let bcfg = BatchConfig {
        input_views: 1,
        input_selection: InputSelection::First,
        target_views: TargetViews::NonInput,
        rays_per_scene: None,
        with_masks: false,
        salient_fraction: 0.0,
        ray_frame: osrt_trainer::ray_frame(&cfg),
        input_stride: 1,
    };
    let batch = build_batch(&[&scenes[0]], &bcfg, &mut ChaCha8Rng::seed_from_u64(0))?;
    let t = BatchTensors::new(&batch, device)?;
    let s = model
        .encode(&t.images, &t.origins, &t.directions, None)?
        .slots;
    let px = (image_size * image_size) as usize;
    let (o, d) = (
        t.target_origins.narrow(1, 0, px)?,
        t.target_directions.narrow(1, 0, px)?,
    );
    let mut times = Vec::new();
    for i in 0..=repeats {
        let t0 = Instant::now();
        // As the render path runs it (render::decode_rays).
        let out = osrt_kernels::on_device_pool(device, || model.decode(&s, &o, &d))?;
        let _ = out.rgb.flatten_all()?.to_vec1::<f32>()?;
        if i > 0 {
            times.push(t0.elapsed().as_secs_f64());
        }
    }
    let m = median(times);
    Ok(RenderFigures {
        decoder: decoder.to_string(),
        slots,
        image_size,
        median_frame_s: m,
        fps: 1.0 / m,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The timed round trip (a GPU's, run here through the CPU's staging) checks what
    /// comes back, over several buckets, with the staging kept between calls.
    #[test]
    fn the_gradient_round_trip_comes_back_whole() {
        let n = 12_345;
        let buckets = ring_buckets(n + CONTROL_FLOATS, 1_000);
        let mut staging = Some(Staging::new(&Device::Cpu, n, buckets).unwrap());
        for _ in 0..2 {
            let s = gradient_round_trip(&mut staging, n, &Device::Cpu).unwrap();
            assert!(s > 0.0);
        }
    }
}
