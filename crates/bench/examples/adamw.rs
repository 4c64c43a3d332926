//! The host optimiser alone at the `paper` preset's size: the gradient's summary (norm,
//! finiteness, largest magnitude) and the AdamW update, on 82,590,720 parameters in 80
//! tensors of the preset's common sizes.
//!
//! ```sh
//! RAYON_NUM_THREADS=2 cargo run --release -p osrt-trainer --example adamw
//! ```
//!
//! Medians of 6 updates (the first touches the moments' pages). `osrt bench model`
//! reports the same phases inside a whole step (`median_optimizer_s`).

use candle_core::{Device, Tensor, Var};
use osrt_bench::median;
use osrt_trainer::optim::{AdamW, GradSummary, Hyperparams};
use std::time::Instant;

/// Deterministic values in [-0.5, 0.5).
fn values(n: usize, seed: u64) -> Vec<f32> {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| rng.random_range(-0.5f32..0.5)).collect()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let sizes: Vec<usize> = (0..80)
        .map(|i| [768 * 768, 768 * 3072, 768, 1536 * 768][i % 4])
        .collect();
    let vars = sizes
        .iter()
        .enumerate()
        .map(|(i, &n)| Var::from_tensor(&Tensor::from_vec(values(n, i as u64), n, &Device::Cpu)?))
        .collect::<candle_core::Result<Vec<_>>>()?;
    let n: usize = sizes.iter().sum();
    let g = values(n, 99);
    let hyper = Hyperparams {
        beta1: 0.9,
        beta2: 0.999,
        eps: 1e-8,
        weight_decay: 0.01,
    };
    let mut opt = AdamW::new(n, hyper);
    let (mut summary_s, mut update_s) = (Vec::new(), Vec::new());
    for _ in 0..6 {
        let t = Instant::now();
        let s = GradSummary::of(&g);
        summary_s.push(t.elapsed().as_secs_f64());
        let t = Instant::now();
        if !opt.step(&vars, 0, &g, s.max_abs, 1e-4)? {
            return Err("the update was refused".into());
        }
        update_s.push(t.elapsed().as_secs_f64());
    }
    println!(
        "{n} parameters, {} thread(s): summary {:.1} ms, update {:.1} ms (medians of 6)",
        rayon::current_num_threads(),
        median(summary_s) * 1e3,
        median(update_s) * 1e3
    );
    Ok(())
}
