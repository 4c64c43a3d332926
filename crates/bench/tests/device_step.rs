//! The train step on a GPU against the CPU's: the same weights, batch and slot noise give
//! gradients within `check::GRADIENT_TOLERANCE_*` (relative L2) and, from the same
//! gradient, weights within `check::STEP_TOLERANCE` after an AdamW step. Runs where the
//! `cuda` feature is built and a GPU is present; prints SKIPPED otherwise.

use candle_core::Device;
use osrt_bench::device_step::compare_with_cpu;
use osrt_kernels::Precision;
use osrt_trainer::device::cuda_device_count;
use osrt_trainer::{JobConfig, device::DeviceSpec};

fn gpu() -> Option<Device> {
    if cuda_device_count() == 0 {
        eprintln!(
            "SKIPPED: no CUDA device (built with the `cuda` feature: {})",
            cfg!(feature = "cuda")
        );
        return None;
    }
    Some(DeviceSpec::Cuda(0).open().expect("opening cuda:0"))
}

#[test]
fn gpu_gradients_and_optimiser_step_match_the_cpu() {
    let Some(dev) = gpu() else { return };
    for preset in ["tiny", "clevr-lite-cpu"] {
        for precision in [Precision::F32, Precision::Bf16] {
            let mut job = JobConfig::preset(preset).unwrap();
            job.train.device = DeviceSpec::Cuda(0);
            job.train.precision = precision;
            let c = compare_with_cpu(preset, &job, &dev, 32).unwrap();
            eprintln!("{c:?}");
            assert!(c.pass, "{c:?}");
        }
    }
}

/// The CPU against itself passes with zero error: the comparison's own arithmetic (same
/// seeds, same batch on both sides) adds nothing.
#[test]
fn the_comparison_of_the_cpu_with_itself_is_exact() {
    let job = JobConfig::preset("tiny").unwrap();
    let c = compare_with_cpu("tiny", &job, &Device::Cpu, 32).unwrap();
    assert_eq!(c.gradient_rel_l2, 0.0, "{c:?}");
    assert_eq!(c.step_rel_max, 0.0, "{c:?}");
    assert!(c.pass);
}
