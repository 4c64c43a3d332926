//! The Coordinator gRPC service over a shared [`Core`], the monitor loop (heartbeat
//! timeouts, generation formation) and persistence of `job.json` and `metrics.jsonl`.

use crate::core::{
    Core, JobSpec, MetricsWrite, Persisted, Phase, Progress, Registration, record_step,
};
use crate::error::CoordinatorError;
use crate::events::Events;
use crate::retention::Retention;
use crate::timeline::{Timeline, Turn};
use osrt_proto::auth::{CheckToken, Token};
use osrt_proto::convert::Directive;
use osrt_proto::v1;
use osrt_proto::v1::coordinator_server::{self, CoordinatorServer};
use osrt_run::Location;
use osrt_run::lease::{self, Holder, Keeper, Lease, LeaseTiming};
use osrt_run::retry::{Failing, RetryPolicy};
use osrt_run::{
    CONFIG_FILE, ClusterConfig, INFO_FILE, METRICS_FILE, RunError, RunInfo, checkpoint, read_file,
    write_file,
};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::Notify;
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Response, Status};

pub use osrt_run::JOB_FILE;

/// Largest message the coordinator takes or sends.
const MAX_MESSAGE_BYTES: usize = 16 << 20;

/// How long a plan request waits for a change before answering `Waiting`.
const PLAN_POLL: Duration = Duration::from_secs(2);

struct Shared {
    core: Mutex<Core>,
    changed: Notify,
    run: Location,
    /// The run folder's lease, held and renewed from `open` until the job is over
    /// (`None` once released).
    lease: tokio::sync::Mutex<Option<Keeper>>,
    /// The records as TensorBoard events (only the monitor loop writes them).
    events: tokio::sync::Mutex<Events>,
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
    fn with<T>(&self, f: impl FnOnce(&mut Core, Instant) -> T) -> T {
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

/// Refuses a job whose `min_workers` its batch cannot feed (one scene per worker), or
/// whose chunks the collective does not carry.
fn gatherable(spec: &JobSpec, run: &Location) -> Result<(), CoordinatorError> {
    let chunk = spec.cluster.chunk_floats;
    if chunk > osrt_proto::MAX_CHUNK_FLOATS {
        return Err(run_err(
            run,
            CONFIG_FILE,
            format!(
                "cluster.chunk_floats = {chunk} exceeds the collective's chunk of 1 MiB of f32 ({})",
                osrt_proto::MAX_CHUNK_FLOATS
            ),
        ));
    }
    let min = spec.cluster.min_workers;
    match ClusterConfig::global_batch_of(&spec.job_toml).filter(|&b| min > b) {
        Some(b) => Err(run_err(
            run,
            CONFIG_FILE,
            format!(
                "cluster.min_workers = {min} can never gather: a step's {b} scenes \
                 (train.batch_size) feed at most {b} workers; lower --min-workers or raise \
                 --batch-size"
            ),
        )),
        None => Ok(()),
    }
}

fn run_err(run: &Location, name: &str, reason: impl std::fmt::Display) -> CoordinatorError {
    CoordinatorError::Run(RunError::Run {
        path: run.describe(&run.path(name)),
        reason: reason.to_string(),
    })
}

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
            let mut core = Self::open_core(spec, &run, resume).await?;
            let can_append = run.local_file(&run.path(METRICS_FILE)).is_some();
            let events = Events::open(&run, &mut core, can_append).await?;
            Ok::<_, CoordinatorError>((core, events))
        };
        let (core, events) = match opened.await {
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
                events: tokio::sync::Mutex::new(events),
            }),
        })
    }

    /// The job's state from the run folder (read again under the lease: the folder's
    /// previous holder may have written last), or a new job's.
    async fn open_core(
        mut spec: JobSpec,
        run: &Location,
        resume: bool,
    ) -> Result<Core, CoordinatorError> {
        let run = run.clone();
        let persisted: Option<Persisted> = match read_file(&run, JOB_FILE).await? {
            Some(b) => Some(
                serde_json::from_slice(&b)
                    .map_err(|e| run_err(&run, JOB_FILE, format!("unreadable: {e}")))?,
            ),
            None => None,
        };
        let now = Instant::now();
        let core = match persisted {
            None if resume => {
                return Err(run_err(
                    &run,
                    JOB_FILE,
                    "--resume: no job to resume in this run folder",
                ));
            }
            None => Self::create(spec, &run, now).await?,
            Some(p) => {
                let finished = p.state == "done" || p.state == "failed";
                if finished && !resume {
                    return Err(run_err(
                        &run,
                        JOB_FILE,
                        format!(
                            "the job in this run folder is {}; pass --resume to continue it with new limits, or choose a new --run",
                            p.state
                        ),
                    ));
                }
                let text = read_file(&run, CONFIG_FILE)
                    .await?
                    .ok_or_else(|| run_err(&run, CONFIG_FILE, "missing"))?;
                let text = String::from_utf8_lossy(&text).into_owned();
                spec.cluster =
                    ClusterConfig::from_job_toml(&run.describe(&run.path(CONFIG_FILE)), &text)?;
                // The command line's membership limits win over the stored ones; the
                // stored text (hashed into checkpoints) is what workers get.
                spec.cluster_overrides.apply(&mut spec.cluster);
                spec.cluster.validate()?;
                spec.job_toml = text;
                spec.job_id = p.job_id.clone();
                spec.data = p.data.clone();
                gatherable(&spec, &run)?;
                if !resume {
                    // A restarted coordinator keeps the job's limits.
                    spec.max_steps = p.max_steps;
                    spec.deadline_unix_s = p.deadline_unix_s;
                }
                let records: Vec<String> = read_file(&run, METRICS_FILE)
                    .await?
                    .map(|b| {
                        String::from_utf8_lossy(&b)
                            .lines()
                            .map(str::to_string)
                            .collect()
                    })
                    .unwrap_or_default();
                // The job continues from the checkpoint `job.json` recorded (or the newest
                // older one that verifies), and never from past the last step whose records
                // reached `metrics.jsonl` (they are flushed once a second): the steps after
                // it are replayed and their records sent again, so none is missing.
                // No record at all: the job starts over.
                let last_record = records.iter().filter_map(|l| record_step(l)).max();
                let at_most = checkpoint::resume_bound(last_record, p.last_checkpoint);
                let checkpoint = checkpoint::latest_verified(&run, Some(at_most)).await?;
                tracing::info!(
                    job = %p.job_id,
                    generation = p.generation,
                    checkpoint = ?checkpoint,
                    "continuing the job in the run folder"
                );
                let mut core = Core::new(spec, now);
                core.restore(&p, records, checkpoint, resume, now);
                core
            }
        };
        Ok(core)
    }

    /// A new job in an empty run folder: refused before anything is written if it cannot
    /// run; then its config and run info are written.
    async fn create(spec: JobSpec, run: &Location, now: Instant) -> Result<Core, CoordinatorError> {
        let metrics = read_file(run, METRICS_FILE).await?;
        if metrics.is_some_and(|m| !m.is_empty()) {
            return Err(run_err(
                run,
                METRICS_FILE,
                "the run folder already holds a run; choose a new --run or pass --resume",
            ));
        }
        // Refused before anything is written.
        gatherable(&spec, run)?;
        write_file(run, CONFIG_FILE, spec.job_toml.clone().into_bytes()).await?;
        // The parameter count comes from rank 0: the coordinator never builds the
        // model (the `paper` preset's weights and optimizer state are a gigabyte).
        let info = RunInfo {
            data: spec.data.clone(),
            parameters: None,
            workers: spec.cluster.min_workers,
        };
        write_file(
            run,
            INFO_FILE,
            serde_json::to_vec_pretty(&info).expect("serialises"),
        )
        .await?;
        Ok(Core::new(spec, now))
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
        token: Token,
        tls: Option<osrt_proto::tls::Tls>,
        linger: Duration,
        shutdown: impl std::future::Future<Output = ()> + Send + 'static,
    ) -> Result<StatusSnapshot, CoordinatorError> {
        let (health, health_service) = tonic_health::server::health_reporter();
        health.set_serving::<CoordinatorServer<Service>>().await;
        let service = InterceptedService::new(
            CoordinatorServer::new(Service {
                shared: self.shared.clone(),
            })
            // Reports carry at most MAX_RECORDS_PER_REPORT records of a few hundred bytes.
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES),
            CheckToken::new(token, "coordinator"),
        );
        let (mut stop_server, stopped) = osrt_proto::Shutdown::new();
        let mut builder = tonic::transport::Server::builder();
        if let Some(tls) = &tls {
            builder = builder.tls_config(tls.server()).map_err(|e| {
                CoordinatorError::Cluster(format!("coordinator TLS configuration: {e}"))
            })?;
        }
        let server = tokio::spawn(
            builder
                .http2_keepalive_interval(Some(osrt_proto::KEEP_ALIVE_INTERVAL))
                .http2_keepalive_timeout(Some(osrt_proto::KEEP_ALIVE_TIMEOUT))
                .tcp_nodelay(true)
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

    /// Times out members, forms generations, persists state; returns when the job is over.
    async fn monitor(
        &self,
        linger: Duration,
        shutdown: impl std::future::Future<Output = ()>,
    ) -> Result<StatusSnapshot, CoordinatorError> {
        tokio::pin!(shutdown);
        let mut last_flush = Instant::now();
        let mut over_since: Option<Instant> = None;
        let mut store = StoreRetry::default();
        let can_append = self.local_metrics().is_some();
        let mut retention = Retention::default();
        let mut timeline = Timeline::default();
        let keep_last = self.shared.with(|c, _| c.spec.cluster.keep_last);
        loop {
            tokio::select! {
                _ = &mut shutdown => break,
                _ = tokio::time::sleep(Duration::from_millis(100)) => {}
            }
            self.check_lease().await?;
            self.discard_abandoned(&mut timeline).await;
            let write_now = store.due();
            let mut events = self.shared.events.lock().await;
            let (job, metrics, work, over) = self.shared.with(|c, now| {
                c.tick(now);
                let job = (write_now && std::mem::take(&mut c.dirty_job)).then(|| c.persisted());
                let flush = write_now
                    && c.dirty_metrics
                    && (c.is_over() || last_flush.elapsed() >= Duration::from_secs(1));
                let metrics = flush.then(|| (c.metrics_write(can_append), c.last_record_step()));
                // Events follow what metrics.jsonl holds.
                let work = (write_now
                    && !c.dirty_metrics
                    && (c.events_pending() || events.is_dirty())
                    && events.due(c.is_over()))
                .then(|| c.events_work());
                (job, metrics, work, c.is_over())
            });
            let run = &self.shared.run;
            let (had_job, had_metrics) = (job.is_some(), metrics.is_some());
            let job_checkpoint = job.as_ref().map(|p| p.last_checkpoint);
            let mut written: Result<(), CoordinatorError> = Ok(());
            if let Some(p) = job {
                let bytes = serde_json::to_vec_pretty(&p).expect("serialises");
                written = write_file(run, JOB_FILE, bytes).await.map_err(Into::into);
            }
            let metrics_last = metrics.as_ref().map(|(_, last)| *last);
            if let Some((w, _)) = metrics {
                if written.is_ok() {
                    written = self.write_metrics(w).await;
                    last_flush = Instant::now();
                } else {
                    self.shared.with(|c, _| c.metrics_write_failed());
                }
            }
            let had_events = work.is_some();
            if let Some(w) = work {
                // Added to the log even if this write fails: its next write has them.
                let w = events.write(w).await;
                if written.is_ok() {
                    written = w;
                }
            }
            drop(events);
            if let Err(e) = written {
                // Whatever was not written is written again at the next try.
                self.shared.with(|c, _| {
                    c.dirty_job |= had_job;
                    if had_metrics {
                        c.metrics_write_failed();
                    }
                });
                store.failed(e)?;
                continue;
            }
            if had_job || had_metrics || had_events {
                store.succeeded();
            }
            if let Some(c) = job_checkpoint {
                retention.job_written(c);
            }
            if let Some(r) = metrics_last {
                retention.metrics_written(r);
            }
            retention.maybe_start(run, keep_last);
            let events_dirty = self.shared.events.lock().await.is_dirty();
            let pending = {
                let c = self.shared.core.lock().expect("state");
                c.dirty_job || c.dirty_metrics || c.events_pending() || events_dirty
            };
            if over {
                let since = *over_since.get_or_insert_with(Instant::now);
                if since.elapsed() >= linger && !pending {
                    break;
                }
            }
        }
        self.write_last(can_append, &mut retention, keep_last)
            .await?;
        Ok(self.status())
    }

    /// What the run folder lacks, written once more (the job is over, or a signal stopped
    /// the coordinator), a last retention pass, and the lease released.
    async fn write_last(
        &self,
        can_append: bool,
        retention: &mut Retention,
        keep_last: usize,
    ) -> Result<(), CoordinatorError> {
        let (job, metrics) = self.shared.with(|c, _| {
            let job = std::mem::take(&mut c.dirty_job).then(|| c.persisted());
            let metrics = c
                .dirty_metrics
                .then(|| (c.metrics_write(can_append), c.last_record_step()));
            (job, metrics)
        });
        if let Some(p) = job {
            let bytes = serde_json::to_vec_pretty(&p).expect("serialises");
            write_file(&self.shared.run, JOB_FILE, bytes).await?;
            retention.job_written(p.last_checkpoint);
        }
        if let Some((w, last)) = metrics {
            self.write_metrics(w).await?;
            retention.metrics_written(last);
        }
        retention.finish(&self.shared.run, keep_last).await;
        let work = self.shared.with(|c, _| c.events_work());
        self.shared.events.lock().await.write(work).await?;
        if let Some(lease) = self.shared.lease.lock().await.take() {
            lease.release().await?;
        }
        Ok(())
    }

    /// Stops the coordinator (with the error) once its lease was lost or expired: it must
    /// not drive the job or write the folder any more. The lease is renewed by a task of
    /// its own, so no store write of this loop delays a renewal.
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

    /// Fences off older generations in the lease, then discards the checkpoints past the
    /// new generation's starting point (verified first) before its plans go out; a
    /// discard that cannot be made fails the job.
    async fn discard_abandoned(&self, timeline: &mut Timeline) {
        let (pending, resume_step, generation) = self.shared.with(|c, _| {
            (
                c.discard_pending && !c.is_over(),
                c.resume_step,
                c.generation,
            )
        });
        if !pending {
            return;
        }
        // The lease names the new generation first: from then on no rank of an older one
        // can commit a checkpoint the discard would have to catch.
        let token = match self.shared.lease.lock().await.as_ref() {
            Some(k) if k.fence(generation) => k.token().to_string(),
            _ => return,
        };
        match timeline.turn(&self.shared.run, &token, resume_step).await {
            Turn::Pending => {}
            Turn::Done => self.shared.with(|c, _| {
                if c.resume_step == resume_step {
                    c.discarded();
                }
            }),
            Turn::Fatal(reason) => self
                .shared
                .with(|c, _| c.fail(format!("the generation could not start: {reason}"))),
        }
    }

    /// `RUN/metrics.jsonl` as a local file, where the run folder is one.
    fn local_metrics(&self) -> Option<std::path::PathBuf> {
        let run = &self.shared.run;
        run.local_file(&run.path(METRICS_FILE))
    }

    /// Appends to `metrics.jsonl` in place (a local run folder: synced before it counts),
    /// or writes it whole (object stores cannot append).
    async fn write_metrics(&self, w: MetricsWrite) -> Result<(), CoordinatorError> {
        let run = &self.shared.run;
        match (w, self.local_metrics()) {
            (MetricsWrite::Append(text), Some(file)) => {
                let shown = run.describe(&run.path(METRICS_FILE));
                tokio::task::spawn_blocking(move || -> std::io::Result<()> {
                    use std::io::Write;
                    let mut f = std::fs::OpenOptions::new()
                        .create(true)
                        .append(true)
                        .open(&file)?;
                    f.write_all(text.as_bytes())?;
                    f.sync_data()
                })
                .await
                .map_err(|e| run_err(run, METRICS_FILE, e))?
                .map_err(|e| {
                    CoordinatorError::Run(RunError::Run {
                        path: shown,
                        reason: format!("appending: {e}"),
                    })
                })
            }
            (MetricsWrite::Whole(text), _) => {
                Ok(write_file(run, METRICS_FILE, text.into_bytes()).await?)
            }
            // Not asked of an object store (`can_append` is false there); were it, the
            // failure makes the next write whole.
            (MetricsWrite::Append(_), None) => Err(run_err(
                run,
                METRICS_FILE,
                "an append was asked of a store that cannot append",
            )),
        }
    }
}

/// How long writes of `job.json` and `metrics.jsonl` may keep failing before the
/// coordinator gives up (the job's state stays in memory meanwhile, and workers train on).
pub const STORE_RETRY_BUDGET: Duration = Duration::from_secs(120);

/// Failed writes of the run folder, retried by the monitor loop under
/// [`RetryPolicy::backoff`] within [`STORE_RETRY_BUDGET`].
#[derive(Default)]
struct StoreRetry(Failing);

impl StoreRetry {
    fn due(&self) -> bool {
        self.0.due()
    }

    fn failed(&mut self, e: CoordinatorError) -> Result<(), CoordinatorError> {
        match self.0.failed(&RetryPolicy::backoff(STORE_RETRY_BUDGET)) {
            Some(wait) => {
                tracing::warn!(error = %e, retry_in = ?wait, "writing the run folder failed; retrying");
                Ok(())
            }
            None => {
                tracing::error!(error = %e, "the run folder could not be written for {STORE_RETRY_BUDGET:?}");
                Err(e)
            }
        }
    }

    fn succeeded(&mut self) {
        if let Some(after) = self.0.succeeded() {
            tracing::info!(?after, "the run folder is written again");
        }
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

struct Service {
    shared: Arc<Shared>,
}

impl Service {
    fn check_job(&self, job: &str) -> Result<(), Status> {
        let c = self.shared.core.lock().expect("state");
        if job != c.spec.job_id {
            return Err(Status::permission_denied(format!(
                "message for job `{job}`, this coordinator runs job `{}`",
                c.spec.job_id
            )));
        }
        Ok(())
    }
}

fn ack(d: Directive) -> Response<v1::Ack> {
    Response::new(v1::Ack {
        action: v1::Action::from(d) as i32,
    })
}

#[tonic::async_trait]
impl coordinator_server::Coordinator for Service {
    async fn register(
        &self,
        request: Request<v1::RegisterRequest>,
    ) -> Result<Response<v1::RegisterReply>, Status> {
        let r = request.into_inner();
        let registration = Registration {
            protocol_version: r.protocol_version,
            name: r.name,
            addr: r.collective_addr,
            threads: r.threads,
            instance: r.instance,
        };
        let (id, job) = self.shared.with(|c, now| {
            c.register(registration, now)
                .map(|id| (id, c.spec.job_id.clone()))
        })?;
        Ok(Response::new(v1::RegisterReply { job, worker_id: id }))
    }

    async fn get_plan(
        &self,
        request: Request<v1::PlanRequest>,
    ) -> Result<Response<v1::Plan>, Status> {
        let r = request.into_inner();
        self.check_job(&r.job)?;
        let deadline = tokio::time::Instant::now() + PLAN_POLL;
        loop {
            let notified = self.shared.changed.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            let (plan, job) = {
                let mut c = self.shared.core.lock().expect("state");
                let plan = c.plan(r.worker_id, r.after_generation, Instant::now())?;
                (plan, c.spec.job_id.clone())
            };
            let waiting = plan == osrt_proto::convert::PlanState::Waiting;
            if !waiting || tokio::time::timeout_at(deadline, notified).await.is_err() {
                return Ok(Response::new(plan.into_proto(&job)));
            }
        }
    }

    async fn heartbeat(
        &self,
        request: Request<v1::HeartbeatRequest>,
    ) -> Result<Response<v1::HeartbeatReply>, Status> {
        let r = request.into_inner();
        self.check_job(&r.job)?;
        let (d, generation) = self
            .shared
            .with(|c, now| c.heartbeat(r.worker_id, r.generation, r.step, now))?;
        Ok(Response::new(v1::HeartbeatReply {
            action: v1::Action::from(d) as i32,
            generation,
        }))
    }

    async fn report_progress(
        &self,
        request: Request<v1::ProgressReport>,
    ) -> Result<Response<v1::Ack>, Status> {
        let r = request.into_inner();
        self.check_job(&r.job)?;
        let d = self.shared.with(|c, now| {
            c.progress(
                Progress {
                    worker_id: r.worker_id,
                    generation: r.generation,
                    rank: r.rank as usize,
                    step: r.step,
                    param_hash: r.param_hash,
                    records: r.records,
                },
                now,
            )
        })?;
        Ok(ack(d))
    }

    async fn report_checkpoint(
        &self,
        request: Request<v1::CheckpointReport>,
    ) -> Result<Response<v1::Ack>, Status> {
        let r = request.into_inner();
        self.check_job(&r.job)?;
        let d = self
            .shared
            .with(|c, now| c.checkpoint(r.worker_id, r.generation, r.step, r.r#final, now))?;
        Ok(ack(d))
    }

    async fn report_fault(
        &self,
        request: Request<v1::FaultReport>,
    ) -> Result<Response<v1::Ack>, Status> {
        let r = request.into_inner();
        self.check_job(&r.job)?;
        tracing::warn!(worker_id = r.worker_id, generation = r.generation, fatal = r.fatal, reason = %r.reason, "fault reported");
        let d = self.shared.with(|c, now| {
            c.fault(
                r.worker_id,
                r.generation,
                &r.reason,
                r.fatal,
                r.leaving,
                now,
            )
        })?;
        Ok(ack(d))
    }

    async fn get_status(
        &self,
        _request: Request<v1::StatusRequest>,
    ) -> Result<Response<v1::JobStatus>, Status> {
        let c = self.shared.core.lock().expect("state");
        Ok(Response::new(status_of(&c, Instant::now())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(cluster: ClusterConfig) -> JobSpec {
        JobSpec {
            job_id: "j".into(),
            cluster,
            job_toml: String::new(),
            data: "data".into(),
            run: "run".into(),
            max_steps: None,
            deadline_unix_s: None,
            cluster_overrides: Default::default(),
        }
    }

    /// The run folder's default chunk is the collective's largest, and a larger one is
    /// refused before any worker joins.
    #[test]
    fn chunks_the_collective_cannot_carry_are_refused() {
        let run = Location::parse("memory://gatherable").unwrap();
        let default = ClusterConfig::default();
        assert_eq!(default.chunk_floats, osrt_proto::MAX_CHUNK_FLOATS);
        assert!(gatherable(&spec(default.clone()), &run).is_ok());
        let big = ClusterConfig {
            chunk_floats: osrt_proto::MAX_CHUNK_FLOATS + 1,
            ..default
        };
        let e = gatherable(&spec(big), &run).unwrap_err().to_string();
        assert!(e.contains("exceeds the collective's chunk"), "{e}");
    }
}
