//! `osrt bench model`: train-step time per preset at 1 and 2 threads, and render speed of
//! each decoder at 6 and 32 slots. Each thread count runs in its own child process (the
//! thread pools are sized once per process), and the parent prints and saves the union.

use anyhow::{Context, Result, bail};
use clap::Args;
use osrt_bench::model::{
    ModelReport, ProfileFigures, StepFigures, bench_render, bench_step, profile_step,
};
use osrt_kernels::{Kernels, Precision};
use osrt_run::MetricsRecord;
use osrt_trainer::{DeviceSpec, JobConfig};

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
    /// Run in this process only (used by the parent, which sets the thread environment).
    #[arg(long, hide = true)]
    pub child: bool,
    /// Where the model runs: cpu, or cuda / cuda:N (one process with every core; no
    /// composed-vs-fused comparison, the fused ops are CPU-only).
    #[arg(long, default_value = "cpu")]
    pub device: DeviceSpec,
    /// Matrix products in f32 or bf16 (GPU only).
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
        profiles: Vec::new(),
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

/// Saves benchmark figures (creating the folder) and returns the text.
pub fn save_json(path: &std::path::Path, value: &serde_json::Value) -> Result<String> {
    let text = serde_json::to_string_pretty(value)?;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(path, &text).with_context(|| format!("writing {}", path.display()))?;
    Ok(text)
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

/// One step's profile (`--profile`): op kinds, then the costliest distinct calls.
fn print_profile(p: &ProfileFigures) {
    let (fwd, bwd) = (p.forward_s, p.backward_s);
    println!(
        "  profile of {} (batch {}, {} view(s), {} rays, {} px) on {}, {}, {} kernels: \
         forward {:.1} ms, backward {:.1} ms (medians of the whole step's passes)",
        p.preset,
        p.batch_size,
        p.input_views,
        p.rays_per_scene,
        p.image_size,
        p.device,
        p.precision,
        p.kernels,
        fwd * 1e3,
        bwd * 1e3,
    );
    println!(
        "    {:<12} {:>6} {:>11} {:>11} {:>11} {:>9} {:>10} {:>14}",
        "op",
        "calls",
        "forward ms",
        "backward ms",
        "total ms",
        "% of step",
        "kept MiB",
        "largest peak"
    );
    let (step, mib) = (fwd + bwd, |b: f64| b / (1u64 << 20) as f64);
    let (mut sf, mut sb, mut sk) = (0.0, 0.0, 0.0);
    for k in &p.kinds {
        let (of, ob) = (k.forward_s, k.backward_s);
        let kept = k.kept_bytes.unwrap_or(0) as f64;
        (sf, sb, sk) = (sf + of, sb + ob, sk + kept);
        println!(
            "    {:<12} {:>6} {:>11.2} {:>11.2} {:>11.2} {:>8.1}% {:>10.1} {:>10.1} MiB",
            k.kind,
            k.calls,
            of * 1e3,
            ob * 1e3,
            (of + ob) * 1e3,
            100.0 * (of + ob) / step,
            mib(kept),
            mib(k.peak_bytes.unwrap_or(0) as f64),
        );
    }
    if let (Some(kept), Some(peak)) = (p.step_kept_bytes, p.step_peak_bytes) {
        println!(
            "    the step's forward pass left {:.1} MiB held (the batch and the graph), its \
             passes peaked {:.1} MiB above their start",
            mib(kept as f64),
            mib(peak as f64)
        );
    }
    println!(
        "    {:<12} {:>6} {:>11.2} {:>11.2} {:>11.2} {:>8.1}% {:>10.1}   (the rest: ops \
         between these, gradient accumulation)",
        "ops alone",
        "",
        sf * 1e3,
        sb * 1e3,
        (sf + sb) * 1e3,
        100.0 * (sf + sb) / step,
        mib(sk),
    );
    println!("    costliest calls (calls × (forward + backward); calls × kept):");
    for o in p.ops.iter().take(8) {
        let n = o.calls as f64;
        println!(
            "      {:>9.2} ms {:>9.1} MiB  {} × {}",
            n * (o.forward_s + o.backward_s) * 1e3,
            mib(n * o.kept_bytes.unwrap_or(0) as f64),
            n,
            o.signature
        );
    }
}

/// One step's figures of `osrt bench model`, for people.
fn print_step(s: &StepFigures) {
    let ms = |x: f64| x * 1e3;
    println!(
        "  train step {:<16} {:<8} {:>8.1} ms median ({:.1} scenes/s; fwd+bwd {:.1} ms; {} params, batch {}, {} view(s), {} rays, {}px, {} {}{})",
        s.preset,
        s.kernels,
        ms(s.median_step_s),
        s.scenes_per_s,
        ms(s.median_forward_backward_s),
        s.parameters,
        s.batch_size,
        s.input_views,
        s.rays_per_scene,
        s.image_size,
        s.device,
        s.precision,
        match (s.recompute, s.micro_batch_size) {
            (true, Some(m)) => format!(", activations recomputed, passes of {m}"),
            (true, None) => ", activations recomputed".into(),
            (false, Some(m)) => format!(", passes of {m}"),
            (false, None) => String::new(),
        },
    );
    let gib = |g: Option<f64>| match g {
        Some(g) => format!("{g:.2} GiB"),
        None => "not counted".into(),
    };
    println!(
        "    optimiser {:.1} ms median; peak heap {}, peak resident {}; estimated peak {}",
        ms(s.median_optimizer_s),
        gib(s.peak_heap_gib),
        gib(s.peak_rss_gib),
        gib(s.estimated_peak_gib),
    );
    if s.skipped_steps > 0 {
        println!(
            "    SKIPPED {} of the timed steps: {}",
            s.skipped_steps,
            s.skip_reason.as_deref().unwrap_or("")
        );
    }
    if s.peak_gib.is_some() {
        println!("    peak device memory {}", gib(s.peak_gib));
    }
    if s.median_gradient_transfer_s > 0.0 {
        println!(
            "    gradient device → host → device through the all-reduce's staging \
             (paid by each of ≥ 2 workers beside the ring, not in the step above): \
             {:.2} ms median ({:.1} % of the step)",
            ms(s.median_gradient_transfer_s),
            100.0 * s.median_gradient_transfer_s / s.median_step_s
        );
    }
    if let Some(e) = &s.gradient_transfer_error {
        println!("    GRADIENT ROUND TRIP FAILED: {e}");
    }
}

/// The figures of `osrt bench model`, for people.
fn print_model_report(a: &BenchModelArgs, report: &[(usize, ModelReport)]) {
    for (threads, v) in report {
        println!("{threads} thread(s):");
        for p in &v.profiles {
            print_profile(p);
        }
        for s in &v.steps {
            print_step(s);
        }
        for p in &a.presets {
            let t = |fused: bool| {
                v.steps
                    .iter()
                    .find(|s| &s.preset == p && s.fused == fused)
                    .map(|s| s.median_step_s)
            };
            if let (Some(f), Some(c)) = (t(true), t(false)) {
                println!("  {p}: fused ops make the step {:.2}× as fast", c / f);
            }
        }
        for r in &v.renders {
            println!(
                "  render {:<18} {:>3} slots {:>9.1} fps",
                r.decoder, r.slots, r.fps
            );
        }
        for &k in &a.slots {
            let fps = |d: &str| {
                v.renders
                    .iter()
                    .find(|r| r.decoder == d && r.slots == k)
                    .map(|r| r.fps)
            };
            if let (Some(sm), Some(sb)) = (fps("slot_mixer"), fps("spatial_broadcast")) {
                println!(
                    "  Slot Mixer / spatial broadcast at {k} slots: {:.1}×",
                    sm / sb
                );
            }
            if let (Some(sm), Some(v)) = (fps("slot_mixer"), fps("volumetric")) {
                println!("  Slot Mixer / volumetric at {k} slots: {:.1}×", sm / v);
            }
            if let (Some(v), Some(all)) = (fps("volumetric"), fps("volumetric_no_cull")) {
                println!("  box culling: volumetric {:.2}× as fast with it", v / all);
            }
        }
    }
}

#[derive(Args)]
pub struct BenchAllReduceArgs {
    /// Buffer sizes in floats.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "1000000,10000000,50000000"
    )]
    pub floats: Vec<usize>,
    /// Timed repeats per size (after one warm-up; sizes under 10 M floats get proportionally
    /// more, at most 20×); medians are reported.
    #[arg(long, default_value_t = 5)]
    pub repeats: usize,
    /// Floats per chunk (1024 to 262144: 4 KiB to 1 MiB).
    #[arg(long, default_value_t = osrt_proto::MAX_CHUNK_FLOATS, value_parser = crate::flags::chunk_floats)]
    pub chunk_floats: usize,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    /// Where the JSON figures are saved.
    #[arg(long, default_value = "target/bench/allreduce.json")]
    pub out: std::path::PathBuf,
}

pub async fn allreduce(a: BenchAllReduceArgs) -> Result<()> {
    crate::cluster::reexec_with_worker_allocator()?;
    let mut rows = Vec::new();
    for &n in &a.floats {
        rows.push(osrt_bench::allreduce::bench_allreduce(n, a.repeats, a.chunk_floats).await);
    }
    let text = save_json(&a.out, &serde_json::to_value(&rows)?)?;
    if a.json {
        println!("{text}");
        return Ok(());
    }
    println!(
        "ring all-reduce, 2 ranks over gRPC on loopback, vs bare TCP sockets copying the same \
         bytes in the same ring into message-sized buffers (the target's baseline) and the same \
         ring discarding what it reads:"
    );
    for r in &rows {
        println!(
            "  {:>10} floats: all-reduce {:>8.2} ms ({:.2} GB/s) | TCP ring {:>8.2} ms, ratio {:.2} (paired {:.2}, {} repeats) | TCP ring discarding {:>8.2} ms, ratio {:.2} (paired {:.2}) | busy cores: all-reduce {:.2} (user {:.2}), TCP ring {:.2}",
            r.floats,
            r.median_allreduce_s * 1e3,
            r.allreduce_gb_per_s,
            r.median_tcp_ring_s * 1e3,
            r.ratio,
            r.ratio_paired,
            r.repeats,
            r.median_tcp_ring_discard_s * 1e3,
            r.ratio_discard,
            r.ratio_discard_paired,
            r.allreduce_busy_cores,
            r.allreduce_user_cores,
            r.tcp_ring_busy_cores
        );
    }
    println!("saved to {}", a.out.display());
    Ok(())
}

#[derive(Args)]
pub struct BenchClusterArgs {
    /// Job preset to train.
    #[arg(long, default_value = "clevr-lite-cpu")]
    pub preset: String,
    /// Dataset (the default ./data is generated if absent, as by `osrt train`).
    #[arg(long, default_value = "data")]
    pub data: String,
    /// Steps per configuration; the first `--warmup` are not counted.
    #[arg(long, default_value_t = 40)]
    pub steps: u64,
    #[arg(long, default_value_t = 8)]
    pub warmup: u64,
    /// Configurations as WORKERSxTHREADS; one listed several times runs several times
    /// (in the order given), and its speed-ups use the median of its runs.
    #[arg(long, value_delimiter = ',', default_value = "1x1,1x2,2x1")]
    pub configs: Vec<String>,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
    /// Where the JSON figures are saved.
    #[arg(long, default_value = "target/bench/cluster.json")]
    pub out: std::path::PathBuf,
}

/// One local cluster's training throughput in `osrt bench cluster`.
#[derive(Debug, serde::Serialize)]
struct ClusterRow {
    config: String,
    workers: usize,
    threads: usize,
    median_scenes_per_s: f64,
}

/// What `osrt bench cluster` saves.
#[derive(Debug, serde::Serialize)]
struct ClusterReport {
    preset: String,
    steps: u64,
    warmup: u64,
    rows: Vec<ClusterRow>,
    speedup_2x1_over_1x1: Option<f64>,
    speedup_2x1_over_1x2: Option<f64>,
}

/// Training throughput of whole local clusters (`osrt train` in a child process per
/// configuration): the median of the logged global scenes/s after warm-up.
pub fn cluster(a: BenchClusterArgs) -> Result<()> {
    let exe = std::env::current_exe()?;
    let tmp = std::env::temp_dir().join(format!("osrt-bench-cluster-{}", std::process::id()));
    let mut rows = Vec::new();
    for (i, c) in a.configs.iter().enumerate() {
        let (w, t) = c
            .split_once('x')
            .and_then(|(w, t)| Some((w.parse::<usize>().ok()?, t.parse::<usize>().ok()?)))
            .with_context(|| format!("configuration `{c}`: expected WORKERSxTHREADS, e.g. 2x1"))?;
        // A configuration may be listed more than once (interleaved repeats on a noisy
        // machine): each run gets its own folder.
        let run = tmp.join(format!("{i}-{c}"));
        eprintln!(
            "training {} steps with {w} worker(s) × {t} thread(s)…",
            a.steps
        );
        let out = std::process::Command::new(&exe)
            .args(["train", "--preset", &a.preset, "--data", &a.data])
            .args(["--workers", &w.to_string(), "--threads", &t.to_string()])
            .args(["--max-steps", &a.steps.to_string(), "--eval-every-s", "1e9"])
            .arg("--run")
            .arg(&run)
            .output()
            .context("running osrt train")?;
        if !out.status.success() {
            bail!(
                "osrt train ({c}) failed:\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        let text = std::fs::read_to_string(run.join(osrt_run::METRICS_FILE))?;
        let sps: Vec<f64> = text
            .lines()
            .filter_map(|l| match MetricsRecord::parse(l)? {
                MetricsRecord::Train(r) if r.step > a.warmup => Some(r.scenes_per_s),
                _ => None,
            })
            .collect();
        if sps.is_empty() {
            bail!("no training records after warm-up for {c}: raise --steps");
        }
        let median = osrt_bench::median(sps);
        rows.push(ClusterRow {
            config: c.clone(),
            workers: w,
            threads: t,
            median_scenes_per_s: median,
        });
    }
    let _ = std::fs::remove_dir_all(&tmp);
    // Over repeated configurations: the median of their runs' medians.
    let base = |cfg: &str| {
        let runs: Vec<f64> = rows
            .iter()
            .filter(|r| r.config == cfg)
            .map(|r| r.median_scenes_per_s)
            .collect();
        (!runs.is_empty()).then(|| osrt_bench::median(runs))
    };
    let report = ClusterReport {
        preset: a.preset.clone(),
        steps: a.steps,
        warmup: a.warmup,
        speedup_2x1_over_1x1: base("2x1").zip(base("1x1")).map(|(x, y)| x / y),
        speedup_2x1_over_1x2: base("2x1").zip(base("1x2")).map(|(x, y)| x / y),
        rows,
    };
    let text = save_json(&a.out, &serde_json::to_value(&report)?)?;
    if a.json {
        println!("{text}");
        return Ok(());
    }
    println!("training throughput of local clusters ({}):", a.preset);
    for r in &report.rows {
        println!("  {:>4}: {:>7.2} scenes/s", r.config, r.median_scenes_per_s);
    }
    for (k, v) in [
        ("speedup_2x1_over_1x1", report.speedup_2x1_over_1x1),
        ("speedup_2x1_over_1x2", report.speedup_2x1_over_1x2),
    ] {
        if let Some(v) = v {
            println!("  {k}: {v:.2}×");
        }
    }
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
