//! Model benchmarks for `osrt bench model`: train-step time of a job preset and render
//! speed of each decoder at several slot counts. Figures are medians over repeats; the
//! thread count is whatever this process runs with (the CLI runs one process per count).

use crate::config::JobConfig;
use crate::error::Result;
use crate::step::{BatchTensors, Trainer};
use candle_core::Device;
use osrt_dataset::bench::median;
use osrt_dataset::generator::GeneratorConfig;
use osrt_dataset::{BatchConfig, InputSelection, Scene, TargetViews, build_batch, generate_scene};
use osrt_model::{Config, Osrt, Params};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::time::Instant;

#[derive(Debug, Clone, Serialize)]
pub struct StepFigures {
    pub preset: String,
    pub parameters: usize,
    pub batch_size: usize,
    pub rays_per_scene: usize,
    pub image_size: u32,
    /// Whether the fused ops (osrt_model::fused) were on.
    pub fused: bool,
    pub median_step_s: f64,
    pub median_forward_backward_s: f64,
    pub scenes_per_s: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct RenderFigures {
    pub decoder: String,
    pub slots: usize,
    pub image_size: u32,
    pub median_frame_s: f64,
    pub fps: f64,
}

fn bench_scenes(n: u64, size: u32) -> Result<Vec<Scene>> {
    let cfg = GeneratorConfig {
        image_size: size,
        ..GeneratorConfig::clevr_lite()
    };
    Ok((0..n)
        .map(|i| generate_scene(&cfg, 0, "bench", i))
        .collect::<osrt_dataset::Result<_>>()?)
}

/// Median time of a full optimiser step (batch build excluded) over `steps` after one
/// warm-up step, with the fused ops as this thread has them (`fused::with_fused`).
pub fn bench_step(
    preset: &str,
    job: &JobConfig,
    image_size: u32,
    steps: usize,
) -> Result<StepFigures> {
    let scenes = bench_scenes(job.train.batch_size as u64, image_size)?;
    let refs: Vec<&Scene> = scenes.iter().collect();
    let mut trainer = Trainer::new(job.clone(), Device::Cpu)?;
    let cfg = BatchConfig {
        input_views: job.train.input_views,
        input_selection: InputSelection::Random,
        target_views: TargetViews::All,
        rays_per_scene: Some(job.train.rays_per_scene),
        with_masks: false,
        salient_fraction: 0.0,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut step_s = Vec::new();
    let mut fb_s = Vec::new();
    for i in 0..=steps {
        let batch = build_batch(&refs, &cfg, &mut rng)?;
        let t0 = Instant::now();
        let g = trainer.gradients(&batch, &mut rng)?;
        let t1 = Instant::now();
        trainer.apply(g.loss, g.grads)?;
        if i > 0 {
            step_s.push(t0.elapsed().as_secs_f64());
            fb_s.push((t1 - t0).as_secs_f64());
        }
    }
    let m = median(step_s);
    Ok(StepFigures {
        preset: preset.to_string(),
        parameters: trainer.num_parameters(),
        batch_size: job.train.batch_size,
        rays_per_scene: job.train.rays_per_scene,
        image_size,
        fused: osrt_model::fused::enabled(),
        median_step_s: m,
        median_forward_backward_s: median(fb_s),
        scenes_per_s: job.train.batch_size as f64 / m,
    })
}

/// Median time to decode one whole `image_size²` view from `slots` slots (encoding
/// excluded: rendering novel views reuses the slots).
pub fn bench_render(
    model_cfg: &Config,
    decoder: &str,
    slots: usize,
    image_size: u32,
    repeats: usize,
) -> Result<RenderFigures> {
    let mut cfg = model_cfg
        .clone()
        .with_decoder(decoder)
        .expect("known decoder");
    cfg.slot_attention.num_slots = slots;
    let params = Params::new(0);
    let model = Osrt::new(&cfg, params.var_builder(&Device::Cpu))?;
    let scenes = bench_scenes(1, image_size)?;
    let bcfg = BatchConfig {
        input_views: 1,
        input_selection: InputSelection::First,
        target_views: TargetViews::NonInput,
        rays_per_scene: None,
        with_masks: false,
        salient_fraction: 0.0,
    };
    let batch = build_batch(&[&scenes[0]], &bcfg, &mut ChaCha8Rng::seed_from_u64(0))?;
    let t = BatchTensors::new(&batch, &Device::Cpu)?;
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
        let out = osrt_model::fused::on_device_pool(&Device::Cpu, || model.decode(&s, &o, &d))?;
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
