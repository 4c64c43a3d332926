//! The discard of an abandoned timeline, done by the coordinator alone.
//!
//! When a generation ends, its ranks may have committed checkpoints past the one the
//! next generation starts from (too late to count); the next generation replays those
//! steps, maybe with another world size, and must not meet them. They are deleted by the
//! run folder's lease holder only, only while it still holds the lease, and only after
//! the starting checkpoint itself was read and verified: a store that cannot be read
//! never costs a checkpoint. No plan goes out before that ([`Core::discard_pending`]).
//!
//! [`Core::discard_pending`]: crate::core::Core::discard_pending

use osrt_retry::{Failing, RetryPolicy};
use osrt_run::{RunError, checkpoint, lease};
use osrt_store::Location;
use tokio::task::JoinHandle;

/// How long the discard may keep failing for a reason that may pass before the job
/// fails (nothing is deleted meanwhile; the new generation waits).
pub const DISCARD_BUDGET: std::time::Duration = std::time::Duration::from_secs(120);

/// A discard in flight: the starting point it is for, and its task.
type InFlight = (Option<u64>, JoinHandle<Result<Vec<u64>, RunError>>);

/// The discard in flight and its failures so far.
#[derive(Default)]
pub struct Timeline {
    task: Option<InFlight>,
    failing: Failing,
}

/// What the monitor loop learns from a turn.
#[derive(Debug, PartialEq)]
pub enum Turn {
    /// Nothing finished (or nothing to do).
    Pending,
    /// The checkpoints past the starting point are gone: plans may go out.
    Done,
    /// The discard cannot be made: the job must fail with this reason.
    Fatal(String),
}

impl Timeline {
    /// Starts the discard of checkpoints past `resume_step` (unless one is running or
    /// waiting to be retried), or collects the one in flight.
    pub async fn turn(
        &mut self,
        run: &Location,
        lease_token: &str,
        resume_step: Option<u64>,
    ) -> Turn {
        match &self.task {
            Some((step, t)) if *step == resume_step && !t.is_finished() => return Turn::Pending,
            Some((step, _)) if *step == resume_step => {
                let (_, t) = self.task.take().expect("checked");
                return self.finished(resume_step, t.await);
            }
            // A newer generation formed meanwhile: its own discard follows this one.
            Some(_) => {
                let (_, t) = self.task.take().expect("checked");
                let _ = t.await;
            }
            None => {}
        }
        if !self.failing.due() {
            return Turn::Pending;
        }
        let (run, token) = (run.clone(), lease_token.to_string());
        let task = tokio::spawn(async move { discard(&run, &token, resume_step).await });
        self.task = Some((resume_step, task));
        Turn::Pending
    }

    fn finished(
        &mut self,
        resume_step: Option<u64>,
        r: Result<Result<Vec<u64>, RunError>, tokio::task::JoinError>,
    ) -> Turn {
        let r = r.unwrap_or_else(|e| {
            Err(RunError::Run {
                path: "checkpoints".into(),
                reason: format!("the discard task ended: {e}"),
            })
        });
        match r {
            Ok(discarded) => {
                self.failing.succeeded();
                if !discarded.is_empty() {
                    tracing::info!(
                        ?discarded,
                        ?resume_step,
                        "checkpoints of an abandoned timeline discarded"
                    );
                }
                Turn::Done
            }
            Err(e @ (RunError::Checkpoint { .. } | RunError::LeaseLost { .. })) => {
                Turn::Fatal(e.to_string())
            }
            Err(e) => match self.failing.failed(&RetryPolicy::backoff(DISCARD_BUDGET)) {
                Some(wait) => {
                    tracing::warn!(error = %e, retry_in = ?wait, "discarding an abandoned timeline failed; nothing was deleted; retrying");
                    Turn::Pending
                }
                None => Turn::Fatal(format!(
                    "{e} (the new generation waited {DISCARD_BUDGET:?} to start from it)"
                )),
            },
        }
    }
}

/// Verifies the starting checkpoint, checks the lease is still `token`'s, then deletes
/// every checkpoint folder past `resume_step`.
async fn discard(
    run: &Location,
    token: &str,
    resume_step: Option<u64>,
) -> Result<Vec<u64>, RunError> {
    let newer = checkpoint::list_steps(run)
        .await?
        .into_iter()
        .any(|s| resume_step.is_none_or(|r| s > r));
    if !newer {
        return Ok(Vec::new());
    }
    if let Some(step) = resume_step {
        checkpoint::check(run, step).await?;
    }
    lease::still_held(run, token).await?;
    checkpoint::discard_after(run, resume_step).await
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::retention::tests::commit_manifests;
    use osrt_run::lease::{Holder, Lease, LeaseTiming};

    async fn until_done(t: &mut Timeline, run: &Location, token: &str, step: Option<u64>) -> Turn {
        for _ in 0..200 {
            match t.turn(run, token, step).await {
                Turn::Pending => tokio::time::sleep(std::time::Duration::from_millis(10)).await,
                other => return other,
            }
        }
        panic!("the discard did not finish")
    }

    /// A starting checkpoint that does not verify is never the reason to delete the ones
    /// after it: the job fails and every folder stays.
    #[tokio::test]
    async fn nothing_goes_unless_the_start_verifies_and_the_lease_is_held() {
        let run = Location::parse("memory://timeline-start/run").unwrap();
        let lease = Lease::acquire(
            &run,
            Holder::this_process("j"),
            LeaseTiming::default(),
            false,
        )
        .await
        .unwrap();
        commit_manifests(&run, &[5, 10, 15]).await;
        let mut t = Timeline::default();
        let turn = until_done(&mut t, &run, &lease.holder().token, Some(5)).await;
        assert!(
            matches!(&turn, Turn::Fatal(m) if m.contains("step-000000005")),
            "{turn:?}"
        );
        assert_eq!(checkpoint::list_steps(&run).await.unwrap(), vec![15, 10, 5]);
        // Without a starting point, a lease that is another's stops it too.
        let turn = until_done(&mut t, &run, "someone-else", None).await;
        assert!(
            matches!(&turn, Turn::Fatal(m) if m.contains("taken over")),
            "{turn:?}"
        );
        assert_eq!(checkpoint::list_steps(&run).await.unwrap(), vec![15, 10, 5]);
        let turn = until_done(&mut t, &run, &lease.holder().token, None).await;
        assert_eq!(turn, Turn::Done);
        assert!(checkpoint::list_steps(&run).await.unwrap().is_empty());
    }
}
