//! The Coordinator gRPC service over a shared [`Core`], the monitor loop (heartbeat
//! timeouts, generation formation) and persistence of `job.json` and `metrics.jsonl`.

use crate::core::{Core, JobSpec, Persisted, Phase, Progress, Registration};
use crate::error::CoordinatorError;
use crate::events::Events;
use crate::persist::Persister;
use osrt_proto::auth::{CheckToken, Token};
use osrt_proto::convert::Directive;
use osrt_proto::v1;
use osrt_proto::v1::coordinator_server::{self, CoordinatorServer};
use osrt_run::lease::{self, Holder, Keeper, Lease, LeaseTiming};
use osrt_run::metrics_log::MetricsLog;
use osrt_run::{
    CONFIG_FILE, ClusterConfig, INFO_FILE, METRICS_FILE, RunError, RunInfo, checkpoint, read_file,
    write_file,
};
use osrt_store::Location;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::sync::Notify;
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Response, Status};

use osrt_run::JOB_FILE;

/// Largest message the coordinator takes or sends.
const MAX_MESSAGE_BYTES: usize = 16 << 20;

/// The longest a call to the coordinator may last (a plan's long poll takes 2 s).
const CALL_LIMIT: Duration = Duration::from_secs(60);

/// How long a plan request waits for a change before answering `Waiting`.
const PLAN_POLL: Duration = Duration::from_secs(2);

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

    /// The job's state from the run folder (read again under the lease: the folder's
    /// previous holder may have written last), or a new job's; `last_record`: the newest
    /// step of the folder's metrics records.
    async fn open_core(
        mut spec: JobSpec,
        run: &Location,
        resume: bool,
        last_record: Option<u64>,
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
            None if resume => Self::continue_imported(spec, &run, last_record, now).await?,
            None => Self::create(spec, &run, last_record, now).await?,
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
                // The job continues from the checkpoint `job.json` recorded (or the newest
                // older one that verifies), and never from past the last step whose records
                // reached the store (flushed every 1 s, 5 s on object stores): the steps after
                // it are replayed and their records sent again, so none is missing.
                // No record at all: the job starts over.
                let at_most = checkpoint::resume_bound(last_record, p.last_checkpoint);
                let checkpoint = checkpoint::latest_verified(&run, Some(at_most)).await?;
                tracing::info!(
                    job = %p.job_id,
                    generation = p.generation,
                    checkpoint = ?checkpoint,
                    "continuing the job in the run folder"
                );
                let mut core = Core::new(spec, now);
                core.restore(&p, last_record, checkpoint, resume, now);
                core
            }
        };
        Ok(core)
    }

    /// `--resume` on a folder without a job: one `osrt import-checkpoint` wrote (its
    /// config and a checkpoint of a model trained elsewhere, no records) starts a job
    /// from that checkpoint, with the folder's config; its records begin at that step.
    /// Anything else has no job to resume.
    async fn continue_imported(
        mut spec: JobSpec,
        run: &Location,
        last_record: Option<u64>,
        now: Instant,
    ) -> Result<Core, CoordinatorError> {
        let no_job = || {
            run_err(
                run,
                JOB_FILE,
                "--resume: no job to resume in this run folder",
            )
        };
        let Some(text) = read_file(run, CONFIG_FILE).await? else {
            return Err(no_job());
        };
        if last_record.is_some() {
            return Err(no_job());
        }
        let Some(step) = checkpoint::latest_verified(run, None).await? else {
            return Err(no_job());
        };
        let text = String::from_utf8_lossy(&text).into_owned();
        spec.cluster = ClusterConfig::from_job_toml(&run.describe(&run.path(CONFIG_FILE)), &text)?;
        spec.cluster_overrides.apply(&mut spec.cluster);
        spec.cluster.validate()?;
        spec.job_toml = text;
        gatherable(&spec, run)?;
        let mut info: RunInfo = match read_file(run, INFO_FILE).await? {
            Some(b) => serde_json::from_slice(&b)
                .map_err(|e| run_err(run, INFO_FILE, format!("unreadable: {e}")))?,
            None => return Err(no_job()),
        };
        info.data = spec.data.clone();
        info.workers = spec.cluster.min_workers;
        let bytes = serde_json::to_vec_pretty(&info).expect("serialises");
        write_file(run, INFO_FILE, bytes).await?;
        tracing::info!(
            checkpoint = step,
            "starting the job from the imported checkpoint"
        );
        let p = Persisted {
            job_id: spec.job_id.clone(),
            data: spec.data.clone(),
            max_steps: spec.max_steps,
            deadline_unix_s: spec.deadline_unix_s,
            generation: 0,
            restarts: 0,
            last_checkpoint: Some(step),
            hash_checks: 0,
            state: "waiting".into(),
            message: String::new(),
        };
        let mut core = Core::new(spec, now);
        // The folder's history begins at the checkpoint: nothing before it is missing.
        core.restore(&p, Some(step), Some(step), true, now);
        Ok(core)
    }

    /// A new job in an empty run folder: refused before anything is written if it cannot
    /// run; then its config and run info are written.
    async fn create(
        spec: JobSpec,
        run: &Location,
        last_record: Option<u64>,
        now: Instant,
    ) -> Result<Core, CoordinatorError> {
        let metrics = read_file(run, METRICS_FILE).await?;
        if last_record.is_some() || metrics.is_some_and(|m| !m.is_empty()) {
            return Err(run_err(
                run,
                METRICS_FILE,
                "the run folder already holds a run; choose a new --run or pass --resume",
            ));
        }
        if !checkpoint::list_steps(run).await?.is_empty() {
            return Err(run_err(
                run,
                "checkpoints",
                "the run folder holds checkpoints (a model imported with osrt \
                 import-checkpoint?): pass --resume to continue from them, or choose a new --run",
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
            horizon: None,
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
        let health_service = osrt_proto::server::CheckOnly::server(&[
            osrt_proto::v1::coordinator_server::SERVICE_NAME,
        ]);
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
        let mut builder = osrt_proto::server::builder(tls.as_ref(), CALL_LIMIT).map_err(|e| {
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
