//! Where a train step's time goes, stage by stage, for a job preset on this CPU:
//! ray encoding, encoder, slot attention and decoder forward, and the backward pass.
//!
//! ```sh
//! RAYON_NUM_THREADS=1 cargo run --release -p osrt-trainer --example step_stages [PRESET]
//! ```
//!
//! Medians over 8 repeats of the preset's batch (scenes generated in memory). Run it
//! with the workers' allocator settings for figures comparable to `osrt bench model`
//! (`MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=4294967296
//! MALLOC_TOP_PAD_=268435456`).

use candle_core::{Device, Var};
use osrt_bench::median;
use osrt_dataset::generator::GeneratorConfig;
use osrt_dataset::{
    BatchConfig, InputSelection, TargetViews, build_batch, generator::generate_scene,
};
use osrt_trainer::{BatchTensors, JobConfig, Trainer};
use rand::SeedableRng;
use std::time::Instant;

const REPEATS: usize = 8;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let preset = std::env::args().nth(1).unwrap_or("clevr-lite-cpu".into());
    let job = JobConfig::preset(&preset)?;
    let t = &job.train;
    let generator = GeneratorConfig {
        image_size: 32,
        ..GeneratorConfig::clevr_lite()
    };
    let scenes = (0..t.batch_size as u64)
        .map(|i| generate_scene(&generator, 0, "stages", i))
        .collect::<Result<Vec<_>, _>>()?;
    let refs: Vec<_> = scenes.iter().collect();
    let cfg = BatchConfig {
        input_views: t.input_views,
        input_selection: InputSelection::Random,
        target_views: TargetViews::All,
        rays_per_scene: Some(t.rays_per_scene),
        with_masks: false,
        salient_fraction: 0.0,
        ray_frame: osrt_dataset::RayFrame::World,
        input_stride: 1,
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let trainer = Trainer::new(job.clone(), Device::Cpu)?;
    let b = BatchTensors::new(&build_batch(&refs, &cfg, &mut rng)?, &Device::Cpu)?;
    let m = &trainer.model;

    let stages = [
        "input ray encoding",
        "encoder (with its ray encoding)",
        "slot attention",
        "target ray encoding",
        "decoder",
        "backward (whole step)",
        "decoder alone, forward + backward",
    ];
    let mut times = vec![Vec::new(); stages.len()];
    for _ in 0..REPEATS {
        let mut clock = Instant::now();
        let mut lap = |i: usize, times: &mut Vec<Vec<f64>>| {
            times[i].push(clock.elapsed().as_secs_f64());
            clock = Instant::now();
        };
        m.rays.forward(&b.origins, &b.directions)?;
        lap(0, &mut times);
        let tokens = m
            .encoder
            .forward(&m.rays, &b.images, &b.origins, &b.directions)?;
        lap(1, &mut times);
        let slots = m.slot_attention.forward(&tokens, None)?.slots;
        lap(2, &mut times);
        m.rays.forward(&b.target_origins, &b.target_directions)?;
        lap(3, &mut times);
        let out = m.decode(&slots, &b.target_origins, &b.target_directions)?;
        lap(4, &mut times);
        let loss = (&out.rgb - &b.target_rgb)?.sqr()?.mean_all()?;
        loss.backward()?;
        lap(5, &mut times);
        // The decoder on its own: the slots as a leaf variable.
        let leaf = Var::from_tensor(&slots.detach())?;
        let out = m.decode(leaf.as_tensor(), &b.target_origins, &b.target_directions)?;
        (&out.rgb - &b.target_rgb)?.sqr()?.mean_all()?.backward()?;
        lap(6, &mut times);
    }
    println!(
        "{preset}: batch {}, {} rays per scene, {} thread(s); medians of {REPEATS}",
        t.batch_size,
        t.rays_per_scene,
        candle_core::utils::get_num_threads()
    );
    for (name, t) in stages.iter().zip(times) {
        println!("  {name:<36} {:>8.1} ms", median(t) * 1e3);
    }
    Ok(())
}
