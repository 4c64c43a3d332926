//! The Coordinator gRPC service over a shared [`Core`], the monitor loop (heartbeat
//! timeouts, generation formation) and persistence of `job.json` and `metrics.jsonl`.
//! The handlers are in `grpc`; opening the run folder (a new, restarted, resumed or
//! imported job) in `start`.

use crate::core::{Core, JobSpec, Persisted, Phase};
use crate::error::CoordinatorError;
use crate::events::Events;
use crate::persist::Persister;
use grpc::Service;
use osrt_proto::credentials::Credentials;
use osrt_proto::v1;
use osrt_proto::v1::coordinator_server::CoordinatorServer;
use osrt_run::lease::{self, Holder, Keeper, Lease, LeaseTiming};
use osrt_run::metrics_log::MetricsLog;
use osrt_run::{JOB_FILE, read_file};
use osrt_store::Location;
use start::run_err;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::Notify;
use tonic::service::interceptor::InterceptedService;

mod grpc;
mod start;

/// Largest message the coordinator takes or sends.
const MAX_MESSAGE_BYTES: usize = 16 << 20;

/// The longest a call to the coordinator may last (a plan's long poll takes 2 s).
const CALL_LIMIT: Duration = Duration::from_secs(60);

pub(crate) struct Shared {
    pub core: Mutex<Core>,
    changed: Notify,
    pub run: Location,
    /// The run folder's lease, held and renewed from `open` until the job is over
    /// (`None` once released).
    pub lease: tokio::sync::Mutex<Option<Keeper>>,
    /// The records as written to the run folder, and as TensorBoard events (only the
    /// [`Persister`] writes them).
    pub metrics: tokio::sync::Mutex<MetricsLog>,
    pub events: tokio::sync::Mutex<Events>,
}

/// How a coordinator opens its run folder.
#[derive(Debug, Clone, Copy, Default)]
pub struct OpenOptions {
    /// Continue a finished job with new limits (`--resume`).
    pub resume: bool,
    /// Take the run folder's lease without watching it for a live holder (`--take-over`:
    /// the holder is known to be dead).
    pub take_over: bool,
    pub lease: LeaseTiming,
}

impl Shared {
    pub fn with<T>(&self, f: impl FnOnce(&mut Core, Instant) -> T) -> T {
        let out = f(
            &mut self.core.lock().expect("coordinator state"),
            Instant::now(),
        );
        self.changed.notify_waiters();
        out
    }
}

/// A job's coordinator, ready to serve.
#[derive(Clone)]
pub struct Coordinator {
    shared: Arc<Shared>,
}

/// A copy of the job's status for displays (the launcher's progress bar).
pub type StatusSnapshot = v1::JobStatus;

impl Coordinator {
    /// Opens the job in `spec.run`. A run folder with an unfinished `job.json` is a
    /// restarted coordinator: the job continues from its newest committed checkpoint (its
    /// own `config.toml` wins). `resume` continues a finished job with the new limits.
    pub async fn open(spec: JobSpec, resume: bool) -> Result<Self, CoordinatorError> {
        let opts = OpenOptions {
            resume,
            ..Default::default()
        };
        Self::open_with(spec, opts).await
    }

    /// [`Coordinator::open`] with all of [`OpenOptions`].
    pub async fn open_with(spec: JobSpec, opts: OpenOptions) -> Result<Self, CoordinatorError> {
        let run = Location::parse(&spec.run)?;
        Self::open_at_with(spec, run, opts).await
    }

    /// [`Coordinator::open`] on an already opened run location (`spec.run` names it).
    pub async fn open_at(
        spec: JobSpec,
        run: Location,
        resume: bool,
    ) -> Result<Self, CoordinatorError> {
        let opts = OpenOptions {
            resume,
            ..Default::default()
        };
        Self::open_at_with(spec, run, opts).await
    }

    /// [`Coordinator::open_at`] with all of [`OpenOptions`]. The run folder's lease is
    /// taken before anything in it is written: a second coordinator on a folder whose
    /// coordinator is alive is refused (`osrt_run::lease`).
    pub async fn open_at_with(
        spec: JobSpec,
        run: Location,
        opts: OpenOptions,
    ) -> Result<Self, CoordinatorError> {
        let resume = opts.resume;
        let persisted: Option<Persisted> = match read_file(&run, JOB_FILE).await? {
            Some(b) => Some(
                serde_json::from_slice(&b)
                    .map_err(|e| run_err(&run, JOB_FILE, format!("unreadable: {e}")))?,
            ),
            None => None,
        };
        let job_id = persisted.as_ref().map_or(&spec.job_id, |p| &p.job_id);
        // A store that silently overwrites create-only or conditional writes would let
        // two writers share the folder: refused before anything is taken or written.
        lease::probe_store(&run).await?;
        // The next generation this coordinator forms is the persisted one's successor:
        // ranks of the persisted one (a previous holder's) are fenced off at once.
        let fence = persisted.as_ref().map_or(0, |p| p.generation + 1);
        let lease = Lease::acquire_fencing(
            &run,
            Holder::this_process(job_id),
            opts.lease,
            opts.take_over,
            fence,
        )
        .await?;
        // A refusal below leaves the folder free at once.
        let opened = async {
            let log = MetricsLog::open(&run).await?;
            let mut core = Self::open_core(spec, &run, resume, log.last_step()).await?;
            let events = Events::open(&run, &mut core, log.appends_in_place()).await?;
            Ok::<_, CoordinatorError>((core, log, events))
        };
        let (core, log, events) = match opened.await {
            Ok(opened) => opened,
            Err(e) => {
                if let Err(r) = lease.release().await {
                    tracing::warn!(error = %r, "releasing the run folder's lease");
                }
                return Err(e);
            }
        };
        Ok(Self {
            shared: Arc::new(Shared {
                core: Mutex::new(core),
                changed: Notify::new(),
                run,
                lease: tokio::sync::Mutex::new(Some(Keeper::start(lease))),
                metrics: tokio::sync::Mutex::new(log),
                events: tokio::sync::Mutex::new(events),
            }),
        })
    }

    pub fn job_id(&self) -> String {
        self.shared.core.lock().expect("state").spec.job_id.clone()
    }

    /// Fails the job with `reason` (written to `job.json` like a fatal fault); the
    /// server then ends as after any failure.
    pub fn fail(&self, reason: String) {
        self.shared.with(|c, _| c.fail(reason));
    }

    pub fn status(&self) -> StatusSnapshot {
        status_of(&self.shared.core.lock().expect("state"), Instant::now())
    }

    /// Serves until the job is over (then keeps answering for `linger`, so every worker
    /// learns the outcome) or `shutdown` resolves. Returns the final status.
    pub async fn serve(
        self,
        listener: tokio::net::TcpListener,
        credentials: Credentials,
        linger: Duration,
        shutdown: impl std::future::Future<Output = ()> + Send + 'static,
    ) -> Result<StatusSnapshot, CoordinatorError> {
        let health_service = osrt_proto::server_setup::CheckOnly::server(&[
            osrt_proto::v1::coordinator_server::SERVICE_NAME,
        ]);
        let service = InterceptedService::new(
            CoordinatorServer::new(Service {
                shared: self.shared.clone(),
            })
            // Reports carry at most MAX_RECORDS_PER_REPORT records of a few hundred bytes.
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES),
            credentials.check("coordinator"),
        );
        let (mut stop_server, stopped) = osrt_proto::Shutdown::new();
        let mut builder = credentials.server(CALL_LIMIT).map_err(|e| {
            CoordinatorError::Cluster(format!("coordinator TLS configuration: {e}"))
        })?;
        let server = tokio::spawn(
            builder
                .add_service(health_service)
                .add_service(service)
                .serve_with_incoming_shutdown(
                    tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true)),
                    stopped,
                ),
        );
        let result = self.monitor(linger, shutdown).await;
        stop_server.trigger();
        let _ = server.await;
        result
    }

    /// Times out members and forms generations every 100 ms, beside the run folder's
    /// writer ([`Persister`]), until the job is over and written; stops at once (with
    /// the error) if the lease was lost.
    async fn monitor(
        &self,
        linger: Duration,
        shutdown: impl std::future::Future<Output = ()>,
    ) -> Result<StatusSnapshot, CoordinatorError> {
        let appends = self.shared.metrics.lock().await.appends_in_place();
        let writing = Persister::new(&self.shared, appends).run(linger, shutdown);
        let ticking = async {
            loop {
                tokio::time::sleep(Duration::from_millis(100)).await;
                self.check_lease().await?;
                self.shared.with(|c, now| c.tick(now));
            }
            #[allow(unreachable_code)]
            Ok::<StatusSnapshot, CoordinatorError>(self.status())
        };
        tokio::select! {
            written = writing => written?,
            lost = ticking => return lost,
        }
        Ok(self.status())
    }

    /// Stops the coordinator (with the error) once its lease was lost or expired: it must
    /// not drive the job or write the folder any more. The lease is renewed by a task of
    /// its own, so no store write delays a renewal.
    async fn check_lease(&self) -> Result<(), CoordinatorError> {
        let mut guard = self.shared.lease.lock().await;
        let Some(keeper) = guard.as_ref() else {
            return Ok(());
        };
        if let Err(e) = keeper.check() {
            if let Some(k) = guard.take()
                && let Err(r) = k.release().await
            {
                tracing::warn!(error = %r, "releasing the run folder's lease");
            }
            return Err(e.into());
        }
        Ok(())
    }
}

fn status_of(c: &Core, now: Instant) -> StatusSnapshot {
    let (state, message) = match &c.phase {
        Phase::Waiting { .. } => (v1::JobState::Waiting, String::new()),
        Phase::Running => (v1::JobState::Running, String::new()),
        Phase::Done => (v1::JobState::Done, String::new()),
        Phase::Failed(m) => (v1::JobState::Failed, m.clone()),
    };
    v1::JobStatus {
        job: c.spec.job_id.clone(),
        state: state as i32,
        generation: c.generation,
        step: c
            .ring
            .iter()
            .filter_map(|id| c.members.get(id))
            .map(|m| m.step)
            .max()
            .unwrap_or(0),
        restarts: c.restarts,
        last_checkpoint: c.last_checkpoint,
        hash_checks: c.hash_checks,
        members: c
            .members
            .values()
            .map(|m| v1::MemberStatus {
                worker_id: m.id,
                name: m.name.clone(),
                collective_addr: m.addr.clone(),
                rank: c.ring.iter().position(|&x| x == m.id).map(|r| r as u32),
                step: m.step,
                last_seen_s: now.duration_since(m.last_seen).as_secs_f64(),
            })
            .collect(),
        last_record: c.last_record.clone(),
        message,
    }
}
