//! Whether a device computes the CPU's train step: the same initial weights, batch and
//! slot noise on the CPU (fused kernels, f32) and on the device (the job's kernels and
//! precision), compared as relative errors of the loss and of the flat gradient, and of
//! the weights after one AdamW step from the same gradient (on the device, as a device
//! tensor). The one-node ops with device kernels are compared one by one in
//! `osrt_kernels::device_check`.
//!
//! `osrt check-device` prints it; `tests/device.rs` asserts the tolerances below.

use crate::model::bench_batch;
use candle_core::Device;
use osrt_kernels::Precision;
use osrt_trainer::device::DeviceSpec;
use osrt_trainer::{Gradient, JobConfig, Result, Trainer};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

/// Largest relative L2 error of the whole gradient accepted with f32 products: the CPU
/// kernels and cuBLAS sum in different orders, nothing more.
pub const GRADIENT_TOLERANCE_F32: f64 = 1e-3;
/// The same with bf16 products (8 bits of mantissa: ~0.4 % per rounded operand).
pub const GRADIENT_TOLERANCE_BF16: f64 = 5e-2;
/// Largest relative difference of the weights after one AdamW step from the same
/// gradient (the update is the same f64 arithmetic on both sides).
pub const STEP_TOLERANCE: f64 = 1e-6;

#[derive(Debug, Clone, Serialize)]
pub struct DeviceCheck {
    pub preset: String,
    pub device: String,
    pub precision: String,
    pub parameters: usize,
    pub loss_cpu: f64,
    pub loss_device: f64,
    /// `‖g_device − g_cpu‖ / ‖g_cpu‖` over the flat gradient.
    pub gradient_rel_l2: f64,
    /// The parameter tensor with the largest relative L2 error, and that error:
    /// `‖Δ_p‖ / max(‖g_p‖, 1e-3·‖g‖)`. The floor keeps a tensor whose gradient is
    /// nearly zero on both sides from reporting its rounding noise as a large ratio.
    pub worst_parameter: String,
    pub worst_parameter_rel_l2: f64,
    /// `max |w_device − w_cpu| / max |w_cpu|` after one AdamW step from the CPU's gradient.
    pub step_rel_max: f64,
    /// Whether the figures are within the tolerances above.
    pub pass: bool,
}

/// `(‖a − b‖, ‖a‖)`.
fn diff_and_norm(a: &[f32], b: &[f32]) -> (f64, f64) {
    let (mut d, mut n) = (0f64, 0f64);
    for (&x, &y) in a.iter().zip(b) {
        d += (x as f64 - y as f64).powi(2);
        n += (x as f64).powi(2);
    }
    (d.sqrt(), n.sqrt())
}

/// `‖a − b‖ / max(‖a‖, floor)` (0 when both are 0).
fn rel_l2(a: &[f32], b: &[f32], floor: f64) -> f64 {
    let (d, n) = diff_and_norm(a, b);
    if d == 0.0 { 0.0 } else { d / n.max(floor) }
}

/// Runs the comparison for `job` (its model, batch size and rays; `train.precision` for
/// the device side) at `image_size`.
pub fn compare_with_cpu(
    preset: &str,
    job: &JobConfig,
    device: &Device,
    image_size: u32,
) -> Result<DeviceCheck> {
    let mut on_cpu = job.clone();
    on_cpu.train.device = DeviceSpec::Cpu;
    on_cpu.train.precision = Precision::F32;
    let mut on_dev = job.clone();
    on_dev.train.device = DeviceSpec::from_device(device);
    let mut cpu = Trainer::new(on_cpu, Device::Cpu)?;
    let mut dev = Trainer::new(on_dev, device.clone())?;
    let batch = bench_batch(job, image_size, &mut ChaCha8Rng::seed_from_u64(7))?;
    let g_cpu = cpu.gradients(&batch, &mut ChaCha8Rng::seed_from_u64(8))?;
    let g_dev = dev.gradients(&batch, &mut ChaCha8Rng::seed_from_u64(8))?;

    let gradient_rel_l2 = rel_l2(&g_cpu.grads, &g_dev.grads, 0.0);
    let floor = 1e-3 * osrt_trainer::optim::global_norm(&g_cpu.grads);
    let mut worst = (String::new(), 0f64);
    let mut off = 0;
    for (name, var) in cpu.params.vars() {
        let n = var.elem_count();
        let e = rel_l2(
            &g_cpu.grads[off..off + n],
            &g_dev.grads[off..off + n],
            floor,
        );
        if e > worst.1 || worst.0.is_empty() {
            worst = (name, e);
        }
        off += n;
    }

    cpu.apply(g_cpu.loss, g_cpu.grads.clone())?;
    // On a GPU the gradient goes in as a device tensor, as a single worker's stays there.
    let on_dev = if device.is_cpu() {
        Gradient::Host(g_cpu.grads)
    } else {
        let n = g_cpu.grads.len();
        Gradient::Device(candle_core::Tensor::from_vec(g_cpu.grads, n, device)?)
    };
    dev.apply(g_cpu.loss, on_dev)?;
    let (w_cpu, w_dev) = (cpu.params.flatten()?, dev.params.flatten()?);
    let scale = w_cpu
        .iter()
        .fold(0f32, |m, x| m.max(x.abs()))
        .max(f32::MIN_POSITIVE);
    let step_rel_max = w_cpu
        .iter()
        .zip(&w_dev)
        .fold(0f32, |m, (a, b)| m.max((a - b).abs()))
        / scale;

    let tolerance = match job.train.precision {
        Precision::F32 => GRADIENT_TOLERANCE_F32,
        Precision::Bf16 => GRADIENT_TOLERANCE_BF16,
    };
    let step_rel_max = step_rel_max as f64;
    Ok(DeviceCheck {
        preset: preset.to_string(),
        device: DeviceSpec::from_device(device).to_string(),
        precision: job.train.precision.to_string(),
        parameters: cpu.num_parameters(),
        loss_cpu: g_cpu.loss,
        loss_device: g_dev.loss,
        gradient_rel_l2,
        worst_parameter: worst.0,
        worst_parameter_rel_l2: worst.1,
        step_rel_max,
        pass: gradient_rel_l2 <= tolerance
            && step_rel_max <= STEP_TOLERANCE
            && g_dev.loss.is_finite(),
    })
}

/// One check of the device's plumbing beside the ops and steps: the staging of a
/// gradient for the all-reduce, the memory pool's peak, the recognition of an
/// out-of-memory error, and buffers freed on another thread.
#[derive(Debug, Clone, Serialize)]
pub struct PlumbingCheck {
    pub check: &'static str,
    pub pass: bool,
    /// What was seen, in words.
    pub detail: String,
}

/// Floats of the gradient the staging check sends through (three ring buckets and a part).
const PLUMBING_FLOATS: usize = 3 * (1 << 22) + 12_345;

/// The plumbing checks for `device`; on the CPU only the staging and the recomputed step
/// (the others concern a GPU's memory pool and context).
pub fn plumbing(device: &Device) -> Result<Vec<PlumbingCheck>> {
    let bucket = osrt_run::cluster_config::ClusterConfig::default().bucket_floats;
    let mut out = vec![
        staged_round_trip(device, PLUMBING_FLOATS, bucket)?,
        recomputed_step(device)?,
    ];
    if device.is_cuda() {
        out.push(peak_memory(device)?);
        out.push(out_of_memory(device)?);
        out.push(freed_on_another_thread(device)?);
    }
    Ok(out)
}

/// Largest relative L2 difference between a step's gradient with its activations made
/// again in the backward pass and the same step keeping them: the same ops on the same
/// inputs, where only the decoder's query sums its three gradients in another order.
pub const RECOMPUTE_TOLERANCE: f64 = 1e-5;

/// `clevr-lite-cpu`'s step on the GPU's graph with `train.recompute` against the same step
/// without (f32, and bf16 on a GPU): a device whose ops gave other values the second time
/// they run on the same inputs would show here.
fn recomputed_step(device: &Device) -> Result<PlumbingCheck> {
    let precisions: &[Precision] = match device.is_cuda() {
        true => &[Precision::F32, Precision::Bf16],
        false => &[Precision::F32],
    };
    let mut detail = Vec::new();
    let mut pass = true;
    for &precision in precisions {
        let mut job = JobConfig::preset("clevr-lite-cpu")?;
        job.train.device = DeviceSpec::from_device(device);
        job.train.kernels = osrt_kernels::Kernels::Device;
        job.train.precision = precision;
        let batch = bench_batch(&job, 32, &mut ChaCha8Rng::seed_from_u64(7))?;
        let step = |recompute: bool| -> Result<Vec<f32>> {
            let mut job = job.clone();
            job.train.recompute = recompute;
            let t = Trainer::new(job, device.clone())?;
            Ok(t.gradients(&batch, &mut ChaCha8Rng::seed_from_u64(8))?
                .grads)
        };
        let (kept, recomputed) = (step(false)?, step(true)?);
        let rel = rel_l2(&kept, &recomputed, 0.0);
        let same_bits = kept
            .iter()
            .zip(&recomputed)
            .all(|(a, b)| a.to_bits() == b.to_bits());
        pass &= rel <= RECOMPUTE_TOLERANCE && recomputed.iter().all(|g| g.is_finite());
        detail.push(format!(
            "{precision}: gradient rel. L2 {rel:.1e} (≤ {RECOMPUTE_TOLERANCE:e}){}",
            if same_bits { ", the same bits" } else { "" }
        ));
    }
    Ok(PlumbingCheck {
        check: "recomputed activations",
        pass,
        detail: detail.join("; "),
    })
}

/// A gradient of `n` floats to the host and back through the all-reduce's staging
/// (page-locked memory, the ring's cut into buckets of `bucket`) comes back with its bits,
/// twice with the same staging.
fn staged_round_trip(device: &Device, n: usize, bucket: usize) -> Result<PlumbingCheck> {
    use osrt_trainer::staging::{Staging, ring_buckets};
    let g = (candle_core::Tensor::arange(0u32, n as u32, device)?
        .to_dtype(candle_core::DType::F32)?
        * 1e-3)?;
    let sent = g.to_vec1::<f32>()?;
    let mut staging = Staging::new(
        device,
        n,
        ring_buckets(n + osrt_trainer::CONTROL_FLOATS, bucket),
    )?;
    let mut detail = format!("{n} floats in buckets of {bucket}: ");
    let mut pass = true;
    for round in 1..=2 {
        let back = staging.round_trip(&g)?.into_host()?;
        match (0..n).find(|&i| back[i].to_bits() != sent[i].to_bits()) {
            None => detail.push_str(&format!("round {round} exact; ")),
            Some(i) => {
                pass = false;
                detail.push_str(&format!(
                    "round {round}: float {i} sent {} came back {}; ",
                    sent[i], back[i]
                ));
            }
        }
    }
    Ok(PlumbingCheck {
        check: "staged gradient round trip",
        pass,
        detail: detail.trim_end_matches("; ").to_string(),
    })
}

/// The pool's high-water mark sees a 256 MiB buffer allocated after a reset.
fn peak_memory(device: &Device) -> Result<PlumbingCheck> {
    let bytes = 256u64 << 20;
    let reset = osrt_trainer::device::reset_device_peak(device);
    let t = candle_core::Tensor::zeros((bytes / 4) as usize, candle_core::DType::F32, device)?;
    device.synchronize()?;
    let peak = osrt_trainer::device::device_peak_bytes(device);
    drop(t);
    let pass = reset && peak.is_some_and(|p| p >= bytes);
    // How the pool counts small buffers, of which a step holds thousands (PyTorch's peak
    // counts each at its size rounded up to 512 bytes): a figure, not a condition.
    use osrt_kernels::profile::MemoryMeter;
    let before = osrt_trainer::device::Meter(device.clone()).live();
    osrt_trainer::device::reset_device_peak(device);
    let small = (0..1000)
        .map(|_| candle_core::Tensor::zeros(1024, candle_core::DType::F32, device))
        .collect::<candle_core::Result<Vec<_>>>()?;
    device.synchronize()?;
    let small_peak = osrt_trainer::device::device_peak_bytes(device);
    drop(small);
    let counted = small_peak.zip(before).map(|(p, b)| p.saturating_sub(b));
    Ok(PlumbingCheck {
        check: "peak device memory",
        pass,
        detail: format!(
            "reset {reset}; after a 256 MiB buffer the peak reads {peak:?} bytes; 1,000 \
             buffers of 4,096 bytes add {counted:?} to it"
        ),
    })
}

/// A request larger than the card fails as out of memory (what the step's retry and its
/// final error recognise), the pool gives its free blocks back, and the device goes on.
fn out_of_memory(device: &Device) -> Result<PlumbingCheck> {
    let ordinal = match device.location() {
        candle_core::DeviceLocation::Cuda { gpu_id } => gpu_id,
        _ => 0,
    };
    let card = osrt_trainer::device::gpu_memory(ordinal).unwrap_or(1e12);
    let floats = (2.0 * card / 4.0) as usize;
    let (recognised, text) =
        match candle_core::Tensor::zeros(floats, candle_core::DType::F32, device) {
            Ok(_) => (
                false,
                "a buffer twice the card's size was allocated".to_string(),
            ),
            Err(e) => (osrt_trainer::device::is_out_of_memory(&e), e.to_string()),
        };
    let released = osrt_trainer::device::release_cached(device);
    // The device still works after the failed request.
    let after = candle_core::Tensor::ones(1024, candle_core::DType::F32, device)
        .and_then(|t| t.sum_all()?.to_scalar::<f32>());
    let works = matches!(after, Ok(s) if s == 1024.0);
    Ok(PlumbingCheck {
        check: "out of memory recognised",
        pass: recognised && released && works,
        detail: format!(
            "{floats} floats asked for: \"{text}\"; recognised {recognised}, pool released \
             {released}, device works after {works}"
        ),
    })
}

/// A device buffer dropped on a thread that never touched the device is freed without
/// an error left on the context (cudarc frees on the buffer's stream without binding the
/// context when it does not track events).
fn freed_on_another_thread(device: &Device) -> Result<PlumbingCheck> {
    let t = candle_core::Tensor::ones(1 << 20, candle_core::DType::F32, device)?;
    device.synchronize()?;
    std::thread::spawn(move || drop(t)).join().map_err(|_| {
        osrt_trainer::TrainError::Device("the thread dropping a buffer panicked".into())
    })?;
    let state = context_error(device);
    let again = candle_core::Tensor::ones(1 << 20, candle_core::DType::F32, device)
        .and_then(|t| t.sum_all()?.to_scalar::<f32>())
        .map_err(|e| e.to_string());
    let pass = state.is_none() && again == Ok((1 << 20) as f32);
    Ok(PlumbingCheck {
        check: "buffer freed on another thread",
        pass,
        detail: format!(
            "context error after the drop: {}; a sum after it: {again:?}",
            state.as_deref().unwrap_or("none")
        ),
    })
}

/// The error an earlier asynchronous call left on the device's context, if any.
fn context_error(device: &Device) -> Option<String> {
    #[cfg(feature = "cuda")]
    if let Device::Cuda(d) = device {
        return d
            .cuda_stream()
            .context()
            .check_err()
            .err()
            .map(|e| e.to_string());
    }
    let _ = device;
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On the CPU the staging check runs (plain host pieces) and passes, over several
    /// buckets (`osrt check-device --device cpu` runs it at full size: tests/cli.rs).
    #[test]
    fn the_cpu_runs_the_staging_check() {
        let c = staged_round_trip(&Device::Cpu, 12_345, 1_000).unwrap();
        assert!(c.pass, "{c:?}");
        assert!(c.detail.contains("round 2 exact"), "{c:?}");
    }
}
