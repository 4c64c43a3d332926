//! The coordinator's state machine.
//!
//! ```text
//!   Waiting ──(≥ min_workers for join_grace, or max_workers)──▶ Running(generation g)
//!   Running ──(member lost / joined / failed round)──▶ Waiting ──▶ Running(g + 1)
//!   Running ──(final checkpoint committed)──▶ Done
//!   Running ──(replicas diverged)──▶ Waiting (counts as a restart)
//!   any ──(max_restarts exceeded / fatal fault)──▶ Failed
//! ```
//!
//! A new generation restarts every member from the newest committed checkpoint; metrics
//! records past that checkpoint belong to the abandoned timeline and are dropped, so
//! `metrics.jsonl` always describes the steps the final weights went through.

use osrt_proto::convert::{Directive, PlanState, WorkerPlan};
use osrt_proto::{MAX_RECORDS_PER_REPORT, PROTOCOL_VERSION};
use osrt_run::ClusterOverrides;
use osrt_run::{ClusterConfig, MetricsRecord};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::time::{Duration, Instant};
use tonic::Status;

/// Steps whose parameter hashes the coordinator holds while waiting for every rank's.
pub const MAX_PENDING_HASH_STEPS: usize = 64;

/// What the job is: fixed for its lifetime (a `--resume` may extend the limits).
#[derive(Debug, Clone)]
pub struct JobSpec {
    pub job_id: String,
    /// The job config's `[cluster]` table: all of it the coordinator reads.
    pub cluster: ClusterConfig,
    /// The exact TOML handed to workers (its hash is checked against checkpoints).
    pub job_toml: String,
    pub data: String,
    pub run: String,
    pub max_steps: Option<u64>,
    pub deadline_unix_s: Option<f64>,
    /// Membership limits from the command line: they win over the run folder's
    /// `config.toml` when a job is resumed (that file's text, whose hash checkpoints
    /// carry, stays as it is).
    pub cluster_overrides: ClusterOverrides,
}

/// The part of the state kept in `RUN/job.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Persisted {
    pub job_id: String,
    pub data: String,
    pub max_steps: Option<u64>,
    pub deadline_unix_s: Option<f64>,
    pub generation: u64,
    pub restarts: u32,
    pub last_checkpoint: Option<u64>,
    pub hash_checks: u64,
    /// `waiting`, `running`, `done` or `failed`.
    pub state: String,
    pub message: String,
}

/// A worker's progress report: its step, optionally its parameter hash, and (rank 0)
/// metrics records.
#[derive(Debug, Clone)]
pub struct Progress {
    pub worker_id: u64,
    pub generation: u64,
    pub rank: usize,
    pub step: u64,
    pub param_hash: Option<String>,
    pub records: Vec<String>,
}

#[derive(Debug, Clone)]
pub struct Member {
    pub id: u64,
    pub name: String,
    pub addr: String,
    pub threads: u32,
    /// The worker process's random instance (0: none sent).
    pub instance: u64,
    pub last_seen: Instant,
    pub step: u64,
}

/// What a worker registers with.
#[derive(Debug, Clone)]
pub struct Registration {
    pub protocol_version: u32,
    /// For logs (host and pid); not an identity.
    pub name: String,
    /// `http(s)://host:port` of the worker's Collective service.
    pub addr: String,
    pub threads: u32,
    /// Random per worker process (0: none): a repeated registration of one instance is
    /// the same member.
    pub instance: u64,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Phase {
    Waiting { since: Instant },
    Running,
    Done,
    Failed(String),
}

#[derive(Debug)]
pub struct Core {
    pub spec: JobSpec,
    /// The job's global batch, where its config says: the most workers a step can feed.
    pub batch: Option<usize>,
    pub phase: Phase,
    pub generation: u64,
    /// Worker ids in ring order (rank = index) of the current generation.
    pub ring: Vec<u64>,
    /// Rank 0 of the generation that ended, until the next forms: its late reports' records
    /// still count, as its late checkpoints do.
    ended_rank0: Option<u64>,
    pub members: BTreeMap<u64, Member>,
    /// This coordinator process's incarnation, the high 32 bits of every id it issues:
    /// a worker id from an earlier incarnation (a coordinator restarted while the
    /// worker was paused) is unknown here, so its holder registers again instead of
    /// acting as another member.
    incarnation: u32,
    /// The low 32 bits of the next id.
    next_id: u32,
    pub restarts: u32,
    /// `restarts` when this invocation began: `cluster.max_restarts` bounds the restarts
    /// of one invocation (a `--resume` gets a fresh budget; a coordinator restarted
    /// after a crash does not).
    restarts_before: u32,
    pub last_checkpoint: Option<u64>,
    /// The checkpoint the current generation started from (fixed at formation: a late
    /// report of an abandoned generation's checkpoint must not split the ring).
    pub resume_step: Option<u64>,
    /// The generation's checkpoints past `resume_step` (an abandoned timeline's) are
    /// still to be discarded by the service, which verifies `resume_step` first: no plan
    /// goes out meanwhile, so no rank of the new generation meets them.
    pub discard_pending: bool,
    pub hash_checks: u64,
    /// step → rank → parameter hash, until every rank has reported.
    hashes: BTreeMap<u64, BTreeMap<usize, String>>,
    /// `(step, JSON line)` of the records not yet handed to both `metrics.jsonl` and the
    /// event log: the others live in the run folder only, so memory stays bounded however
    /// long the job runs.
    pub records: Vec<(u64, String)>,
    /// The newest step taken (whether still in `records` or not), and its lines: a report
    /// resent after a lost answer repeats them. Closed: the step is a checkpoint a
    /// generation starts from, so no line of it is new.
    last_step: Option<u64>,
    newest: Vec<String>,
    newest_closed: bool,
    pub last_record: String,
    /// Something persisted changed since the last save.
    pub dirty_job: bool,
    pub dirty_metrics: bool,
    /// Records handed to `metrics.jsonl` (a prefix of `records`), at most what step it
    /// holds, and the cut it must make first (records it holds were dropped).
    flushed: usize,
    metrics_last: Option<u64>,
    metrics_cut: Option<Option<u64>>,
    /// The same for the TensorBoard event log, and the training record last sent to it
    /// (step times are differences).
    events_sent: usize,
    events_last: Option<u64>,
    events_cut: Option<Option<u64>>,
    previous_train: Option<(u64, String)>,
}

/// What the TensorBoard event log must do to match `records`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct EventsWork {
    /// Cut out the events past this step (`Some(None)`: all of them) first.
    pub cut_after: Option<Option<u64>>,
    /// Record lines to add, in order.
    pub records: Vec<String>,
    /// The training record before them (step times are differences).
    pub previous_train: Option<String>,
}

/// How to bring `metrics.jsonl` up to date.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct MetricsWrite {
    /// Cut out the records past this step (`Some(None)`: all of them) first.
    pub cut_after: Option<Option<u64>>,
    /// `(step, line)` to append, in order.
    pub lines: Vec<(u64, String)>,
}

/// The smaller of two cuts (`None` inside: cut everything).
fn earlier_cut(a: Option<Option<u64>>, keep: Option<u64>) -> Option<Option<u64>> {
    Some(match a {
        Some(earlier) => earlier.min(keep),
        None => keep,
    })
}

/// The `step` of a metrics record line (`None`: not a record).
pub fn record_step(line: &str) -> Option<u64> {
    MetricsRecord::parse(line).map(|r| r.step())
}

impl Core {
    /// A coordinator of `spec` with a random incarnation.
    pub fn new(spec: JobSpec, now: Instant) -> Self {
        Self::with_incarnation(spec, rand::random(), now)
    }

    pub fn with_incarnation(spec: JobSpec, incarnation: u32, now: Instant) -> Self {
        Self {
            batch: ClusterConfig::global_batch_of(&spec.job_toml),
            spec,
            phase: Phase::Waiting { since: now },
            generation: 0,
            ring: Vec::new(),
            ended_rank0: None,
            members: BTreeMap::new(),
            incarnation,
            next_id: 1,
            restarts: 0,
            restarts_before: 0,
            last_checkpoint: None,
            resume_step: None,
            discard_pending: false,
            hash_checks: 0,
            hashes: BTreeMap::new(),
            records: Vec::new(),
            last_step: None,
            newest: Vec::new(),
            newest_closed: false,
            last_record: String::new(),
            dirty_job: true,
            dirty_metrics: false,
            flushed: 0,
            metrics_last: None,
            metrics_cut: None,
            events_sent: 0,
            events_last: None,
            events_cut: None,
            previous_train: None,
        }
    }

    /// Takes what the event log must do to match the records.
    pub fn events_work(&mut self) -> EventsWork {
        let sent = self.events_sent.min(self.records.len());
        let new = &self.records[sent..];
        let work = EventsWork {
            cut_after: self.events_cut.take(),
            records: new.iter().map(|(_, l)| l.clone()).collect(),
            previous_train: self.previous_train.as_ref().map(|(_, l)| l.clone()),
        };
        if let Some((s, l)) = new
            .iter()
            .rev()
            .find(|(_, l)| matches!(MetricsRecord::parse(l), Some(MetricsRecord::Train(_))))
        {
            self.previous_train = Some((*s, l.clone()));
        }
        if let Some((s, _)) = new.last() {
            self.events_last = Some(*s);
        }
        self.events_sent = self.records.len();
        self.forget_delivered();
        work
    }

    /// Whether the event log lags the records.
    pub fn events_pending(&self) -> bool {
        self.events_cut.is_some() || self.events_sent != self.records.len()
    }

    /// The event log (just opened) lacks `backlog`, records `metrics.jsonl` holds (from
    /// the step its events end at up to the checkpoint); `previous_train` is the training
    /// record before them.
    pub fn events_resume(
        &mut self,
        backlog: Vec<(u64, String)>,
        previous_train: Option<(u64, String)>,
    ) {
        self.records = backlog;
        self.flushed = self.records.len();
        self.events_sent = 0;
        self.events_cut = None;
        self.events_last = None;
        self.previous_train = previous_train;
    }

    /// The write that brings `metrics.jsonl` up to date; counts the records as handed
    /// over (the writer keeps what it could not write yet).
    pub fn metrics_write(&mut self) -> MetricsWrite {
        let write = MetricsWrite {
            cut_after: self.metrics_cut.take(),
            lines: self.records[self.flushed.min(self.records.len())..].to_vec(),
        };
        if let Some((s, _)) = write.lines.last() {
            self.metrics_last = Some(*s);
        }
        self.flushed = self.records.len();
        self.dirty_metrics = false;
        self.forget_delivered();
        write
    }

    /// Drops the records both the metrics and the event log have taken.
    fn forget_delivered(&mut self) {
        let n = self.flushed.min(self.events_sent).min(self.records.len());
        self.records.drain(..n);
        self.flushed -= n;
        self.events_sent -= n;
    }

    /// Drops the records past `keep` (`None`: all) wherever they are: in memory, and by a
    /// cut in `metrics.jsonl` and the event log where they may have reached them.
    fn drop_records_after(&mut self, keep: Option<u64>) {
        let past = |s: u64| keep.is_none_or(|k| s > k);
        // Records are in step order: those kept are a prefix.
        self.records.retain(|(s, _)| !past(*s));
        self.flushed = self.flushed.min(self.records.len());
        self.events_sent = self.events_sent.min(self.records.len());
        if self.metrics_last.is_some_and(past) {
            self.metrics_cut = earlier_cut(self.metrics_cut, keep);
            self.metrics_last = keep;
            self.dirty_metrics = true;
        }
        if self.events_last.is_some_and(past) {
            self.events_cut = earlier_cut(self.events_cut, keep);
            self.events_last = keep;
        }
        if self.previous_train.as_ref().is_some_and(|(s, _)| past(*s)) {
            self.previous_train = None;
        }
        if self.last_step.is_some_and(past) {
            self.last_step = keep;
            self.newest.clear();
            self.newest_closed = true;
        }
    }

    /// Continues a job from its persisted state and records (a restarted coordinator, or
    /// `resume`: a new invocation, with a fresh restart budget); `checkpoint` is the
    /// newest committed checkpoint found in the store.
    pub fn restore(
        &mut self,
        p: &Persisted,
        last_record: Option<u64>,
        checkpoint: Option<u64>,
        resume: bool,
        now: Instant,
    ) {
        self.generation = p.generation;
        self.restarts = p.restarts;
        self.restarts_before = if resume { p.restarts } else { 0 };
        self.hash_checks = p.hash_checks;
        self.last_checkpoint = checkpoint;
        // The file may hold records past the checkpoint (or a line a crash cut short): cut
        // once. Without a checkpoint the job starts over, and so does its record.
        self.records.clear();
        self.last_step = last_record.min(checkpoint);
        self.newest.clear();
        self.newest_closed = true;
        self.metrics_last = last_record;
        self.metrics_cut = Some(checkpoint);
        self.phase = Phase::Waiting { since: now };
        self.dirty_job = true;
        self.dirty_metrics = true;
    }

    pub fn persisted(&self) -> Persisted {
        let (state, message) = match &self.phase {
            Phase::Waiting { .. } => ("waiting", String::new()),
            Phase::Running => ("running", String::new()),
            Phase::Done => ("done", String::new()),
            Phase::Failed(m) => ("failed", m.clone()),
        };
        Persisted {
            job_id: self.spec.job_id.clone(),
            data: self.spec.data.clone(),
            max_steps: self.spec.max_steps,
            deadline_unix_s: self.spec.deadline_unix_s,
            generation: self.generation,
            restarts: self.restarts,
            last_checkpoint: self.last_checkpoint,
            hash_checks: self.hash_checks,
            state: state.into(),
            message,
        }
    }

    pub fn is_over(&self) -> bool {
        matches!(self.phase, Phase::Done | Phase::Failed(_))
    }

    /// Fails the job for a reason found outside the protocol (the local launcher's
    /// verdict on its worker processes); nothing once the job is over.
    pub fn fail(&mut self, reason: String) {
        if !self.is_over() {
            tracing::error!(%reason, "job failed");
            self.phase = Phase::Failed(reason);
            self.dirty_job = true;
        }
    }

    /// Abandons the current generation: everyone restarts from the last checkpoint.
    fn regenerate(&mut self, reason: &str, counts_as_restart: bool, now: Instant) {
        if self.is_over() {
            return;
        }
        tracing::warn!(generation = self.generation, reason, "generation ends");
        self.ended_rank0 = self.ring.first().copied();
        self.ring.clear();
        self.hashes.clear();
        self.phase = Phase::Waiting { since: now };
        self.dirty_job = true;
        if counts_as_restart {
            self.restarts += 1;
            let max = self.spec.cluster.max_restarts;
            if self.restarts - self.restarts_before > max {
                self.fail(format!(
                    "{reason}; gave up after {max} restarts (cluster.max_restarts)"
                ));
            }
        }
    }

    /// Admits a worker and returns its id. A registration of an instance already a member
    /// (its first reply was lost, and the worker asked again) returns that member's id:
    /// a second member would be a ghost the ring waits for until its heartbeat times out.
    pub fn register(&mut self, r: Registration, now: Instant) -> Result<u64, Status> {
        let Registration {
            protocol_version,
            name,
            addr,
            threads,
            instance,
        } = r;
        if protocol_version != PROTOCOL_VERSION {
            return Err(Status::failed_precondition(format!(
                "protocol version {protocol_version}, this coordinator speaks {PROTOCOL_VERSION}"
            )));
        }
        if addr.is_empty() || !addr.starts_with("http") {
            return Err(Status::invalid_argument(format!(
                "collective address `{addr}` is not an http(s) URL"
            )));
        }
        let host = addr.split("://").nth(1).unwrap_or("");
        if ["0.0.0.0:", "[::]:"].iter().any(|a| host.starts_with(a)) {
            // Every peer that dialled it would reach itself.
            return Err(Status::invalid_argument(format!(
                "collective address `{addr}` names no host: advertise the address other \
                 workers reach this one at (--advertise)"
            )));
        }
        if self.is_over() {
            return Err(Status::failed_precondition("the job is over"));
        }
        if let Some(m) = self
            .members
            .values_mut()
            .find(|m| instance != 0 && m.instance == instance)
        {
            m.last_seen = now;
            tracing::info!(worker_id = m.id, %name, "worker registered again (a lost reply)");
            return Ok(m.id);
        }
        let max = self.spec.cluster.max_workers;
        if self.members.len() >= max {
            return Err(Status::resource_exhausted(format!(
                "the job already has {max} workers (cluster.max_workers)"
            )));
        }
        if let Some(b) = self.batch
            && self.members.len() >= b
        {
            return Err(Status::resource_exhausted(format!(
                "the job already has {b} workers: its global batch of {b} scenes \
                 (train.batch_size) feeds at most {b}, one scene each"
            )));
        }
        let id = (u64::from(self.incarnation) << 32) | u64::from(self.next_id);
        // 2^32 registrations in one incarnation would wrap onto a live id; refuse instead.
        self.next_id = self.next_id.checked_add(1).ok_or_else(|| {
            Status::resource_exhausted("this coordinator has issued 2^32 worker ids")
        })?;
        tracing::info!(worker_id = id, %name, %addr, threads, "worker registered");
        self.members.insert(
            id,
            Member {
                id,
                name,
                addr,
                threads,
                instance,
                last_seen: now,
                step: 0,
            },
        );
        if self.phase == Phase::Running {
            self.regenerate(&format!("worker {id} joined"), false, now);
        }
        Ok(id)
    }

    fn member(&mut self, id: u64, now: Instant) -> Result<&mut Member, Status> {
        let m = self.members.get_mut(&id).ok_or_else(|| {
            Status::not_found(format!(
                "unknown worker {id}: register again (the coordinator may have restarted)"
            ))
        })?;
        m.last_seen = now;
        Ok(m)
    }

    fn directive_for(&self, id: u64, generation: u64) -> Directive {
        match self.phase {
            Phase::Done | Phase::Failed(_) => Directive::Stop,
            Phase::Running if generation == self.generation && self.ring.contains(&id) => {
                Directive::Continue
            }
            _ => Directive::Restart,
        }
    }

    pub fn heartbeat(
        &mut self,
        id: u64,
        generation: u64,
        step: u64,
        now: Instant,
    ) -> Result<(Directive, u64), Status> {
        self.member(id, now)?.step = step;
        Ok((self.directive_for(id, generation), self.generation))
    }

    /// The checkpoints past the generation's `resume_step` are gone: plans go out.
    pub fn discarded(&mut self) {
        self.discard_pending = false;
    }

    /// The plan of member `id` if a generation newer than `after` includes it.
    pub fn plan(&mut self, id: u64, after: u64, now: Instant) -> Result<PlanState, Status> {
        self.member(id, now)?;
        Ok(match &self.phase {
            Phase::Done => PlanState::Done,
            Phase::Failed(m) => PlanState::Failed(m.clone()),
            Phase::Running if self.generation > after && !self.discard_pending => {
                match self.ring.iter().position(|&m| m == id) {
                    Some(rank) => PlanState::Running(WorkerPlan {
                        job: self.spec.job_id.clone(),
                        generation: self.generation,
                        rank,
                        peers: self
                            .ring
                            .iter()
                            .map(|m| self.members[m].addr.clone())
                            .collect(),
                        job_config_toml: self.spec.job_toml.clone(),
                        data: self.spec.data.clone(),
                        run: self.spec.run.clone(),
                        resume_step: self.resume_step,
                        max_steps: self.spec.max_steps,
                        deadline_unix_s: self.spec.deadline_unix_s,
                        restarts: self.restarts,
                    }),
                    None => PlanState::Waiting,
                }
            }
            _ => PlanState::Waiting,
        })
    }

    /// Times out silent members and starts a generation when enough are present.
    pub fn tick(&mut self, now: Instant) {
        if self.is_over() {
            return;
        }
        let timeout: Duration = self.spec.cluster.heartbeat_timeout();
        let lost: Vec<u64> = self
            .members
            .values()
            .filter(|m| now.duration_since(m.last_seen) > timeout)
            .map(|m| m.id)
            .collect();
        for id in lost {
            let m = self.members.remove(&id).expect("listed");
            tracing::warn!(worker_id = id, name = %m.name, "worker lost (no heartbeat)");
            if self.phase == Phase::Running && self.ring.contains(&id) {
                self.regenerate(
                    &format!(
                        "worker {id} ({}) lost: no heartbeat for {timeout:?}",
                        m.name
                    ),
                    true,
                    now,
                );
            }
        }
        if let Phase::Waiting { since } = self.phase {
            // Only members heard from since the last generation ended take part: a peer
            // that just failed a round may be dead but not yet timed out.
            let eligible: Vec<u64> = self
                .members
                .values()
                .filter(|m| m.last_seen >= since)
                .map(|m| m.id)
                .collect();
            let c = &self.spec.cluster;
            let n = eligible.len();
            let grace = c.join_grace();
            let waited = now.duration_since(since);
            let limit = c.max_workers.min(self.batch.unwrap_or(usize::MAX));
            if n >= limit || (n >= c.min_workers && waited >= grace) {
                // A ring larger than the batch could not give every rank a scene.
                self.form(eligible.into_iter().take(limit).collect());
            } else if waited > c.wait_timeout() {
                let names: Vec<&str> = self.members.values().map(|m| m.name.as_str()).collect();
                let (min, limit) = (c.min_workers, c.wait_timeout_s);
                self.fail(format!(
                    "waited {limit} s (cluster.wait_timeout_s) for {min} workers \
                     (cluster.min_workers); {n} took part: [{}]",
                    names.join(", ")
                ));
            }
        }
    }

    fn form(&mut self, ring: Vec<u64>) {
        self.generation += 1;
        self.ended_rank0 = None;
        self.ring = ring;
        self.resume_step = self.last_checkpoint;
        self.discard_pending = true;
        self.phase = Phase::Running;
        self.hashes.clear();
        self.drop_records_after(self.last_checkpoint);
        self.dirty_job = true;
        tracing::info!(
            generation = self.generation,
            world = self.ring.len(),
            resume_step = ?self.last_checkpoint,
            "generation starts"
        );
    }

    /// Stores rank 0's record lines, in order, skipping those already held.
    fn take_records(&mut self, records: Vec<String>) -> Result<(), Status> {
        // Every line is checked before any is stored: a line that would split
        // `metrics.jsonl` (and lose records past it when a restart reads the file) is
        // refused, and a refused report stores none of its records.
        let mut steps = Vec::with_capacity(records.len());
        for (i, line) in records.iter().enumerate() {
            let record = osrt_run::records::validate_line(line)
                .map_err(|e| Status::invalid_argument(format!("record {i} of the report: {e}")))?;
            steps.push(record.step());
        }
        for (line, s) in records.into_iter().zip(steps) {
            // A report resent after a lost answer repeats records already taken: rank 0
            // sends them in step order, so they are older than the newest step, or among
            // its lines.
            match self.last_step {
                Some(l) if s < l => continue,
                Some(l) if s == l && (self.newest_closed || self.newest.contains(&line)) => {
                    continue;
                }
                Some(l) if s == l => {}
                _ => {
                    self.newest.clear();
                    self.newest_closed = false;
                }
            }
            if self.newest.len() < MAX_RECORDS_PER_REPORT {
                self.newest.push(line.clone());
            }
            self.last_step = Some(s);
            self.last_record = line.clone();
            self.records.push((s, line));
            self.dirty_metrics = true;
        }
        Ok(())
    }

    pub fn progress(&mut self, p: Progress, now: Instant) -> Result<Directive, Status> {
        let Progress {
            worker_id: id,
            generation,
            rank,
            step,
            param_hash,
            records,
        } = p;
        self.member(id, now)?.step = step;
        let d = self.directive_for(id, generation);
        // The last generation's final reports can arrive after rank 0 committed the final
        // checkpoint (Done): they still count, and a divergence still fails the job.
        let finishing = self.phase == Phase::Done && generation == self.generation;
        if d != Directive::Continue && !finishing {
            // Rank 0 of the generation that just ended: a checkpoint it commits now is
            // still accepted (`checkpoint`), so the records before it must be too, or the
            // checkpoint would leave a gap in `metrics.jsonl` (the worker counts a report
            // the coordinator answered as delivered). The next generation drops those
            // past its checkpoint.
            if generation == self.generation
                && rank == 0
                && self.ended_rank0 == Some(id)
                && records.len() <= MAX_RECORDS_PER_REPORT
            {
                self.take_records(records)?;
            }
            return Ok(d);
        }
        if self.ring.get(rank) != Some(&id) {
            return Err(Status::invalid_argument(format!(
                "worker {id} reports rank {rank}, the ring has it at {:?}",
                self.ring.iter().position(|&m| m == id)
            )));
        }
        if records.len() > MAX_RECORDS_PER_REPORT {
            return Err(Status::invalid_argument(format!(
                "{} records in one report, at most {MAX_RECORDS_PER_REPORT}",
                records.len()
            )));
        }
        if rank == 0 {
            self.take_records(records)?;
        }
        if let Some(h) = param_hash {
            let world = self.ring.len();
            // A rank whose reports never arrive leaves every step short: the oldest go, so
            // the map stays bounded whatever the job's length.
            if !self.hashes.contains_key(&step) {
                while self.hashes.len() >= MAX_PENDING_HASH_STEPS {
                    self.hashes.pop_first();
                }
            }
            let entry = self.hashes.entry(step).or_default();
            entry.insert(rank, h);
            if entry.len() == world {
                let all = self.hashes.remove(&step).expect("present");
                // Ranks report steps in order: an earlier step still short of a rank's
                // hash (its report was lost) can never complete, and would stay forever.
                self.hashes.retain(|&s, _| s > step);
                let first = all[&0].clone();
                if all.values().all(|h| *h == first) {
                    self.hash_checks += 1;
                } else {
                    let listing: Vec<String> =
                        all.iter().map(|(r, h)| format!("rank {r}: {h}")).collect();
                    let reason = format!(
                        "replicas diverged at step {step}: parameter hashes {}",
                        listing.join(", ")
                    );
                    if self.phase == Phase::Done {
                        // The final checkpoint holds one replica's weights: they cannot
                        // be trusted, and there is no generation left to restart.
                        tracing::error!(%reason, "job failed");
                        self.phase = Phase::Failed(reason);
                        self.dirty_job = true;
                        return Ok(Directive::Stop);
                    }
                    // A replica that computed differently (a flipped bit, a faulty
                    // device) is not the job's fault: everyone restarts from the last
                    // checkpoint, within the restart budget.
                    self.regenerate(&reason, true, now);
                    return Ok(self.directive_for(id, generation));
                }
                self.dirty_job = true;
            }
        }
        Ok(d)
    }

    pub fn checkpoint(
        &mut self,
        id: u64,
        generation: u64,
        step: u64,
        is_final: bool,
        now: Instant,
    ) -> Result<Directive, Status> {
        self.member(id, now)?;
        if generation != self.generation {
            // An abandoned generation's checkpoint (committed just before it was aborted):
            // valid, but not on the timeline the current generation follows.
            tracing::info!(
                step,
                generation,
                "checkpoint of an earlier generation ignored"
            );
            return Ok(self.directive_for(id, generation));
        }
        if self.last_checkpoint.is_none_or(|c| step > c) {
            self.last_checkpoint = Some(step);
            self.dirty_job = true;
        }
        if is_final && generation == self.generation && self.phase == Phase::Running {
            tracing::info!(step, "final checkpoint committed: job done");
            self.phase = Phase::Done;
            self.dirty_job = true;
            self.dirty_metrics = true;
        }
        Ok(self.directive_for(id, generation))
    }

    /// A worker's fault; `leaving`: the worker is stopping and leaves the membership now
    /// (a generation it is part of ends, as it would after the heartbeat timeout).
    pub fn fault(
        &mut self,
        id: u64,
        generation: u64,
        reason: &str,
        fatal: bool,
        leaving: bool,
        now: Instant,
    ) -> Result<Directive, Status> {
        self.member(id, now)?;
        let msg = format!("worker {id}: {reason}");
        let in_ring = self.phase == Phase::Running && self.ring.contains(&id);
        if leaving {
            self.members.remove(&id);
            tracing::info!(worker_id = id, "worker left");
        }
        if fatal {
            self.fail(msg);
        } else if in_ring && (leaving || generation == self.generation) {
            self.regenerate(&msg, true, now);
        }
        Ok(self.directive_for(id, generation))
    }
}

#[cfg(test)]
mod record_lines;
#[cfg(test)]
mod tests;
