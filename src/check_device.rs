//! `osrt check-device`: whether a GPU computes the CPU's train step (gradients and one
//! AdamW step on the same weights and batch), with the tolerances it is held to, and
//! whether its plumbing works (the gradient's staging, the memory pool, the context).

use anyhow::{Result, bail};
use clap::Args;
use osrt_bench::device_step::{
    DeviceCheck, GRADIENT_TOLERANCE_BF16, GRADIENT_TOLERANCE_F32, STEP_TOLERANCE, compare_with_cpu,
    plumbing,
};
use osrt_kernels::{Kernels, Precision};
use osrt_trainer::{JobConfig, device::DeviceSpec};

#[derive(Args)]
pub struct CheckDeviceArgs {
    /// The device compared with the CPU: cuda or cuda:N.
    #[arg(long, default_value = "cuda")]
    pub device: DeviceSpec,
    /// Job presets whose step is compared.
    #[arg(long, value_delimiter = ',', default_value = "tiny,clevr-lite-cpu")]
    pub presets: Vec<String>,
    /// Precisions of the device's matrix products (the CPU side is always f32); default
    /// f32,bf16 on a GPU, f32 where the device is the CPU (whose kernels are f32 only).
    #[arg(long, value_delimiter = ',')]
    pub precisions: Option<Vec<Precision>>,
    /// The device's kernels: fused (LayerNorm, softmax and bias+activation as one-node
    /// CUDA ops) and/or composed (candle's ops only).
    #[arg(long, value_delimiter = ',', default_value = "fused,composed")]
    pub kernels: Vec<Kernels>,
    /// Image size of the generated scenes.
    #[arg(long, default_value_t = 32)]
    pub image_size: u32,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    /// Only compile osrt's CUDA kernels with NVRTC (no GPU needed): whether they build.
    #[arg(long)]
    pub compile_only: bool,
}

pub fn run(a: CheckDeviceArgs) -> Result<()> {
    if a.compile_only {
        #[cfg(feature = "cuda")]
        {
            let bytes = osrt_kernels::cuda::compile()?;
            println!("osrt's CUDA kernels compile with NVRTC: {bytes} bytes of PTX");
            return Ok(());
        }
        #[cfg(not(feature = "cuda"))]
        bail!(
            "this osrt was built without the `cuda` feature: there are no CUDA kernels to compile"
        );
    }
    let precisions = match (a.precisions.clone(), a.device.is_cuda()) {
        (Some(p), false) if p.contains(&Precision::Bf16) => {
            bail!("--precisions bf16 needs a GPU (--device cuda): the CPU's kernels are f32 only")
        }
        (Some(p), _) => p,
        (None, true) => vec![Precision::F32, Precision::Bf16],
        (None, false) => vec![Precision::F32],
    };
    let device = a.device.open()?;
    let ops = osrt_kernels::device_check::compare_ops_with_cpu(&device)?;
    if !a.json {
        for c in &ops {
            println!(
                "op {:<32} value rel. {:.2e}, gradient rel. {:.2e}{}: {}",
                c.op,
                c.value_rel_max,
                c.gradient_rel_max,
                if c.finite { "" } else { ", NOT FINITE" },
                if c.pass { "ok" } else { "OUT OF TOLERANCE" }
            );
        }
    }
    // The staging, the memory pool and the context (cheap, and first: a broken one
    // explains failures further on).
    let pipes = plumbing(&device)?;
    if !a.json {
        for c in &pipes {
            let verdict = if c.pass { "ok" } else { "FAILED" };
            println!("plumbing {:<30} {}: {verdict}", c.check, c.detail);
        }
    }
    let mut all = Vec::new();
    for p in &a.presets {
        for &kernels in &a.kernels {
            for &precision in &precisions {
                let mut job = JobConfig::preset(p)?;
                job.train.device = a.device;
                job.train.precision = precision;
                job.train.kernels = kernels;
                let c = compare_with_cpu(p, &job, &device, a.image_size)?;
                if !a.json {
                    print_step(&c, kernels);
                }
                all.push((kernels, c));
            }
        }
    }
    if a.json {
        let steps: Vec<serde_json::Value> = all
            .iter()
            .map(|(k, c)| {
                let mut v = serde_json::to_value(c).expect("serialisable");
                v["kernels"] = k.to_string().into();
                v
            })
            .collect();
        let out = serde_json::json!({ "ops": ops, "plumbing": pipes, "steps": steps });
        println!("{}", serde_json::to_string_pretty(&out)?);
    } else {
        println!(
            "tolerances: op rel. ≤ {:e}; gradient rel. L2 ≤ {GRADIENT_TOLERANCE_F32:e} (f32), \
             ≤ {GRADIENT_TOLERANCE_BF16:e} (bf16); weights after a step ≤ {STEP_TOLERANCE:e}",
            osrt_kernels::device_check::OP_TOLERANCE
        );
    }
    if ops.iter().any(|c| !c.pass) || all.iter().any(|(_, c)| !c.pass) {
        bail!("the device's ops or step differ from the CPU's beyond the tolerances");
    }
    if let Some(c) = pipes.iter().find(|c| !c.pass) {
        bail!(
            "the device's plumbing failed a check: {}: {}",
            c.check,
            c.detail
        );
    }
    Ok(())
}

fn print_step(c: &DeviceCheck, kernels: Kernels) {
    println!(
        "{:<15} {:<8} {:<5} {} params: loss cpu {:.6} / {} {:.6}; gradient rel. L2 {:.2e} \
         (worst {} {:.2e}); weights after one step rel. {:.2e}: {}",
        c.preset,
        kernels,
        c.precision,
        c.parameters,
        c.loss_cpu,
        c.device,
        c.loss_device,
        c.gradient_rel_l2,
        c.worst_parameter,
        c.worst_parameter_rel_l2,
        c.step_rel_max,
        if c.pass { "ok" } else { "OUT OF TOLERANCE" }
    );
}
