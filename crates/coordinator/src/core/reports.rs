//! A generation's reports: progress (with rank 0's records and the replicas' parameter
//! hashes, checked against each other), committed checkpoints and faults.

use super::{Core, MAX_PENDING_HASH_STEPS, Phase, Progress};
use osrt_proto::MAX_RECORDS_PER_REPORT;
use osrt_proto::convert::Directive;
use std::time::Instant;
use tonic::Status;

impl Core {
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
