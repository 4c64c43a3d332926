//! A train step's peak memory per worker, estimated before anything is allocated, and
//! the memory of the machine it would run on: `osrt train` and the workers refuse a job
//! that cannot fit, with the figures and what to change.
//!
//! The estimate adds to the activations' peak ([`osrt_model::footprint`]) the weights,
//! AdamW's two moments and the batch (as built on the host and as the step's tensors).
//! On a GPU the weights, moments, batch tensors and activations are device memory; the
//! host keeps the batch and the gradient's copy for the all-reduce.

use crate::config::JobConfig;
use crate::device::DeviceSpec;
use osrt_kernels::{Kernels, Precision};
use osrt_model::footprint::{OpPath, StepShape};

const GIB: f64 = (1u64 << 30) as f64;

/// The estimated peak of one worker's train step, in bytes, by part.
#[derive(Debug, Clone, PartialEq)]
pub struct StepMemory {
    /// `host RAM` or `GPU memory`.
    pub kind: &'static str,
    pub weights: f64,
    /// AdamW's first and second moments.
    pub optimizer: f64,
    /// The batch as built on the host and as the step's tensors.
    pub batch: f64,
    /// Activations and gradients at the forward or backward pass's peak (of one
    /// micro-batch).
    pub activations: f64,
    /// The gradient summed over micro-batches, beside a micro-batch's own (none in one
    /// pass).
    pub accumulated: f64,
    /// Scenes of this worker's share of the batch, run as `shape.batch`-scene passes.
    pub share: usize,
    /// The shapes it was computed for.
    pub shape: StepShape,
    /// Whether this op path's estimate is checked against measured peaks (the fused
    /// CPU step's is, in `tests/memory_estimate.rs`); the others are counts from the code.
    pub checked: bool,
    /// Where the step runs (whose memory it is held against).
    pub device: DeviceSpec,
}

impl StepMemory {
    pub fn total(&self) -> f64 {
        self.weights + self.optimizer + self.batch + self.activations + self.accumulated
    }

    /// One line for people: the total and its parts.
    pub fn describe(&self) -> String {
        let s = &self.shape;
        format!(
            "{}estimated peak {} per worker: {} (weights {}, optimiser {}, batch {}, activations {}{}{}) for {} scene(s) of {} view(s) at {}×{} px, {} rays each",
            if self.checked { "" } else { "(unchecked) " },
            self.kind,
            size(self.total()),
            size(self.weights),
            size(self.optimizer),
            size(self.batch),
            size(self.activations),
            if s.recompute { ", recomputed" } else { "" },
            match self.share > s.batch {
                true => format!(
                    ", summed gradient {}; a share of {} scenes in passes of {}",
                    size(self.accumulated),
                    self.share,
                    s.batch
                ),
                false => String::new(),
            },
            s.batch,
            s.input_views,
            s.width,
            s.height,
            s.rays,
        )
    }
}

/// `bytes` for people: GiB from 1 GiB up, MiB below.
fn size(bytes: f64) -> String {
    if bytes >= GIB {
        format!("{:.2} GiB", bytes / GIB)
    } else {
        format!("{:.1} MiB", bytes / (1u64 << 20) as f64)
    }
}

/// The estimate for one worker of `world` running `job` on `[width, height]` images
/// with `threads` threads; `None` for a model whose activations have no count (the
/// volumetric decoder).
pub fn estimate(
    job: &JobConfig,
    image: [u32; 2],
    world: usize,
    threads: usize,
) -> Option<StepMemory> {
    let t = &job.train;
    let share = crate::shard::local_batch_sizes(t.batch_size, world.max(1))[0];
    // One forward and backward pass holds one micro-batch's activations.
    let batch = t.micro_batch_size.map_or(share, |m| m.min(share));
    let shape = StepShape {
        batch,
        input_views: t.input_views,
        height: image[1] as usize,
        width: image[0] as usize,
        rays: t.rays_per_scene,
        threads,
        recompute: t.recompute,
        // Passes summed on the host take each segment's gradients as it ends
        // (`step::HostSum`); a gradient kept on the device (a GPU, or the device graph's
        // ring) sums whole passes.
        summed: batch < share
            && !t.device.is_cuda()
            && !(world > 1 && t.kernels == Kernels::Device),
    };
    let gpu = t.device.is_cuda();
    // `device` kernels build the GPU's graph on any device; the fused CPU kernels keep
    // f32 activations in bf16 too (their bf16 operands are packed per product).
    let path = if !gpu && t.kernels == Kernels::Fused {
        OpPath::Fused
    } else if gpu || t.kernels == Kernels::Device {
        OpPath::Gpu {
            bf16: t.precision == Precision::Bf16,
        }
    } else {
        OpPath::Composed
    };
    let f = osrt_model::footprint::step(&job.model, &shape, path)?;
    let params = f.parameters as f64;
    // Images, origins and directions of the input views, origins, directions and
    // colours of the target rays: f32; the targets' pixel coordinates. The whole share is
    // built on the host; its tensors are one micro-batch's.
    let scenes_bytes = |n: usize| {
        let pixels = (n * t.input_views * shape.height * shape.width) as f64;
        let rays = (n * t.rays_per_scene) as f64;
        (4.0 * (9.0 * pixels + 9.0 * rays) + 8.0 * rays, 8.0 * rays)
    };
    let (host_share, _) = scenes_bytes(share);
    let (host_batch, coordinates) = scenes_bytes(batch);
    Some(StepMemory {
        kind: if gpu { "GPU memory" } else { "host RAM" },
        weights: 4.0 * params,
        optimizer: 8.0 * params,
        batch: if gpu {
            host_batch - coordinates
        } else {
            host_share + host_batch
        },
        activations: f.activations,
        accumulated: if share > batch { 4.0 * params } else { 0.0 },
        share,
        shape,
        checked: path == OpPath::Fused,
        device: t.device,
    })
}

/// Where set, the memory (GiB) the workers on this machine may use in all, in place of
/// what the machine has: room left for other work, or a smaller machine's figure.
pub const MEMORY_LIMIT_ENV: &str = "OSRT_MEMORY_LIMIT_GIB";

/// The memory a worker on this machine may use for `device`, and what it is: the host's
/// (the smaller of `MemTotal` and the cgroup's limit, which is what a container gets), or
/// the GPU's, or [`MEMORY_LIMIT_ENV`]'s; `None` where it cannot be read.
pub fn machine_memory(device: DeviceSpec) -> Option<(f64, String)> {
    if let Some(gib) = std::env::var(MEMORY_LIMIT_ENV)
        .ok()
        .and_then(|v| v.parse::<f64>().ok())
    {
        return Some((gib * GIB, format!("the limit {MEMORY_LIMIT_ENV}={gib}")));
    }
    match device {
        DeviceSpec::Cpu => host_memory().map(|b| (b, "this machine's RAM".to_string())),
        DeviceSpec::Cuda(i) => {
            crate::device::gpu_memory(i).map(|b| (b, format!("GPU {i}'s memory")))
        }
    }
}

fn host_memory() -> Option<f64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = info.lines().find(|l| l.starts_with("MemTotal:"))?;
    let total = line.split_whitespace().nth(1)?.parse::<f64>().ok()? * 1024.0;
    let limit = [
        "/sys/fs/cgroup/memory.max",
        "/sys/fs/cgroup/memory/memory.limit_in_bytes",
    ]
    .iter()
    .filter_map(|p| std::fs::read_to_string(p).ok())
    .filter_map(|s| s.trim().parse::<f64>().ok())
    .fold(f64::INFINITY, f64::min);
    Some(total.min(limit))
}

/// The resident memory of a worker whose step's heap peaks at `step` bytes: the pages the
/// allocator keeps after a step (the workers' allocator settings keep freed tensors'
/// pages; `osrt bench model` measured resident peaks of 1.1–1.5 × the heap's on the CPU
/// presets at 32–256 px, 2026-11-27), the binary, its runtime and its data.
pub fn with_headroom(step: f64) -> f64 {
    1.35 * step + 0.5 * GIB
}

/// A job's step held against this machine: the estimate, the largest micro-batch that
/// would fit where the job as it is does not ([`micro_batch_that_fits`]), and the verdict
/// ([`fit_here`]).
#[derive(Debug, Clone)]
pub struct Fit {
    pub memory: StepMemory,
    pub micro: Option<usize>,
    pub verdict: Result<Option<String>, String>,
}

/// [`estimate`], [`micro_batch_that_fits`] and [`fit_here`] for `workers` workers of
/// `job` on this machine (`world` in the job, `threads` each, on `image`-sized inputs);
/// `None` where the model has no estimate.
pub fn check(
    job: &JobConfig,
    image: [u32; 2],
    world: usize,
    threads: usize,
    workers: usize,
) -> Option<Fit> {
    let memory = estimate(job, image, world, threads)?;
    let micro = micro_batch_that_fits(job, image, world, threads, workers);
    let verdict = fit_here(&memory, workers, micro);
    Some(Fit {
        memory,
        micro,
        verdict,
    })
}

/// Whether `workers` workers of `m` fit this machine ([`machine_memory`]): `Ok(None)`
/// where they do or its memory cannot be read; `Ok(Some(why))` where they may not but
/// this op path's estimate is not checked against measured peaks (a warning);
/// `Err(why)` where they do not.
/// `micro`: the largest micro-batch that fits ([`micro_batch_that_fits`]), named first in
/// the advice.
pub fn fit_here(
    m: &StepMemory,
    workers: usize,
    micro: Option<usize>,
) -> Result<Option<String>, String> {
    let Some((available, what)) = machine_memory(m.device) else {
        return Ok(None);
    };
    match refusal(m, workers, (available, &what), micro) {
        None => Ok(None),
        Some(why) if !m.checked => Ok(Some(why)),
        Some(why) => Err(why),
    }
}

/// The largest micro-batch (`train.micro_batch_size`, below the one `job` has) with which
/// `workers` workers of `job` fit this machine ([`machine_memory`], with
/// [`with_headroom`]); `None` where the job fits as it is, no micro-batch makes it fit,
/// or the machine's memory cannot be read.
pub fn micro_batch_that_fits(
    job: &JobConfig,
    image: [u32; 2],
    world: usize,
    threads: usize,
    workers: usize,
) -> Option<usize> {
    let m = estimate(job, image, world, threads)?;
    let (available, _) = machine_memory(m.device)?;
    let fits = |m: &StepMemory| with_headroom(m.total()) * workers as f64 <= available;
    if fits(&m) {
        return None;
    }
    (1..m.shape.batch).rev().find(|&size| {
        let mut smaller = job.clone();
        smaller.train.micro_batch_size = Some(size);
        estimate(&smaller, image, world, threads).is_some_and(|m| fits(&m))
    })
}

/// Why `workers` workers of `m` each cannot run in `available` bytes of `what`, and what
/// to change (`micro`: a micro-batch that fits, named first); `None` where they fit with
/// [`with_headroom`].
pub fn refusal(
    m: &StepMemory,
    workers: usize,
    (available, what): (f64, &str),
    micro: Option<usize>,
) -> Option<String> {
    let need = with_headroom(m.total()) * workers as f64;
    if need <= available {
        return None;
    }
    let each = if workers > 1 {
        format!(
            " ({workers} workers of {:.2} GiB)",
            with_headroom(m.total()) / GIB
        )
    } else {
        String::new()
    };
    let recompute = match m.shape.recompute {
        true => "",
        false => {
            " --recompute (activations made again in the backward pass: the same gradients, \
             about a third more time per step),"
        }
    };
    let micro = micro.map_or(String::new(), |size| {
        format!(
            " --micro-batch-size {size} (the largest micro-batch that fits: the same step, \
             its share run in passes of {size} scenes),"
        )
    });
    Some(format!(
        "the job needs about {:.2} GiB{each} and {what} is {:.2} GiB. {}; a worker's \
         resident memory is about 1.35 × that + 0.5 GiB. Make the step smaller:{micro}{recompute} --batch-size (scenes per step), \
         --rays-per-scene (the decoder's share), --precision bf16 (GPU), fewer workers on \
         this machine, or smaller images (osrt data import --resize WxH); --skip-memory-check runs it anyway",
        need / GIB,
        available / GIB,
        m.describe()
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The ledger reaches every parameter once: its count is the model's, for every
    /// preset, every counted decoder and every op path (fused, composed, GPU).
    #[test]
    fn the_ledger_counts_every_parameter_once() {
        for preset in ["tiny", "clevr-lite-cpu", "paper", "msn-hard"] {
            for decoder in ["slot_mixer", "transformer", "spatial_broadcast"] {
                let mut job = JobConfig::preset(preset).unwrap();
                job.model = job.model.with_decoder(decoder).unwrap();
                let p = osrt_model::Params::new(0);
                osrt_model::Osrt::new(&job.model, p.var_builder(&candle_core::Device::Cpu))
                    .unwrap();
                let params = p.num_elements();
                let mut composed = job.clone();
                composed.train.kernels = Kernels::Composed;
                let mut gpu = job.clone();
                gpu.train.device = DeviceSpec::Cuda(0);
                for (path, j) in [("fused", &job), ("composed", &composed), ("gpu", &gpu)] {
                    let m = estimate(j, [64, 64], 1, 2).unwrap();
                    assert_eq!(
                        m.weights,
                        4.0 * params as f64,
                        "{preset}, {decoder}, {path}"
                    );
                }
            }
        }
    }

    /// More pixels, scenes or rays never need less; the encoder's attention grows with
    /// the square of the tokens; a volumetric decoder has no estimate.
    #[test]
    fn the_estimate_grows_with_the_step() {
        let job = JobConfig::preset("tiny").unwrap();
        let at = |job: &JobConfig, w: u32, h: u32| estimate(job, [w, h], 1, 2).unwrap().total();
        let (small, big) = (at(&job, 64, 64), at(&job, 128, 128));
        assert!(big > 10.0 * small, "{small} → {big}");
        assert!(at(&job, 128, 64) > small && at(&job, 128, 64) < big);
        let mut more = job.clone();
        more.train.batch_size *= 2;
        more.train.rays_per_scene *= 4;
        assert!(at(&more, 64, 64) > small);
        let mut v = job.clone();
        v.model = v.model.with_decoder("volumetric").unwrap();
        assert!(estimate(&v, [64, 64], 1, 2).is_none());
    }

    /// The refusal names the figures, the limit and what to change; a job that fits with
    /// its headroom is not refused.
    #[test]
    fn a_refusal_says_what_is_needed_and_what_to_change() {
        let job = JobConfig::preset("tiny").unwrap();
        let m = estimate(&job, [320, 240], 2, 1).unwrap();
        let why = refusal(&m, 2, (24.0 * GIB, "this machine's RAM"), None).expect("refused");
        for needle in [
            "2 workers of",
            "this machine's RAM is 24.00 GiB",
            "--batch-size",
            "--skip-memory-check",
        ] {
            assert!(why.contains(needle), "{needle:?} in {why}");
        }
        let need = with_headroom(m.total()) * 2.0;
        assert!(refusal(&m, 2, (need, "x"), None).is_none());
        assert!(refusal(&m, 2, (need * 0.99, "x"), None).is_some());
    }

    /// Memory follows the micro-batch: its activations and tensors are one pass's, the
    /// share's batch stays on the host and the summed gradient is added; the largest
    /// micro-batch that fits is found and named first in the advice.
    #[test]
    fn memory_follows_the_micro_batch() {
        let mut job = JobConfig::preset("paper").unwrap();
        job.train.batch_size = 16;
        let whole = estimate(&job, [128, 128], 1, 2).unwrap();
        let mut micro = job.clone();
        micro.train.micro_batch_size = Some(2);
        let m = estimate(&micro, [128, 128], 1, 2).unwrap();
        let mut two = job.clone();
        two.train.batch_size = 2;
        let pass = estimate(&two, [128, 128], 1, 2).unwrap();
        assert_eq!((m.share, m.shape.batch), (16, 2));
        assert_eq!(m.activations, pass.activations);
        assert_eq!(m.accumulated, m.weights, "one f32 gradient");
        assert!(
            m.total() < 0.5 * whole.total(),
            "{} vs {}",
            m.describe(),
            whole.describe()
        );
        assert!(
            m.describe().contains("a share of 16 scenes in passes of 2"),
            "{}",
            m.describe()
        );
        let why = refusal(&whole, 1, (with_headroom(m.total()), "x"), Some(2)).unwrap();
        let (first, recompute) = (
            why.find("--micro-batch-size 2").unwrap(),
            why.find("--recompute").unwrap(),
        );
        assert!(first < recompute, "{why}");
    }
}
