//! The worker shell: registers with the coordinator, asks for a plan, and runs each
//! generation's [`Learner`] (the training loop, which makes no RPC) inside membership,
//! heartbeats, the ring all-reduce and the progress and checkpoint reports, until the job
//! is done.
//!
//! One **generation** = one fixed ring of members. A generation starts from the committed
//! checkpoint the plan names (or from rank 0's fresh weights, broadcast over the ring) and
//! ends when the job is finished, or is aborted: the coordinator moved to a new generation
//! (a member was lost or joined), or a round failed here (dead peer, malformed chunk) —
//! then the worker reports the fault and asks for the next plan.
//!
//! Every replica takes bit-identical steps: the data order derives from `(seed, epoch)`
//! and each scene's rays and slot noise from `(seed, step, scene)`
//! ([`osrt_trainer::shard`]), gradients are summed in fixed ring order, and rank 0's clock decides evaluation and stopping for all
//! ([`osrt_trainer::distributed`]). Rank 0 writes checkpoints and sends the metrics records.
//!
//! Registration, the membership loop and heartbeats are in `membership`; one generation's
//! run, its checkpoints and the ring opening in `generation`.
//!
//! [`Learner`]: osrt_trainer::learner::Learner

use crate::error::{Result, WorkerError};
use crate::link::coordinator_client;
use crate::membership::{Membership, worker_loop};
use osrt_collective::{Mailbox, serve};
use osrt_proto::credentials::Credentials;
use osrt_proto::{Shutdown, v1};
use std::net::SocketAddr;
use std::sync::Mutex;
use std::time::Duration;

pub struct WorkerOptions {
    /// `http://host:port` of the coordinator.
    pub coordinator: String,
    /// Where this worker's collective server listens (port 0: any free port).
    pub listen: SocketAddr,
    /// Host name or IP the other workers reach this one at (default: the listen IP).
    pub advertise: Option<String>,
    pub threads: usize,
    /// Overrides the job config's `train.device` (each worker its own GPU).
    pub device: Option<osrt_trainer::device::DeviceSpec>,
    /// The job's token and, where set, mutual TLS, for both services
    /// (`osrt_proto::credentials`).
    pub credentials: Credentials,
    pub name: String,
    /// Give up when the coordinator cannot be reached for this long.
    pub coordinator_timeout: Duration,
    /// Leave a job whose step's estimated peak memory this machine cannot hold
    /// (`osrt_trainer::footprint`), before allocating anything.
    pub memory_check: bool,
}

/// Runs a worker until the job is done (Ok) or failed (Err).
pub async fn run_worker(opts: WorkerOptions) -> Result<()> {
    run_worker_until(opts, std::future::pending()).await
}

/// [`run_worker`] until `stop` resolves (SIGTERM, SIGINT): the generation in progress is
/// abandoned (a checkpoint being written stays torn, without a manifest), the coordinator
/// is told at once instead of noticing after the heartbeat timeout, and the worker ends
/// with an error.
pub async fn run_worker_until(
    opts: WorkerOptions,
    stop: impl std::future::Future<Output = ()>,
) -> Result<()> {
    // A device this machine or build cannot open: the worker never joins.
    if let Some(d) = opts.device {
        d.check_available()?;
    }
    let listener = tokio::net::TcpListener::bind(opts.listen)
        .await
        .map_err(|e| WorkerError::Cluster(format!("cannot listen on {}: {e}", opts.listen)))?;
    let local = listener
        .local_addr()
        .map_err(|e| WorkerError::Cluster(e.to_string()))?;
    let host = advertised_host(opts.advertise.as_deref(), local.ip())?;
    let scheme = opts.credentials.scheme();
    let collective_addr = format!("{scheme}://{host}:{}", local.port());
    // The job id is learnt at registration; the mailbox takes it then.
    let mailbox = Mailbox::new("");
    let (mut stop_server, stopped) = Shutdown::new();
    let server = tokio::spawn(serve(
        listener,
        mailbox.clone(),
        opts.credentials.clone(),
        stopped,
    ));
    let mut client = coordinator_client(&opts.coordinator, &opts.credentials)?;
    let member: Mutex<Option<Membership>> = Mutex::new(None);
    let mut reporter = client.clone();
    let result = tokio::select! {
        r = worker_loop(&opts, &mut client, &mailbox, &collective_addr, &member) => r,
        _ = stop => {
            let known = member.lock().expect("membership").take();
            if let Some(m) = known {
                // Leaving: the coordinator drops this member at once (a generation in
                // progress ends) instead of after the heartbeat timeout.
                let r = reporter
                    .report_fault(v1::FaultReport {
                        job: m.job,
                        worker_id: m.worker_id,
                        generation: m.generation,
                        reason: "the worker was stopped by a signal".into(),
                        fatal: false,
                        leaving: true,
                    })
                    .await;
                if let Err(s) = r {
                    tracing::warn!(status = %s, "could not tell the coordinator this worker leaves");
                }
            }
            Err(WorkerError::Cluster("stopped by a signal".into()))
        }
    };
    stop_server.trigger();
    let _ = server.await;
    result
}

/// The host the other workers dial this one at: `--advertise`, else the listen address,
/// else (listening on every interface, whose address `0.0.0.0` would make a peer dial
/// itself) this machine's host name.
pub(crate) fn advertised_host(advertise: Option<&str>, listen: std::net::IpAddr) -> Result<String> {
    if let Some(h) = advertise {
        return Ok(h.to_string());
    }
    if !listen.is_unspecified() {
        return Ok(listen.to_string());
    }
    let name = osrt_run::lease::host_name().ok_or_else(|| {
        WorkerError::Cluster(format!(
            "listening on {listen} (every interface) and this machine has no host name: \
             pass --advertise HOST, the address the other workers reach this one at"
        ))
    })?;
    tracing::warn!(host = %name, "listening on every interface: advertising this machine's host name (--advertise sets it)");
    Ok(name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_worker_listening_everywhere_advertises_a_name_not_0_0_0_0() {
        let any: std::net::IpAddr = "0.0.0.0".parse().unwrap();
        let lo: std::net::IpAddr = "127.0.0.1".parse().unwrap();
        assert_eq!(advertised_host(Some("w-3.osrt"), any).unwrap(), "w-3.osrt");
        assert_eq!(advertised_host(None, lo).unwrap(), "127.0.0.1");
        match advertised_host(None, any) {
            Ok(h) => assert!(!h.is_empty() && h != "0.0.0.0", "{h}"),
            Err(e) => assert!(e.to_string().contains("--advertise"), "{e}"),
        }
    }
}
