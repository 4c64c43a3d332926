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

use osrt_proto::PROTOCOL_VERSION;
use osrt_proto::convert::{Directive, PlanState, WorkerPlan};
use osrt_trainer::JobConfig;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::time::{Duration, Instant};
use tonic::Status;

/// What the job is: fixed for its lifetime (a `--resume` may extend the limits).
#[derive(Debug, Clone)]
pub struct JobSpec {
    pub job_id: String,
    pub job: JobConfig,
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

/// `--min-workers`, `--max-workers`, `--max-restarts`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ClusterOverrides {
    pub min_workers: Option<usize>,
    pub max_workers: Option<usize>,
    pub max_restarts: Option<u32>,
}

impl ClusterOverrides {
    /// Applies the limits given; without an explicit `max_workers`, the config's is
    /// raised to `min_workers` where it is lower.
    pub fn apply(&self, c: &mut osrt_trainer::ClusterConfig) {
        if let Some(v) = self.min_workers {
            c.min_workers = v;
        }
        match self.max_workers {
            Some(v) => c.max_workers = v,
            None => c.max_workers = c.max_workers.max(c.min_workers),
        }
        if let Some(v) = self.max_restarts {
            c.max_restarts = v;
        }
    }
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
    pub last_seen: Instant,
    pub step: u64,
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
    pub phase: Phase,
    pub generation: u64,
    /// Worker ids in ring order (rank = index) of the current generation.
    pub ring: Vec<u64>,
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
    pub hash_checks: u64,
    /// step → rank → parameter hash, until every rank has reported.
    hashes: BTreeMap<u64, BTreeMap<usize, String>>,
    /// `(step, JSON line)` of metrics.jsonl.
    pub records: Vec<(u64, String)>,
    pub last_record: String,
    /// Something persisted changed since the last save.
    pub dirty_job: bool,
    pub dirty_metrics: bool,
    /// Records `metrics.jsonl` holds (a prefix of `records`), and whether the file must be
    /// written whole (records were dropped, or an append may have failed half-way).
    flushed: usize,
    rewrite: bool,
}

/// How to bring `metrics.jsonl` up to date.
#[derive(Debug, Clone, PartialEq)]
pub enum MetricsWrite {
    /// Append these lines (the file holds the ones before).
    Append(String),
    /// Write the file whole.
    Whole(String),
}

/// Records one progress report may carry (a worker holds at most as many unsent).
pub const MAX_RECORDS_PER_CALL: usize = 10_000;

/// The `step` of a metrics record line.
pub fn record_step(line: &str) -> Option<u64> {
    serde_json::from_str::<serde_json::Value>(line)
        .ok()?
        .get("step")?
        .as_u64()
}

impl Core {
    /// A coordinator of `spec` with a random incarnation.
    pub fn new(spec: JobSpec, now: Instant) -> Self {
        Self::with_incarnation(spec, rand::random(), now)
    }

    pub fn with_incarnation(spec: JobSpec, incarnation: u32, now: Instant) -> Self {
        Self {
            spec,
            phase: Phase::Waiting { since: now },
            generation: 0,
            ring: Vec::new(),
            members: BTreeMap::new(),
            incarnation,
            next_id: 1,
            restarts: 0,
            restarts_before: 0,
            last_checkpoint: None,
            resume_step: None,
            hash_checks: 0,
            hashes: BTreeMap::new(),
            records: Vec::new(),
            last_record: String::new(),
            dirty_job: true,
            dirty_metrics: false,
            flushed: 0,
            rewrite: false,
        }
    }

    /// The write that brings `metrics.jsonl` up to date; `can_append`: the store appends
    /// in place (a local folder). Counts the records as written: call
    /// [`Core::metrics_write_failed`] if the write fails.
    pub fn metrics_write(&mut self, can_append: bool) -> MetricsWrite {
        let lines = |records: &[(u64, String)]| {
            let mut text = String::new();
            for (_, l) in records {
                text.push_str(l);
                text.push('\n');
            }
            text
        };
        let append = can_append && !self.rewrite && self.flushed <= self.records.len();
        let write = if append {
            MetricsWrite::Append(lines(&self.records[self.flushed..]))
        } else {
            MetricsWrite::Whole(lines(&self.records))
        };
        self.flushed = self.records.len();
        self.rewrite = false;
        self.dirty_metrics = false;
        write
    }

    /// A metrics write failed: the next one writes the file whole.
    pub fn metrics_write_failed(&mut self) {
        self.rewrite = true;
        self.dirty_metrics = true;
    }

    /// Continues a job from its persisted state and records (a restarted coordinator, or
    /// `resume`: a new invocation, with a fresh restart budget); `checkpoint` is the
    /// newest committed checkpoint found in the store.
    pub fn restore(
        &mut self,
        p: &Persisted,
        records: Vec<String>,
        checkpoint: Option<u64>,
        resume: bool,
        now: Instant,
    ) {
        self.generation = p.generation;
        self.restarts = p.restarts;
        self.restarts_before = if resume { p.restarts } else { 0 };
        self.hash_checks = p.hash_checks;
        self.last_checkpoint = checkpoint;
        // Without a checkpoint the job starts over, and so does its record.
        self.records = records
            .into_iter()
            .filter_map(|l| record_step(&l).map(|s| (s, l)))
            .filter(|(s, _)| checkpoint.is_some_and(|k| *s <= k))
            .collect();
        self.phase = Phase::Waiting { since: now };
        self.dirty_job = true;
        self.dirty_metrics = true;
        // The file may hold records past the checkpoint: written whole once.
        self.rewrite = true;
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

    fn fail(&mut self, reason: String) {
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
        self.ring.clear();
        self.hashes.clear();
        self.phase = Phase::Waiting { since: now };
        self.dirty_job = true;
        if counts_as_restart {
            self.restarts += 1;
            let max = self.spec.job.cluster.max_restarts;
            if self.restarts - self.restarts_before > max {
                self.fail(format!(
                    "{reason}; gave up after {max} restarts (cluster.max_restarts)"
                ));
            }
        }
    }

    pub fn register(
        &mut self,
        protocol_version: u32,
        name: String,
        addr: String,
        threads: u32,
        now: Instant,
    ) -> Result<u64, Status> {
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
        if self.is_over() {
            return Err(Status::failed_precondition("the job is over"));
        }
        let max = self.spec.job.cluster.max_workers;
        if self.members.len() >= max {
            return Err(Status::resource_exhausted(format!(
                "the job already has {max} workers (cluster.max_workers)"
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

    /// The plan of member `id` if a generation newer than `after` includes it.
    pub fn plan(&mut self, id: u64, after: u64, now: Instant) -> Result<PlanState, Status> {
        self.member(id, now)?;
        Ok(match &self.phase {
            Phase::Done => PlanState::Done,
            Phase::Failed(m) => PlanState::Failed(m.clone()),
            Phase::Running if self.generation > after => {
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
        let timeout = Duration::from_secs_f64(self.spec.job.cluster.heartbeat_timeout_s);
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
            let c = &self.spec.job.cluster;
            let n = eligible.len();
            let grace = Duration::from_secs_f64(c.join_grace_s);
            let waited = now.duration_since(since);
            if n >= c.max_workers || (n >= c.min_workers && waited >= grace) {
                self.form(eligible);
            } else if waited.as_secs_f64() > c.wait_timeout_s {
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
        self.ring = ring;
        self.resume_step = self.last_checkpoint;
        self.phase = Phase::Running;
        self.hashes.clear();
        let keep = self.last_checkpoint;
        let before = self.records.len();
        self.records.retain(|(s, _)| keep.is_some_and(|k| *s <= k));
        if self.records.len() != before {
            self.dirty_metrics = true;
            if self.records.len() < self.flushed {
                self.rewrite = true;
            }
        }
        self.dirty_job = true;
        tracing::info!(
            generation = self.generation,
            world = self.ring.len(),
            resume_step = ?self.last_checkpoint,
            "generation starts"
        );
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
            return Ok(d);
        }
        if self.ring.get(rank) != Some(&id) {
            return Err(Status::invalid_argument(format!(
                "worker {id} reports rank {rank}, the ring has it at {:?}",
                self.ring.iter().position(|&m| m == id)
            )));
        }
        if records.len() > MAX_RECORDS_PER_CALL {
            return Err(Status::invalid_argument(format!(
                "{} records in one report, at most {MAX_RECORDS_PER_CALL}",
                records.len()
            )));
        }
        if rank == 0 {
            for line in records {
                let Some(s) = record_step(&line) else {
                    return Err(Status::invalid_argument(
                        "metrics record is not a JSON object with a `step`",
                    ));
                };
                // A report resent after a lost answer repeats records already held.
                let held = self
                    .records
                    .iter()
                    .rev()
                    .take_while(|(k, _)| *k >= s)
                    .any(|(_, l)| *l == line);
                if held {
                    continue;
                }
                self.last_record = line.clone();
                self.records.push((s, line));
                self.dirty_metrics = true;
            }
        }
        if let Some(h) = param_hash {
            let world = self.ring.len();
            let entry = self.hashes.entry(step).or_default();
            entry.insert(rank, h);
            if entry.len() == world {
                let all = self.hashes.remove(&step).expect("present");
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
mod tests {
    use super::*;

    fn spec(min: usize, max: usize, restarts: u32) -> JobSpec {
        let mut job = JobConfig::preset("tiny").unwrap();
        job.cluster.min_workers = min;
        job.cluster.max_workers = max;
        job.cluster.max_restarts = restarts;
        job.cluster.join_grace_s = 0.0;
        JobSpec {
            job_id: "j".into(),
            job_toml: job.to_toml(),
            job,
            data: "data".into(),
            run: "run".into(),
            max_steps: Some(10),
            deadline_unix_s: None,
            cluster_overrides: ClusterOverrides::default(),
        }
    }

    fn prog(
        id: u64,
        generation: u64,
        rank: usize,
        step: u64,
        hash: Option<&str>,
        records: Vec<String>,
    ) -> Progress {
        Progress {
            worker_id: id,
            generation,
            rank,
            step,
            param_hash: hash.map(str::to_string),
            records,
        }
    }

    fn reg(c: &mut Core, now: Instant) -> u64 {
        c.register(PROTOCOL_VERSION, "w".into(), "http://x:1".into(), 1, now)
            .unwrap()
    }

    #[test]
    fn a_generation_forms_at_min_workers_and_ranks_follow_registration() {
        let t = Instant::now();
        let mut c = Core::new(spec(2, 2, 3), t);
        let a = reg(&mut c, t);
        c.tick(t);
        assert!(matches!(c.phase, Phase::Waiting { .. }));
        assert_eq!(c.plan(a, 0, t).unwrap(), PlanState::Waiting);
        let b = reg(&mut c, t);
        c.tick(t);
        assert_eq!(c.phase, Phase::Running);
        let PlanState::Running(p) = c.plan(b, 0, t).unwrap() else {
            panic!()
        };
        assert_eq!(
            (p.rank, p.world(), p.generation, p.resume_step),
            (1, 2, 1, None)
        );
        // Already running this generation: wait for a newer one.
        assert_eq!(c.plan(b, 1, t).unwrap(), PlanState::Waiting);
    }

    #[test]
    fn a_lost_member_restarts_survivors_from_the_last_checkpoint() {
        let t = Instant::now();
        let mut c = Core::new(spec(1, 2, 3), t);
        let a = reg(&mut c, t);
        let b = reg(&mut c, t);
        c.tick(t);
        c.checkpoint(a, 1, 5, false, t).unwrap();
        for s in [0, 5, 6] {
            let line = format!("{{\"step\":{s}}}");
            c.progress(prog(a, 1, 0, s, None, vec![line]), t).unwrap();
        }
        let later = t + Duration::from_secs(4);
        assert_eq!(c.heartbeat(a, 1, 6, later).unwrap().0, Directive::Continue);
        c.tick(later);
        assert!(!c.members.contains_key(&b), "b timed out");
        assert_eq!(c.restarts, 1);
        assert_eq!(c.heartbeat(a, 1, 6, later).unwrap().0, Directive::Restart);
        c.tick(later);
        let PlanState::Running(p) = c.plan(a, 1, later).unwrap() else {
            panic!()
        };
        assert_eq!((p.generation, p.world(), p.resume_step), (2, 1, Some(5)));
        let steps: Vec<u64> = c.records.iter().map(|(s, _)| *s).collect();
        assert_eq!(steps, vec![0, 5], "records past the checkpoint are dropped");
        // A resent report (its answer was lost) does not repeat records.
        let resent = vec!["{\"step\":5}".to_string(), "{\"step\":7}".to_string()];
        c.progress(prog(a, 2, 0, 7, None, resent), later).unwrap();
        let steps: Vec<u64> = c.records.iter().map(|(s, _)| *s).collect();
        assert_eq!(steps, vec![0, 5, 7]);
        // The unknown (timed-out) worker is told to register again.
        assert_eq!(
            c.heartbeat(b, 1, 6, later).unwrap_err().code(),
            tonic::Code::NotFound
        );
    }

    #[test]
    fn a_failed_round_does_not_re_admit_a_silent_peer() {
        let t = Instant::now();
        let mut c = Core::new(spec(1, 2, 3), t);
        let a = reg(&mut c, t);
        let b = reg(&mut c, t);
        c.tick(t);
        c.checkpoint(a, 1, 5, false, t).unwrap();
        // b died; a's round fails and a reports it at once, long before b times out.
        let t1 = t + Duration::from_millis(500);
        c.fault(a, 1, "sending to rank 1 failed", false, false, t1)
            .unwrap();
        let t2 = t1 + Duration::from_millis(1100);
        c.plan(a, 1, t2).unwrap();
        c.tick(t2);
        let PlanState::Running(p) = c.plan(a, 1, t2).unwrap() else {
            panic!("{:?}", c.phase)
        };
        assert_eq!((p.world(), p.generation, p.resume_step), (1, 2, Some(5)));
        assert_eq!(c.restarts, 1);
        // A late report of generation 1's next checkpoint does not move generation 2's
        // starting point.
        c.checkpoint(a, 1, 10, false, t2).unwrap();
        assert_eq!(c.last_checkpoint, Some(5));
        let _ = b;
    }

    /// A coordinator restarted while a worker was paused issues new ids: the paused
    /// worker's old id is unknown to it (so that worker registers again) even after
    /// another worker registered with the new coordinator.
    #[test]
    fn a_restarted_coordinator_never_reissues_an_earlier_incarnations_ids() {
        let t = Instant::now();
        let mut first = Core::with_incarnation(spec(2, 2, 3), 7, t);
        let paused = reg(&mut first, t);
        let other = reg(&mut first, t);
        let mut second = Core::with_incarnation(spec(2, 2, 3), 8, t);
        let again = reg(&mut second, t);
        assert_ne!(again, paused);
        assert_ne!(again, other);
        for id in [paused, other] {
            let e = second.heartbeat(id, 1, 3, t).unwrap_err();
            assert_eq!(e.code(), tonic::Code::NotFound);
            let e = second.plan(id, 1, t).unwrap_err();
            assert_eq!(e.code(), tonic::Code::NotFound);
        }
        // Two coordinators started independently draw different incarnations.
        let ids: std::collections::BTreeSet<u64> = (0..2)
            .map(|_| reg(&mut Core::new(spec(1, 9, 0), t), t))
            .collect();
        assert_eq!(ids.len(), 2, "random incarnations: {ids:?}");
    }

    /// Too few workers: the waiting phase ends in a clear failure, not a wait forever.
    #[test]
    fn waiting_for_too_few_workers_fails_after_the_wait_timeout() {
        let t = Instant::now();
        let mut c = Core::new(spec(2, 2, 3), t);
        let limit = c.spec.job.cluster.wait_timeout_s;
        let a = reg(&mut c, t);
        let before = t + Duration::from_secs_f64(limit * 0.9);
        c.heartbeat(a, 0, 0, before).unwrap();
        c.tick(before);
        assert!(matches!(c.phase, Phase::Waiting { .. }));
        let after = t + Duration::from_secs_f64(limit + 1.0);
        c.heartbeat(a, 0, 0, after).unwrap();
        c.tick(after);
        let Phase::Failed(m) = &c.phase else {
            panic!("{:?}", c.phase)
        };
        assert!(
            m.contains("cluster.wait_timeout_s") && m.contains("1 took part"),
            "{m}"
        );
        assert_eq!(c.heartbeat(a, 0, 0, after).unwrap().0, Directive::Stop);
        // With nobody at all (a finished job resumed with no workers) as well.
        let mut c = Core::new(spec(1, 2, 3), t);
        c.tick(after);
        assert!(matches!(c.phase, Phase::Failed(_)), "{:?}", c.phase);
    }

    /// `--resume` is a new invocation: the restarts of earlier ones do not count against
    /// its budget; a coordinator restarted after a crash keeps counting.
    #[test]
    fn a_resumed_job_gets_a_fresh_restart_budget() {
        let t = Instant::now();
        for (resume, fails) in [(true, false), (false, true)] {
            let mut c = Core::new(spec(1, 1, 1), t);
            let mut p = c.persisted();
            p.restarts = 1;
            c.restore(&p, vec![], Some(5), resume, t);
            let a = reg(&mut c, t);
            c.tick(t);
            c.fault(a, c.generation, "boom", false, false, t).unwrap();
            assert_eq!(c.restarts, 2);
            assert_eq!(
                matches!(c.phase, Phase::Failed(_)),
                fails,
                "resume {resume}"
            );
        }
    }

    /// metrics.jsonl grows by appends while records only grow; dropped records (a new
    /// generation from an older checkpoint) or a failed write make the next write whole.
    #[test]
    fn metrics_are_appended_until_records_are_dropped() {
        let t = Instant::now();
        let mut c = Core::new(spec(1, 2, 3), t);
        let a = reg(&mut c, t);
        c.tick(t);
        let line = |s: u64| format!("{{\"step\":{s}}}");
        let report = |c: &mut Core, g: u64, steps: std::ops::RangeInclusive<u64>| {
            let lines = steps.clone().map(line).collect();
            c.progress(prog(a, g, 0, *steps.end(), None, lines), t)
                .unwrap();
        };
        report(&mut c, 1, 1..=2);
        let both = format!("{}\n{}\n", line(1), line(2));
        assert_eq!(c.metrics_write(true), MetricsWrite::Append(both.clone()));
        report(&mut c, 1, 3..=3);
        let third = format!("{}\n", line(3));
        assert_eq!(c.metrics_write(true), MetricsWrite::Append(third));
        // An object store rewrites whole.
        report(&mut c, 1, 4..=4);
        assert!(matches!(c.metrics_write(false), MetricsWrite::Whole(_)));
        // A failed write: whole next time.
        c.metrics_write_failed();
        assert!(matches!(c.metrics_write(true), MetricsWrite::Whole(_)));
        // A new generation from checkpoint 2 drops records 3 and 4: whole.
        c.checkpoint(a, 1, 2, false, t).unwrap();
        c.fault(a, 1, "boom", false, false, t).unwrap();
        c.tick(t);
        assert_eq!(c.metrics_write(true), MetricsWrite::Whole(both));
    }

    /// A worker that leaves is dropped at once: the next generation forms without it,
    /// not with a dead member that fails its first round.
    #[test]
    fn a_leaving_worker_is_dropped_at_once() {
        let t = Instant::now();
        let mut c = Core::new(spec(2, 3, 5), t);
        let a = reg(&mut c, t);
        let b = reg(&mut c, t);
        c.tick(t);
        assert_eq!(c.phase, Phase::Running);
        c.fault(b, 1, "stopped by a signal", false, true, t)
            .unwrap();
        assert!(!c.members.contains_key(&b));
        assert_eq!(c.restarts, 1);
        let d = reg(&mut c, t);
        c.tick(t);
        let PlanState::Running(p) = c.plan(a, 1, t).unwrap() else {
            panic!("{:?}", c.phase)
        };
        assert_eq!((p.generation, p.world()), (2, 2));
        assert!(c.ring.contains(&d) && !c.ring.contains(&b));
    }

    #[test]
    fn a_report_may_carry_a_bounded_number_of_records() {
        let t = Instant::now();
        let mut c = Core::new(spec(1, 1, 1), t);
        let a = reg(&mut c, t);
        c.tick(t);
        let many = vec!["{\"step\":1}".to_string(); MAX_RECORDS_PER_CALL + 1];
        let e = c.progress(prog(a, 1, 0, 1, None, many), t).unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument);
        assert!(c.records.is_empty());
    }

    #[test]
    fn cluster_overrides_apply_and_keep_max_at_least_min() {
        let mut c = JobConfig::preset("tiny").unwrap().cluster;
        c.max_workers = 2;
        let o = ClusterOverrides {
            min_workers: Some(3),
            max_workers: None,
            max_restarts: Some(9),
        };
        o.apply(&mut c);
        assert_eq!((c.min_workers, c.max_workers, c.max_restarts), (3, 3, 9));
        ClusterOverrides {
            max_workers: Some(5),
            ..Default::default()
        }
        .apply(&mut c);
        assert_eq!((c.min_workers, c.max_workers, c.max_restarts), (3, 5, 9));
    }

    /// Diverged replicas restart from the last checkpoint (a restart); once the budget
    /// is spent, the job fails and says why.
    #[test]
    fn diverged_hashes_restart_from_the_checkpoint_and_equal_ones_count() {
        let t = Instant::now();
        let mut c = Core::new(spec(2, 2, 1), t);
        let a = reg(&mut c, t);
        let b = reg(&mut c, t);
        c.tick(t);
        c.checkpoint(a, 1, 1, false, t).unwrap();
        c.progress(prog(a, 1, 0, 1, Some("aa"), vec![]), t).unwrap();
        c.progress(prog(b, 1, 1, 1, Some("aa"), vec![]), t).unwrap();
        assert_eq!(c.hash_checks, 1);
        c.progress(prog(a, 1, 0, 2, Some("aa"), vec![]), t).unwrap();
        let d = c.progress(prog(b, 1, 1, 2, Some("bb"), vec![]), t).unwrap();
        assert_eq!(d, Directive::Restart);
        assert_eq!(c.restarts, 1);
        c.tick(t);
        let PlanState::Running(p) = c.plan(a, 1, t).unwrap() else {
            panic!("{:?}", c.phase)
        };
        assert_eq!((p.generation, p.resume_step), (2, Some(1)));
        c.progress(prog(a, 2, 0, 2, Some("aa"), vec![]), t).unwrap();
        let d = c.progress(prog(b, 2, 1, 2, Some("cc"), vec![]), t).unwrap();
        assert_eq!(d, Directive::Stop);
        let Phase::Failed(m) = &c.phase else { panic!() };
        assert!(m.contains("replicas diverged at step 2"), "{m}");
        assert!(m.contains("gave up after 1 restarts"), "{m}");
    }

    #[test]
    fn restarts_are_bounded_and_bad_registrations_refused() {
        let t = Instant::now();
        let mut c = Core::new(spec(1, 1, 1), t);
        let e = c
            .register(99, "w".into(), "http://x:1".into(), 1, t)
            .unwrap_err();
        assert_eq!(e.code(), tonic::Code::FailedPrecondition);
        let a = reg(&mut c, t);
        let e = c
            .register(PROTOCOL_VERSION, "w".into(), "http://y:1".into(), 1, t)
            .unwrap_err();
        assert_eq!(e.code(), tonic::Code::ResourceExhausted);
        c.tick(t);
        c.fault(a, 1, "boom", false, false, t).unwrap();
        assert_eq!(c.restarts, 1);
        c.tick(t);
        c.fault(a, 2, "boom again", false, false, t).unwrap();
        let Phase::Failed(m) = &c.phase else { panic!() };
        assert!(m.contains("gave up after 1 restarts"), "{m}");
        assert_eq!(c.heartbeat(a, 2, 0, t).unwrap().0, Directive::Stop);
        // A final checkpoint of the current generation finishes a job.
        let mut c = Core::new(spec(1, 1, 1), t);
        let a = reg(&mut c, t);
        c.tick(t);
        c.checkpoint(a, 1, 10, true, t).unwrap();
        assert_eq!(c.phase, Phase::Done);
        assert_eq!(c.plan(a, 1, t).unwrap(), PlanState::Done);
    }
}
