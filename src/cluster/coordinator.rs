//! `osrt coordinator`: the job's coordinator as a cluster runs it, with its flags.

use super::spec::{MemoryCheck, memory_check, spec};
use super::{health_listener, report_end, shutdown_signal};
use anyhow::{Context, Result, bail};
use clap::Args;
use osrt_coordinator::{Coordinator, OpenOptions};
use osrt_proto::credentials::Credentials;
use osrt_run::cluster_config::ClusterOverrides;
use osrt_trainer::JobConfig;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

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

pub async fn coordinator(a: CoordinatorArgs) -> Result<()> {
    let credentials = Credentials::from_env()?;
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
            credentials,
            Duration::from_secs_f64(a.linger_s),
            shutdown_signal(),
        )
        .await?;
    report_end(&status)
}
