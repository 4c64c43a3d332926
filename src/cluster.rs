//! `osrt coordinator`, `osrt worker`, and the local launcher behind `osrt train`: a
//! coordinator in this process and N worker processes of this same binary on loopback,
//! started with exactly the flags and environment a cluster's pods use.

use anyhow::{Context, Result, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use osrt_coordinator::{Coordinator, JobSpec, OpenOptions};
use osrt_proto::auth::{TOKEN_ENV, Token};
use osrt_proto::tls::Tls;
use osrt_proto::v1;
use osrt_run::ClusterOverrides;
use osrt_run::MetricsRecord;
use osrt_run::unix_now;
use osrt_trainer::{DeviceSpec, JobConfig};
use osrt_worker::{WorkerOptions, run_worker_until};
use std::io::IsTerminal;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

/// glibc allocator settings for workers: keep freed tensors' pages instead of returning
/// them to the kernel after every step (page faults were 5–10 % of a step).
pub const WORKER_MALLOC_ENV: [(&str, &str); 3] = [
    ("MALLOC_MMAP_THRESHOLD_", "33554432"),
    ("MALLOC_TRIM_THRESHOLD_", "4294967296"),
    ("MALLOC_TOP_PAD_", "268435456"),
];

#[derive(Args)]
pub struct CoordinatorArgs {
    /// Job config (TOML, a full `JobConfig`); default: the `--preset`.
    #[arg(long, env = "OSRT_CONFIG")]
    pub config: Option<PathBuf>,
    /// Named job preset when no --config is given: clevr-lite-cpu, clevr-lite-gpu, tiny,
    /// paper, clevr3d, msn-hard (the paper's settings for those datasets).
    #[arg(long, env = "OSRT_PRESET", default_value = "clevr-lite-cpu")]
    pub preset: String,
    /// Dataset directory or URL (read by the workers).
    #[arg(long, env = "OSRT_DATA")]
    pub data: String,
    /// Run folder or URL: config, metrics, job state and checkpoints.
    #[arg(long, env = "OSRT_RUN")]
    pub run: String,
    /// Address the Coordinator service listens on.
    #[arg(long, env = "OSRT_LISTEN", default_value = "0.0.0.0:7070")]
    pub listen: SocketAddr,
    /// Also answer the gRPC health service in plaintext here (for probes that cannot
    /// speak TLS, such as the kubelet's).
    #[arg(long, env = "OSRT_HEALTH_LISTEN")]
    pub health_listen: Option<SocketAddr>,
    #[arg(long, env = "OSRT_MAX_STEPS")]
    pub max_steps: Option<u64>,
    /// Stop after this many minutes of wall-clock time (positive, finite, at most a year).
    #[arg(long, env = "OSRT_MAX_MINUTES", value_parser = crate::flags::minutes)]
    pub max_minutes: Option<f64>,
    /// Continue the job in --run (a finished one too) with the limits given here.
    #[arg(long, env = "OSRT_RESUME")]
    pub resume: bool,
    /// Take the run folder from a coordinator known to be dead without waiting to see
    /// that its lease is not renewed (a live one is otherwise refused).
    #[arg(long, env = "OSRT_TAKE_OVER")]
    pub take_over: bool,
    /// Override cluster.min_workers / max_workers / max_restarts of the config.
    #[arg(long, env = "OSRT_MIN_WORKERS", value_parser = crate::flags::workers)]
    pub min_workers: Option<usize>,
    #[arg(long, env = "OSRT_MAX_WORKERS", value_parser = crate::flags::workers)]
    pub max_workers: Option<usize>,
    #[arg(long, env = "OSRT_MAX_RESTARTS")]
    pub max_restarts: Option<u32>,
    /// Seconds to keep answering after the job is over, so every worker hears it (a
    /// Deployment sets it long: its pod must not exit and be restarted). At most a year.
    #[arg(long, env = "OSRT_LINGER_S", default_value_t = 3.0, value_parser = crate::flags::seconds)]
    pub linger_s: f64,
}

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

fn job_id() -> String {
    format!("job-{}", &Token::generate().as_str()[..12])
}

/// A relative local path made absolute against the current directory (URLs and absolute
/// paths unchanged): the run records where its data is, and `osrt eval`, `render` and
/// `report` read that record later, from wherever they are started. "URL" by the same
/// rule as `Location::parse`: anything with `://`.
fn absolute_local(data: &str) -> Result<String> {
    let path = std::path::Path::new(data);
    if data.contains("://") || path.is_absolute() {
        return Ok(data.to_string());
    }
    let cwd = std::env::current_dir().context("resolving the dataset path")?;
    Ok(cwd.join(path).to_string_lossy().into_owned())
}

/// What [`memory_check`] may do about a job that does not fit.
#[derive(Debug, Clone, Copy, Default)]
pub struct MemoryCheck {
    /// Run it anyway (`--skip-memory-check`).
    pub skip: bool,
    /// Give a job without `train.micro_batch_size` the largest micro-batch that fits.
    pub pick_micro_batch: bool,
}

/// Prints the estimated peak memory of one worker's step (`world` workers, `threads`
/// threads each) on the dataset's images, and refuses a job whose `here` workers on this
/// machine need more memory than it has, unless `check.skip` — or, with
/// `check.pick_micro_batch`, runs its share in the largest micro-batches that fit (and
/// says so). Only the fused CPU step's estimate is checked against measured peaks
/// (`tests/memory_estimate.rs`): for the others an excess is a warning.
pub async fn memory_check(
    job: &mut JobConfig,
    data: &str,
    (here, world): (usize, usize),
    threads: usize,
    check: MemoryCheck,
) -> Result<()> {
    let skip = check.skip;
    let Ok(manifest) = osrt_dataset::Manifest::read(&osrt_store::Location::parse(data)?).await
    else {
        // The workers report a missing or unreadable dataset with its reason.
        return Ok(());
    };
    let image = manifest.image_size;
    let Some(mut m) = osrt_trainer::footprint::estimate(job, image, world, threads) else {
        eprintln!("no memory estimate for this model (a volumetric decoder)");
        return Ok(());
    };
    eprintln!("{}", m.describe());
    if here == 0 {
        return Ok(());
    }
    let micro = osrt_trainer::footprint::micro_batch_that_fits(job, image, world, threads, here);
    if let Some(size) = micro.filter(|_| check.pick_micro_batch && !skip)
        && job.train.micro_batch_size.is_none()
    {
        job.train.micro_batch_size = Some(size);
        m = osrt_trainer::footprint::estimate(job, image, world, threads).unwrap_or(m);
        eprintln!(
            "a worker's share of {} scenes does not fit in one pass: micro-batches of {size} \
             (--micro-batch-size {size}; the same step, one all-reduce): {}",
            m.share,
            m.describe()
        );
    }
    match osrt_trainer::footprint::fit_here(&m, here, micro) {
        Ok(None) => Ok(()),
        Ok(Some(why)) => {
            eprintln!("warning: {why}");
            Ok(())
        }
        Err(why) if skip => {
            eprintln!("warning (--skip-memory-check): {why}");
            Ok(())
        }
        Err(why) => bail!("{why}"),
    }
}

/// The job as the coordinator receives it, the command line's overrides applied; a
/// volumetric decoder's scene box, unless the job sets one, is read from the dataset's
/// manifest here, so the run's saved config carries it.
pub async fn spec(
    mut job: JobConfig,
    data: &str,
    run: &str,
    max_steps: Option<u64>,
    max_minutes: Option<f64>,
) -> Result<JobSpec> {
    if let osrt_model::decoder::Config::Volumetric(v) = &job.model.decoder
        && v.bounds.is_none()
    {
        let manifest = osrt_dataset::Manifest::read(&osrt_store::Location::parse(data)?)
            .await
            .with_context(|| format!("reading the manifest of {data} for the scene's box"))?;
        job.resolve_scene_bounds(&manifest, data)?;
    }
    job.validate()?;
    // The flags are checked as they are parsed; a sweep file's budget arrives here.
    if let Some(m) = max_minutes {
        crate::flags::check_minutes(m).map_err(|why| anyhow::anyhow!("max_minutes {why}"))?;
    }
    Ok(JobSpec {
        job_id: job_id(),
        job_toml: job.to_toml(),
        cluster: job.cluster,
        data: absolute_local(data)?,
        run: run.to_string(),
        max_steps,
        deadline_unix_s: max_minutes.map(|m| unix_now() + m * 60.0),
        cluster_overrides: ClusterOverrides::default(),
    })
}

pub async fn coordinator(a: CoordinatorArgs) -> Result<()> {
    let token = Token::from_env()?;
    let mut job = JobConfig::load_or_preset(a.config.as_deref(), &a.preset)?;
    let overrides = ClusterOverrides {
        min_workers: a.min_workers,
        max_workers: a.max_workers,
        max_restarts: a.max_restarts,
    };
    overrides.apply(&mut job.cluster);
    if a.max_steps.is_none() && a.max_minutes.is_none() && !a.resume {
        bail!("give the job a limit: --max-steps N and/or --max-minutes M");
    }
    // Probes see a live process from the start: opening the run folder may watch a lease
    // for 15 s and verify checkpoints for a while before the main port is served.
    health_listener(a.health_listen).await?;
    // The workers' machines are not known here: the figure only, at one thread each.
    let world = job.cluster.min_workers.max(1);
    let figure_only = MemoryCheck {
        skip: true,
        pick_micro_batch: false,
    };
    memory_check(&mut job, &a.data, (0, world), 1, figure_only).await?;
    let mut spec = spec(job, &a.data, &a.run, a.max_steps, a.max_minutes).await?;
    spec.cluster_overrides = overrides;
    let opts = OpenOptions {
        resume: a.resume,
        take_over: a.take_over,
        ..Default::default()
    };
    let coord = Coordinator::open_with(spec, opts).await?;
    let listener = tokio::net::TcpListener::bind(a.listen)
        .await
        .with_context(|| format!("listening on {}", a.listen))?;
    eprintln!(
        "coordinator of {} listening on {}",
        coord.job_id(),
        listener.local_addr()?
    );
    let status = coord
        .serve(
            listener,
            token,
            Tls::from_env()?,
            Duration::from_secs_f64(a.linger_s),
            shutdown_signal(),
        )
        .await?;
    report_end(&status)
}

/// Starts the plaintext health listener where `--health-listen` asks for one.
async fn health_listener(addr: Option<SocketAddr>) -> Result<()> {
    if let Some(addr) = addr {
        let local = osrt_proto::health::spawn_plaintext(addr)
            .await
            .with_context(|| format!("health listener on {addr}"))?;
        eprintln!("plaintext health service on {local}");
    }
    Ok(())
}

/// SIGINT (Ctrl-C) or SIGTERM (what Kubernetes sends a pod it stops).
async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {}
                    _ = term.recv() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    let _ = tokio::signal::ctrl_c().await;
}

fn report_end(status: &v1::JobStatus) -> Result<()> {
    match v1::JobState::try_from(status.state) {
        Ok(v1::JobState::Done) => {
            eprintln!(
                "job {} done: final checkpoint at step {}, {} restarts, {} parameter-hash checks agreed",
                status.job,
                status.last_checkpoint.unwrap_or(0),
                status.restarts,
                status.hash_checks
            );
            Ok(())
        }
        Ok(v1::JobState::Failed) => bail!("job {} failed: {}", status.job, status.message),
        _ => bail!("job {} interrupted (state {:?})", status.job, status.state),
    }
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
    let token = Token::from_env()?;
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
            token,
            tls: Tls::from_env()?,
            name: format!("{host}:{}", std::process::id()),
            coordinator_timeout: Duration::from_secs_f64(a.coordinator_timeout_s),
            memory_check: !a.skip_memory_check,
        },
        shutdown_signal(),
    )
    .await?;
    Ok(())
}

/// What `osrt train` runs: a local cluster of `workers` processes.
pub struct LocalJob {
    pub spec: JobSpec,
    pub workers: usize,
    pub threads_per_worker: usize,
    /// The workers join whatever their estimated memory (`--skip-memory-check`).
    pub skip_memory_check: bool,
    /// `--resume`, `--take-over`.
    pub open: OpenOptions,
}

fn spawn_worker(
    coordinator: &str,
    (threads, skip_memory_check): (usize, bool),
    device: DeviceSpec,
    token: &Token,
) -> Result<tokio::process::Child> {
    let mut cmd = tokio::process::Command::new(std::env::current_exe()?);
    cmd.args([
        "worker",
        "--coordinator",
        coordinator,
        "--listen",
        "127.0.0.1:0",
        "--threads",
        &threads.to_string(),
    ]);
    if device.is_cuda() {
        cmd.args(["--device", &device.to_string()]);
    }
    cmd.env(TOKEN_ENV, token.as_str())
        .envs(compute_thread_env(threads))
        .kill_on_drop(true);
    if skip_memory_check {
        cmd.env("OSRT_SKIP_MEMORY_CHECK", "true");
    }
    for (k, v) in WORKER_MALLOC_ENV {
        if std::env::var_os(k).is_none() {
            cmd.env(k, v);
        }
    }
    Ok(cmd.spawn()?)
}

/// Where the job was when a worker was killed: at a step, or setting a generation up
/// from a checkpoint (the heartbeats' step is 0 then, whatever the job's step).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Point {
    Step(u64),
    Setup(Option<u64>),
}

impl Point {
    /// The point of the job's status: its ranks' step, or during a generation's set-up
    /// (step 0), the checkpoint the generation starts from.
    fn of(step: u64, last_checkpoint: Option<u64>) -> Self {
        if step > 0 {
            Point::Step(step)
        } else {
            Point::Setup(last_checkpoint)
        }
    }
}

impl std::fmt::Display for Point {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Point::Step(s) => write!(f, "at step {s}"),
            Point::Setup(Some(c)) => write!(f, "while setting up from checkpoint {c}"),
            Point::Setup(None) => write!(f, "while setting up the job's first step"),
        }
    }
}

/// One local worker slot's SIGKILLs: a worker killed twice at the same point of the job
/// (the kernel's out-of-memory killer, most likely: it kills with SIGKILL) would be
/// killed again however often it is replaced.
#[derive(Default)]
struct Kills {
    /// Where the job was when this slot's worker was last killed.
    at: Option<Point>,
    /// The worker's resident memory when last sampled, in MiB.
    rss_mb: Option<f64>,
}

impl Kills {
    /// Samples the running worker's resident memory (Linux: `VmRSS`).
    fn sample(&mut self, child: &tokio::process::Child) {
        let rss = child.id().and_then(|pid| {
            let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
            let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
            line.split_whitespace().nth(1)?.parse::<f64>().ok()
        });
        if let Some(kib) = rss {
            self.rss_mb = Some(kib / 1024.0);
        }
    }

    /// Why the job must end, where worker `k`'s `exit` is its second SIGKILL at `at`.
    fn killed_again(
        &mut self,
        k: usize,
        exit: std::process::ExitStatus,
        at: Point,
    ) -> Option<String> {
        use std::os::unix::process::ExitStatusExt;
        if exit.signal() != Some(9) {
            self.at = None;
            return None;
        }
        if self.at.replace(at) != Some(at) {
            return None;
        }
        let rss = self.rss_mb.map_or(String::new(), |mb| {
            format!(", last seen at {:.2} GiB resident", mb / 1024.0)
        });
        let machine = osrt_trainer::footprint::machine_memory(DeviceSpec::Cpu)
            .map_or(String::new(), |(b, what)| {
                format!(" ({what}: {:.2} GiB)", b / (1u64 << 30) as f64)
            });
        Some(format!(
            "worker {k} was killed by SIGKILL twice {at}{rss}{machine}: the kernel's \
             out-of-memory killer, most likely, and a replacement would meet the same end. \
             Make the step smaller (--recompute, --batch-size, --rays-per-scene, fewer workers, smaller \
             images: osrt data import --resize) or run on a machine with more memory"
        ))
    }
}

/// The replacements of exited workers the launcher has started, and how many it may.
struct Replacements<'a> {
    used: &'a mut u32,
    max: u32,
}

/// Replaces each local worker that exited while the job runs (as a Job controller
/// would), or fails the job where a replacement would be killed the same way; an error
/// once the replacements are used up.
fn replace_exited(
    children: &mut [tokio::process::Child],
    kills: &mut [Kills],
    (coord, at): (&Coordinator, Point),
    r: Replacements,
    spawn: impl Fn(usize) -> Result<tokio::process::Child>,
) -> Result<()> {
    for (k, child) in children.iter_mut().enumerate() {
        let Ok(Some(exit)) = child.try_wait() else {
            continue;
        };
        if let Some(why) = kills[k].killed_again(k, exit, at) {
            coord.fail(why);
            return Ok(());
        }
        if *r.used >= r.max {
            bail!(
                "worker exited ({exit}) and {} replacements are used up",
                r.max
            );
        }
        tracing::warn!(%exit, "worker exited; starting a replacement");
        *child = spawn(k)?;
        *r.used += 1;
    }
    Ok(())
}

/// How long an interrupted `osrt train` waits for its coordinator's final write.
const FINAL_WRITE_WAIT: Duration = Duration::from_secs(30);

/// Stops an interrupted local job: the workers are killed, and the coordinator writes
/// what it holds and releases the run folder's lease before this process ends (waited
/// for, within [`FINAL_WRITE_WAIT`]: a store may hang). Returns the error to end with.
async fn interrupted<T>(
    mut stop: osrt_proto::Shutdown,
    children: &mut [tokio::process::Child],
    server: &mut tokio::task::JoinHandle<T>,
) -> anyhow::Error {
    stop.trigger();
    for c in children.iter_mut() {
        let _ = c.start_kill();
    }
    if tokio::time::timeout(FINAL_WRITE_WAIT, server)
        .await
        .is_err()
    {
        eprintln!("the coordinator's final write did not finish within {FINAL_WRITE_WAIT:?}");
    }
    anyhow::anyhow!(
        "interrupted; the job continues from its last checkpoint with `osrt train --resume --run RUN`"
    )
}

/// Runs the job on loopback; returns the final status.
pub async fn run_local(job: LocalJob) -> Result<v1::JobStatus> {
    let token = Token::generate();
    let max_steps = job.spec.max_steps;
    let max_restarts = job.spec.cluster.max_restarts;
    let device = JobConfig::from_toml("the job config", &job.spec.job_toml)?
        .train
        .device;
    let coord = Coordinator::open_with(job.spec, job.open).await?;
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let addr = format!("http://{}", listener.local_addr()?);
    let status_view = coord.clone();
    let (mut stop_coordinator, stopped) = osrt_proto::Shutdown::new();
    let server = tokio::spawn(
        // Loopback only: no TLS.
        coord.serve(
            listener,
            token.clone(),
            None,
            Duration::from_secs(2),
            stopped,
        ),
    );
    // Worker k computes on GPU k (GPUs shared round-robin when there are fewer).
    let gpus = device
        .is_cuda()
        .then(osrt_trainer::device::cuda_device_count);
    let device_of = |k: usize| device.for_local_worker(k, gpus.unwrap_or(0));
    let per_worker = (job.threads_per_worker, job.skip_memory_check);
    let mut children = Vec::new();
    for k in 0..job.workers {
        children.push(spawn_worker(&addr, per_worker, device_of(k), &token)?);
    }
    let bar = step_bar(max_steps);
    let mut respawned = 0u32;
    let mut kills: Vec<Kills> = (0..job.workers).map(|_| Kills::default()).collect();
    // Ctrl-C or SIGTERM: stop the workers too (they would otherwise wait out the
    // coordinator timeout).
    let ctrl_c = shutdown_signal();
    tokio::pin!(ctrl_c);
    let mut server = server;
    let status = loop {
        tokio::select! {
            r = &mut server => break r??,
            _ = &mut ctrl_c => {
                bar.finish_and_clear();
                return Err(interrupted(stop_coordinator, &mut children, &mut server).await);
            }
            _ = tokio::time::sleep(Duration::from_millis(250)) => {}
        }
        let s = status_view.status();
        bar.set_position(s.step);
        if let Some(MetricsRecord::Train(r)) = MetricsRecord::parse(&s.last_record) {
            bar.set_message(format!(
                "loss {:.5} {:.1} scenes/s gen {}",
                r.loss, r.scenes_per_s, s.generation
            ));
        }
        let over = matches!(
            v1::JobState::try_from(s.state),
            Ok(v1::JobState::Done | v1::JobState::Failed)
        );
        if !over {
            let spawn = |k: usize| spawn_worker(&addr, per_worker, device_of(k), &token);
            let replacements = Replacements {
                used: &mut respawned,
                max: max_restarts,
            };
            if let Err(e) = replace_exited(
                &mut children,
                &mut kills,
                (&status_view, Point::of(s.step, s.last_checkpoint)),
                replacements,
                spawn,
            ) {
                stop_coordinator.trigger();
                return Err(e);
            }
        }
        for (child, k) in children.iter().zip(kills.iter_mut()) {
            k.sample(child);
        }
    };
    bar.finish_and_clear();
    for c in children {
        reap(c).await;
    }
    report_end(&status)?;
    Ok(status)
}

/// The launcher's progress bar over the job's steps (hidden off a terminal).
fn step_bar(max_steps: Option<u64>) -> ProgressBar {
    if !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let b = match max_steps {
        Some(n) => ProgressBar::new(n),
        None => ProgressBar::no_length(),
    };
    b.set_style(
        ProgressStyle::with_template(
            "{elapsed_precise} [{bar:30}] step {pos}/{len} {msg} ETA {eta}",
        )
        .expect("valid template")
        .progress_chars("=> "),
    );
    b
}

/// Waits 10 s for a worker the job is done with, then kills it.
async fn reap(mut c: tokio::process::Child) {
    if tokio::time::timeout(Duration::from_secs(10), c.wait())
        .await
        .is_err()
    {
        let _ = c.kill().await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::process::ExitStatusExt;

    /// Kills during set-up are told apart by the checkpoint the generation starts from
    /// (the heartbeats' step is 0 in every set-up): one at step 40 and one setting up from
    /// checkpoint 40 are different points, two set-ups from checkpoint 40 the same.
    #[test]
    fn setup_kills_are_keyed_by_the_generations_start() {
        let kill = std::process::ExitStatus::from_raw(9);
        let mut k = Kills::default();
        assert!(k.killed_again(0, kill, Point::of(40, Some(40))).is_none());
        assert!(k.killed_again(0, kill, Point::of(0, Some(40))).is_none());
        assert!(k.killed_again(0, kill, Point::of(0, Some(20))).is_none());
        let why = k.killed_again(0, kill, Point::of(0, Some(20))).unwrap();
        assert!(
            why.contains("twice while setting up from checkpoint 20"),
            "{why}"
        );
        let mut k = Kills::default();
        assert!(k.killed_again(1, kill, Point::of(57, Some(50))).is_none());
        let why = k.killed_again(1, kill, Point::of(57, Some(50))).unwrap();
        assert!(why.contains("twice at step 57"), "{why}");
    }
}
