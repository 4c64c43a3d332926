//! `osrt bench model`: train-step time per preset at 1 and 2 threads, and render speed of
//! each decoder at 6 and 32 slots. Each thread count runs in its own child process (the
//! thread pools are sized once per process), and the parent prints and saves the union.

mod ledger;
mod report;

use super::save_json;
use anyhow::{Context, Result, bail};
use clap::Args;
use osrt_bench::model::{ModelReport, bench_render, bench_step, ledger_step, profile_step};
use osrt_kernels::{Kernels, Precision};
use osrt_trainer::{JobConfig, device::DeviceSpec};
use report::print_model_report;

#[derive(Args)]
pub struct BenchModelArgs {
    /// Job presets whose train step is timed.
    #[arg(long, value_delimiter = ',', default_value = "clevr-lite-cpu")]
    pub presets: Vec<String>,
    /// Image size of the benchmark scenes.
    #[arg(long, default_value_t = 32)]
    pub image_size: u32,
    /// Timed steps (after one warm-up); the median is reported.
    #[arg(long, default_value_t = 10)]
    pub steps: usize,
    /// Slot counts for the render benchmark.
    #[arg(long, value_delimiter = ',', default_value = "6,32")]
    pub slots: Vec<usize>,
    /// Thread counts, one child process each.
    #[arg(long, value_delimiter = ',', default_value = "1,2", value_parser = crate::flags::threads)]
    pub threads: Vec<usize>,
    /// Time only the train step with the fused ops (no composed step, no renders): the
    /// quick figure, and the loop to profile.
    #[arg(long)]
    pub step_only: bool,
    /// Time only the renders (no train steps): the loop for render A/B comparisons.
    #[arg(long, conflicts_with = "step_only")]
    pub render_only: bool,
    /// Print the time of each op kind of the train step, forward and backward: one step's
    /// op calls recorded, then each distinct call timed alone (synchronised), beside the
    /// step's own passes (no renders, no composed-vs-fused comparison).
    #[arg(long, conflicts_with = "render_only")]
    pub profile: bool,
    /// Print the ledger of one train step: every matrix product (shape, operand and output
    /// types, transposes, copies), cast, copy and other op's bytes, per op kind, with the
    /// time each would take at an H200's rates (runs on any device; no timing).
    #[arg(long, conflicts_with_all = ["render_only", "profile"])]
    pub ledger: bool,
    /// Run in this process only (used by the parent, which sets the thread environment).
    #[arg(long, hide = true)]
    pub child: bool,
    /// Where the model runs: cpu, or cuda / cuda:N (one process with every core; no
    /// composed-vs-fused comparison, the fused ops are CPU-only).
    #[arg(long, default_value = "cpu")]
    pub device: DeviceSpec,
    /// Matrix products in f32 or bf16 (on a GPU, or the CPU's AMX / AVX512-BF16 units).
    #[arg(long, default_value = "f32")]
    pub precision: Precision,
    /// Time the step with these kernels only (default: fused, and composed beside it for
    /// the fused ops' speed-up unless --step-only or a GPU).
    #[arg(long)]
    pub kernels: Option<Kernels>,
    /// Make the transformer blocks' and convolutions' activations again in the backward
    /// pass instead of keeping them (`train.recompute`).
    #[arg(long)]
    pub recompute: bool,
    /// Override the presets' scenes per step.
    #[arg(long)]
    pub batch_size: Option<usize>,
    /// Run the step's scenes in passes of at most this many (`train.micro_batch_size`).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub micro_batch_size: Option<u64>,
    /// Override the presets' input views.
    #[arg(long)]
    pub input_views: Option<usize>,
    /// Override the presets' target rays per scene.
    #[arg(long)]
    pub rays_per_scene: Option<usize>,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    /// Where the JSON figures are saved.
    #[arg(long, default_value = "target/bench/model.json")]
    pub out: std::path::PathBuf,
}

/// `name value` where a value is given.
fn flag(name: &str, value: Option<impl ToString>) -> Vec<String> {
    value
        .map(|v| vec![name.to_string(), v.to_string()])
        .unwrap_or_default()
}

/// A preset with the command line's overrides.
fn bench_job(a: &BenchModelArgs, preset: &str) -> Result<JobConfig> {
    let mut job = JobConfig::preset(preset)?;
    let t = &mut job.train;
    t.batch_size = a.batch_size.unwrap_or(t.batch_size);
    if let Some(m) = a.micro_batch_size {
        t.micro_batch_size = Some(usize::try_from(m).unwrap_or(usize::MAX));
    }
    t.input_views = a.input_views.unwrap_or(t.input_views);
    t.rays_per_scene = a.rays_per_scene.unwrap_or(t.rays_per_scene);
    t.device = a.device;
    t.precision = a.precision;
    if let Some(k) = a.kernels {
        t.kernels = k;
    }
    t.recompute = a.recompute;
    job.validate()?;
    Ok(job)
}

fn measure(a: &BenchModelArgs) -> Result<ModelReport> {
    let device = a.device.open()?;
    if a.ledger {
        let mut ledgers = Vec::new();
        for p in &a.presets {
            let mut job = bench_job(a, p)?;
            job.train.kernels = a.kernels.unwrap_or_default();
            ledgers.push(ledger_step(p, &job, a.image_size, &device)?);
        }
        return Ok(ModelReport {
            ledgers,
            ..ModelReport::default()
        });
    }
    if a.profile {
        let mut profiles = Vec::new();
        for p in &a.presets {
            let mut job = bench_job(a, p)?;
            job.train.kernels = a.kernels.unwrap_or_default();
            profiles.push(profile_step(p, &job, a.image_size, a.steps, 3, &device)?);
        }
        return Ok(ModelReport {
            profiles,
            ..ModelReport::default()
        });
    }
    let mut steps = Vec::new();
    let presets: &[String] = if a.render_only { &[] } else { &a.presets };
    for p in presets {
        let job = bench_job(a, p)?;
        // The same step with candle's composed ops, for the fused ops' speed-up.
        let variants: &[Kernels] = match a.kernels {
            Some(Kernels::Fused) => &[Kernels::Fused],
            Some(Kernels::Composed) => &[Kernels::Composed],
            Some(Kernels::Device) => &[Kernels::Device],
            None if a.step_only || a.device.is_cuda() => &[Kernels::Fused],
            None => &[Kernels::Fused, Kernels::Composed],
        };
        for &kernels in variants {
            let mut job = job.clone();
            job.train.kernels = kernels;
            steps.push(bench_step(p, &job, a.image_size, a.steps, &device)?);
        }
    }
    let model = JobConfig::preset(&a.presets[0])?.model;
    let mut renders = Vec::new();
    let slots: &[usize] = if a.step_only { &[] } else { &a.slots };
    for &k in slots {
        for d in osrt_bench::model::RENDER_DECODERS {
            let kernels = a.kernels.unwrap_or_default();
            renders.push(osrt_kernels::with_kernels(kernels, || {
                bench_render(&model, d, k, a.image_size, 5, &device)
            })?);
        }
    }
    Ok(ModelReport {
        steps,
        renders,
        ..ModelReport::default()
    })
}

/// How a benchmark child ended, for people: a SIGKILL, which leaves no message of its
/// own, is most likely the kernel's out-of-memory killer.
fn child_exit(status: std::process::ExitStatus) -> String {
    use std::os::unix::process::ExitStatusExt;
    match status.signal() {
        Some(9) => {
            let machine = osrt_trainer::footprint::machine_memory(DeviceSpec::Cpu)
                .map_or(String::new(), |(b, what)| {
                    format!(" ({what}: {:.2} GiB)", b / (1u64 << 30) as f64)
                });
            format!(
                "killed by SIGKILL: most likely the kernel's out-of-memory killer{machine}; \
                 a smaller case (--batch-size, --rays-per-scene, --image-size, --step-only to \
                 skip the whole-view renders) fits in less"
            )
        }
        Some(s) => format!("killed by signal {s}"),
        None => status.to_string(),
    }
}

pub fn run(a: BenchModelArgs) -> Result<()> {
    // Measure with the allocator settings the local launcher gives its workers (fewer
    // fresh pages per step: ~1.4x on this step); children inherit them.
    crate::cluster::reexec_with_worker_allocator()?;
    if a.child {
        println!("{}", serde_json::to_string(&measure(&a)?)?);
        return Ok(());
    }
    let exe = std::env::current_exe()?;
    let mut by_threads: Vec<(usize, ModelReport)> = Vec::new();
    // A GPU benchmark runs once, with every core for the host's share of the step.
    let threads = if a.device.is_cuda() {
        vec![std::thread::available_parallelism().map_or(1, |n| n.get())]
    } else {
        a.threads.clone()
    };
    for &n in &threads {
        eprintln!("benchmarking with {n} thread(s)…");
        let mut cmd = std::process::Command::new(&exe);
        cmd.args([
            "bench",
            "model",
            "--child",
            "--image-size",
            &a.image_size.to_string(),
            "--steps",
            &a.steps.to_string(),
        ])
        .args(a.step_only.then_some("--step-only"))
        .args(a.render_only.then_some("--render-only"))
        .args(a.profile.then_some("--profile"))
        .args(a.ledger.then_some("--ledger"))
        .args(a.recompute.then_some("--recompute"))
        .args(["--device", &a.device.to_string()])
        .args(["--precision", &a.precision.to_string()])
        .args(
            a.kernels
                .iter()
                .flat_map(|k| ["--kernels".to_string(), k.to_string()]),
        )
        .args(flag("--batch-size", a.batch_size))
        .args(flag("--micro-batch-size", a.micro_batch_size))
        .args(
            a.input_views
                .iter()
                .flat_map(|v| ["--input-views".to_string(), v.to_string()]),
        )
        .args(
            a.rays_per_scene
                .iter()
                .flat_map(|v| ["--rays-per-scene".to_string(), v.to_string()]),
        )
        .arg("--presets")
        .arg(a.presets.join(","))
        .arg("--slots")
        .arg(
            a.slots
                .iter()
                .map(|s| s.to_string())
                .collect::<Vec<_>>()
                .join(","),
        )
        .envs(crate::cluster::compute_thread_env(n));
        // Asked for a log (`RUST_LOG`, e.g. the train step's phases at debug level), the
        // child writes it where this process does; otherwise its messages are kept for
        // the error below.
        let logging = std::env::var_os("RUST_LOG").is_some();
        if logging {
            cmd.stderr(std::process::Stdio::inherit());
        }
        let out = cmd.output().context("running the benchmark child")?;
        if !out.status.success() {
            bail!(
                "benchmark child ({n} threads) failed ({}):\n{}",
                child_exit(out.status),
                match logging {
                    true => "its log is above".into(),
                    false => String::from_utf8_lossy(&out.stderr),
                }
            );
        }
        let v: ModelReport =
            serde_json::from_slice(&out.stdout).context("reading the benchmark child's figures")?;
        by_threads.push((n, v));
    }
    let mut saved = serde_json::Map::new();
    for (n, v) in &by_threads {
        saved.insert(n.to_string(), serde_json::to_value(v)?);
    }
    let text = save_json(&a.out, &serde_json::Value::Object(saved))?;
    if a.json {
        println!("{text}");
        return Ok(());
    }
    print_model_report(&a, &by_threads);
    println!("saved to {}", a.out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::child_exit;
    use std::os::unix::process::ExitStatusExt;

    /// A child killed without a word is named: SIGKILL as the likely out-of-memory kill,
    /// other signals by number, exit codes as such.
    #[test]
    fn a_child_that_dies_silently_is_named() {
        let killed = child_exit(std::process::ExitStatus::from_raw(9));
        assert!(
            killed.contains("SIGKILL") && killed.contains("out-of-memory"),
            "{killed}"
        );
        let segv = child_exit(std::process::ExitStatus::from_raw(11));
        assert_eq!(segv, "killed by signal 11");
        let code = child_exit(std::process::ExitStatus::from_raw(3 << 8));
        assert!(code.contains('3'), "{code}");
    }
}
