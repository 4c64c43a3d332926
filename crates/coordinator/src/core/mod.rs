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

use osrt_run::cluster_config::{ClusterConfig, ClusterOverrides};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::time::Instant;

mod membership;
mod records;
mod reports;

pub use records::{EventsWork, MetricsWrite, record_step};

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
}

#[cfg(test)]
mod record_lines;
#[cfg(test)]
mod tests;
