//! `osrt bench cluster`: the training throughput of whole local clusters, one `osrt
//! train` child process per configuration of workers and threads.

use super::save_json;
use anyhow::{Context, Result, bail};
use clap::Args;
use osrt_run::MetricsRecord;

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
