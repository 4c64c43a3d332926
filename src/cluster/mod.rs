//! `osrt coordinator`, `osrt worker`, and the local launcher behind `osrt train`: a
//! coordinator in this process and N worker processes of this same binary on loopback,
//! started with exactly the flags and environment a cluster's pods use.

mod coordinator;
mod kills;
mod launcher;
mod spec;
mod worker;

pub use coordinator::{CoordinatorArgs, coordinator};
pub use launcher::{LocalJob, run_local};
pub use spec::{MemoryCheck, memory_check, spec};
pub use worker::{WorkerArgs, compute_thread_env, reexec_with_worker_allocator, worker};

use anyhow::{Context, Result, bail};
use osrt_proto::v1;
use std::net::SocketAddr;

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
pub(crate) async fn shutdown_signal() {
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
