//! The local launcher behind `osrt train`: a coordinator in this process and worker
//! processes of this same binary on loopback, replaced when they exit, with a progress bar.

use super::kills::{Kills, Point};
use super::worker::{WORKER_MALLOC_ENV, compute_thread_env};
use super::{report_end, shutdown_signal};
use anyhow::{Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use osrt_coordinator::{Coordinator, JobSpec, OpenOptions};
use osrt_proto::auth::{TOKEN_ENV, Token};
use osrt_proto::credentials::Credentials;
use osrt_proto::v1;
use osrt_run::MetricsRecord;
use osrt_trainer::{JobConfig, device::DeviceSpec};
use std::io::IsTerminal;
use std::time::Duration;

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
            Credentials::new(token.clone(), None),
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
