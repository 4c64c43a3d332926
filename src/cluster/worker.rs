//! `osrt worker`, with its flags, and the environment a worker process computes in: the
//! allocator settings and thread counts, applied by re-executing the process.

use super::{health_listener, shutdown_signal};
use anyhow::{Context, Result};
use clap::Args;
use osrt_proto::credentials::Credentials;
use osrt_trainer::device::DeviceSpec;
use osrt_worker::{WorkerOptions, run_worker_until};
use std::net::SocketAddr;
use std::time::Duration;

/// glibc allocator settings for workers: keep freed tensors' pages instead of returning
/// them to the kernel after every step (page faults were 5–10 % of a step).
pub const WORKER_MALLOC_ENV: [(&str, &str); 3] = [
    ("MALLOC_MMAP_THRESHOLD_", "33554432"),
    ("MALLOC_TRIM_THRESHOLD_", "4294967296"),
    ("MALLOC_TOP_PAD_", "268435456"),
];

#[derive(Args)]
pub struct WorkerArgs {
    /// `http://host:port` of the coordinator.
    #[arg(long, env = "OSRT_COORDINATOR")]
    pub coordinator: String,
    /// Address of this worker's Collective service.
    #[arg(long, default_value = "0.0.0.0:7071", env = "OSRT_WORKER_LISTEN")]
    pub listen: SocketAddr,
    /// Also answer the gRPC health service in plaintext here (for probes that cannot
    /// speak TLS, such as the kubelet's).
    #[arg(long, env = "OSRT_HEALTH_LISTEN")]
    pub health_listen: Option<SocketAddr>,
    /// Host name the other workers reach this one at (a pod's stable DNS name).
    #[arg(long, env = "OSRT_ADVERTISE")]
    pub advertise: Option<String>,
    /// Compute threads (candle's pool); the process re-executes itself to apply it.
    #[arg(long, env = "OSRT_THREADS", value_parser = crate::flags::threads)]
    pub threads: Option<usize>,
    /// Join a job even where its step's estimated peak memory exceeds this machine's.
    #[arg(long, env = "OSRT_SKIP_MEMORY_CHECK")]
    pub skip_memory_check: bool,
    /// Where this worker computes: cpu, cuda or cuda:N (default: the job config's
    /// `train.device`). Each worker owns one GPU.
    #[arg(long, env = "OSRT_DEVICE")]
    pub device: Option<DeviceSpec>,
    /// Give up after the coordinator has been unreachable this many seconds (positive,
    /// at most a year).
    #[arg(long, default_value_t = 60.0, value_parser = crate::flags::positive_seconds)]
    pub coordinator_timeout_s: f64,
}

/// The thread settings of a process that computes with `n` threads: rayon's pools (gemm,
/// our fused ops, the pool candle runs the step in) get `n`; candle's separate barrier
/// pool for elementwise ops gets no workers beside the calling thread, unless the user
/// set `CANDLE_NUM_THREADS`. Those workers spin after every op (25,000 rounds by default)
/// and took a core from gemm's rayon threads: at 2 threads the step took 1.15–1.27× as
/// long with them in interleaved runs (docs/performance.md).
pub fn compute_thread_env(n: usize) -> [(&'static str, String); 2] {
    let candle = std::env::var("CANDLE_NUM_THREADS").unwrap_or_else(|_| "1".into());
    [
        ("RAYON_NUM_THREADS", n.to_string()),
        ("CANDLE_NUM_THREADS", candle),
    ]
}

/// Replaces this process by itself with the workers' allocator settings unless they are
/// set, so a benchmark measures what workers run with.
pub fn reexec_with_worker_allocator() -> Result<()> {
    if WORKER_MALLOC_ENV
        .iter()
        .all(|(k, _)| std::env::var_os(k).is_some())
    {
        return Ok(());
    }
    reexec_with(WORKER_MALLOC_ENV, "with the workers' allocator settings")
}

/// Replaces this process by itself, same arguments, with `env` added; returns only if
/// that fails.
fn reexec_with<K, V>(env: impl IntoIterator<Item = (K, V)>, what: &str) -> Result<()>
where
    K: AsRef<std::ffi::OsStr>,
    V: AsRef<std::ffi::OsStr>,
{
    use std::os::unix::process::CommandExt;
    let err = std::process::Command::new(std::env::current_exe()?)
        .args(std::env::args_os().skip(1))
        .envs(env)
        .exec();
    Err(err).with_context(|| format!("re-executing {what}"))
}

/// Replaces this process by itself with [`compute_thread_env`]`(n)` unless already set so:
/// candle sizes its thread pools from it once, at its first parallel op. `exec` keeps the
/// process id, so signals (a pod's SIGTERM, a test's SIGKILL) still reach the worker.
fn reexec_with_threads(n: usize) -> Result<()> {
    let env = compute_thread_env(n);
    if env
        .iter()
        .all(|(k, v)| std::env::var(k).ok().as_deref() == Some(v.as_str()))
    {
        return Ok(());
    }
    reexec_with(env, "the worker with its thread count")
}

pub async fn worker(a: WorkerArgs) -> Result<()> {
    if let Some(n) = a.threads {
        reexec_with_threads(n)?;
    }
    let credentials = Credentials::from_env()?;
    let threads = std::env::var("RAYON_NUM_THREADS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| {
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        });
    let host = std::env::var("HOSTNAME").unwrap_or_else(|_| "localhost".into());
    health_listener(a.health_listen).await?;
    run_worker_until(
        WorkerOptions {
            coordinator: a.coordinator,
            listen: a.listen,
            advertise: a.advertise,
            threads,
            device: a.device,
            credentials,
            name: format!("{host}:{}", std::process::id()),
            coordinator_timeout: Duration::from_secs_f64(a.coordinator_timeout_s),
            memory_check: !a.skip_memory_check,
        },
        shutdown_signal(),
    )
    .await?;
    Ok(())
}
