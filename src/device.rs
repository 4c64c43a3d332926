//! `osrt check-device`: whether a GPU computes the CPU's train step (gradients and one
//! AdamW step on the same weights and batch), with the tolerances it is held to.

use anyhow::{Result, bail};
use clap::Args;
use osrt_model::Precision;
use osrt_trainer::check::{
    GRADIENT_TOLERANCE_BF16, GRADIENT_TOLERANCE_F32, STEP_TOLERANCE, compare_with_cpu,
};
use osrt_trainer::{DeviceSpec, JobConfig};

#[derive(Args)]
pub struct CheckDeviceArgs {
    /// The device compared with the CPU: cuda or cuda:N.
    #[arg(long, default_value = "cuda")]
    pub device: DeviceSpec,
    /// Job presets whose step is compared.
    #[arg(long, value_delimiter = ',', default_value = "tiny,clevr-lite-cpu")]
    pub presets: Vec<String>,
    /// Precisions of the device's matrix products (the CPU side is always f32).
    #[arg(long, value_delimiter = ',', default_value = "f32,bf16")]
    pub precisions: Vec<Precision>,
    /// Image size of the generated scenes.
    #[arg(long, default_value_t = 32)]
    pub image_size: u32,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: CheckDeviceArgs) -> Result<()> {
    let device = a.device.open()?;
    let mut all = Vec::new();
    for p in &a.presets {
        for &precision in &a.precisions {
            let mut job = JobConfig::preset(p)?;
            job.train.device = a.device;
            job.train.precision = precision;
            let c = compare_with_cpu(p, &job, &device, a.image_size)?;
            if !a.json {
                println!(
                    "{:<15} {:<5} {} params: loss cpu {:.6} / {} {:.6}; gradient rel. L2 {:.2e} \
                     (worst {} {:.2e}); weights after one step rel. {:.2e}: {}",
                    c.preset,
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
            all.push(c);
        }
    }
    if a.json {
        println!("{}", serde_json::to_string_pretty(&all)?);
    } else {
        println!(
            "tolerances: gradient rel. L2 ≤ {GRADIENT_TOLERANCE_F32:e} (f32), \
             ≤ {GRADIENT_TOLERANCE_BF16:e} (bf16); weights after a step ≤ {STEP_TOLERANCE:e}"
        );
    }
    if all.iter().any(|c| !c.pass) {
        bail!("the device's step differs from the CPU's beyond the tolerances");
    }
    Ok(())
}
