//! Membership and generations: registration, heartbeats, plans, the timeout of silent
//! members, and the forming and ending of a generation's ring.

use super::{Core, Member, Phase, Registration};
use osrt_proto::PROTOCOL_VERSION;
use osrt_proto::convert::{Directive, PlanState, WorkerPlan};
use std::time::{Duration, Instant};
use tonic::Status;

impl Core {
    /// Abandons the current generation: everyone restarts from the last checkpoint.
    pub(super) fn regenerate(&mut self, reason: &str, counts_as_restart: bool, now: Instant) {
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

    pub(super) fn member(&mut self, id: u64, now: Instant) -> Result<&mut Member, Status> {
        let m = self.members.get_mut(&id).ok_or_else(|| {
            Status::not_found(format!(
                "unknown worker {id}: register again (the coordinator may have restarted)"
            ))
        })?;
        m.last_seen = now;
        Ok(m)
    }

    pub(super) fn directive_for(&self, id: u64, generation: u64) -> Directive {
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
}
