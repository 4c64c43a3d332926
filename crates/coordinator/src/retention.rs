//! Checkpoint retention, done by the coordinator alone.
//!
//! A coordinator restarted after a crash continues from the newest checkpoint at or
//! before [`checkpoint::resume_bound`] of what `job.json` and `metrics.jsonl` hold *on
//! the store*, which lags what workers have committed (records are flushed every
//! second, every 5 s on object stores). Retention must never delete that checkpoint.
//! Only the run folder's lease holder knows what it has written, so it deletes; workers
//! never do (a worker paused past its coordinator's restart would otherwise wake up and
//! delete, by the old timeline's count, the checkpoint the new coordinator had chosen).

use osrt_run::checkpoint;
use osrt_store::Location;
use tokio::task::JoinHandle;

/// What the store holds of `job.json` and `metrics.jsonl`, as far as this coordinator
/// has written them, and the retention pass in flight.
#[derive(Default)]
pub struct Retention {
    /// `job.json`'s `last_checkpoint` as last written (`None` inside: none recorded);
    /// `None`: not written by this coordinator yet.
    written_checkpoint: Option<Option<u64>>,
    /// The newest step of `metrics.jsonl` as last written (same convention).
    written_record: Option<Option<u64>>,
    /// The `last_checkpoint` the last pass was started for.
    applied_for: Option<Option<u64>>,
    task: Option<JoinHandle<()>>,
}

impl Retention {
    /// `job.json` was written with `last_checkpoint`.
    pub fn job_written(&mut self, last_checkpoint: Option<u64>) {
        self.written_checkpoint = Some(last_checkpoint);
    }

    /// `metrics.jsonl` was written whole or appended to; its newest step is `last_record`.
    pub fn metrics_written(&mut self, last_record: Option<u64>) {
        self.written_record = Some(last_record);
    }

    /// The bound a restarted coordinator would compute from the store now, once both
    /// files were written by this coordinator.
    fn bound(&self) -> Option<u64> {
        Some(checkpoint::resume_bound(
            self.written_record?,
            self.written_checkpoint?,
        ))
    }

    /// Starts a pass in the background when a newer checkpoint was recorded since the
    /// last one and none is running; a failed pass is logged (the next one retries).
    pub fn maybe_start(&mut self, run: &Location, keep_last: usize) {
        if self.task.as_ref().is_some_and(|t| !t.is_finished()) {
            return;
        }
        let (Some(bound), Some(recorded)) = (self.bound(), self.written_checkpoint) else {
            return;
        };
        if recorded.is_none() || self.applied_for == Some(recorded) {
            return;
        }
        self.applied_for = Some(recorded);
        let run = run.clone();
        self.task = Some(tokio::spawn(async move {
            pass(&run, keep_last, bound).await;
        }));
    }

    /// Waits for the pass in flight, then makes a last one with what was written last
    /// (the job is over).
    pub async fn finish(&mut self, run: &Location, keep_last: usize) {
        if let Some(t) = self.task.take() {
            let _ = t.await;
        }
        if let Some(bound) = self.bound()
            && self.written_checkpoint.flatten().is_some()
        {
            pass(run, keep_last, bound).await;
        }
    }
}

async fn pass(run: &Location, keep_last: usize, bound: u64) {
    match checkpoint::apply_retention(run, keep_last, bound).await {
        Ok(deleted) if !deleted.is_empty() => {
            tracing::debug!(?deleted, resume_bound = bound, "old checkpoints deleted")
        }
        Ok(_) => {}
        Err(e) => tracing::warn!(error = %e, "retention failed"),
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Bare manifests at `steps`: folders that count as committed without files.
    pub(crate) async fn commit_manifests(run: &Location, steps: &[u64]) {
        for s in steps {
            let path = format!("{}/{}", checkpoint::step_dir(*s), checkpoint::MANIFEST);
            osrt_run::write_file(run, &path, b"{}".to_vec())
                .await
                .unwrap();
        }
    }

    /// The pass keeps what a coordinator restarted from the store's files would continue
    /// from: nothing runs before both files were written, the first pass (records written
    /// to step 27, checkpoint 50 recorded) keeps 20 and newer with `keep_last = 1`, and
    /// the last one (records to 50) keeps only 50.
    #[tokio::test]
    async fn passes_keep_the_checkpoint_the_written_files_resume_from() {
        let run = Location::parse("memory://retention-bound/run").unwrap();
        commit_manifests(&run, &[10, 20, 30, 40, 50]).await;
        let mut r = Retention::default();
        r.job_written(Some(50));
        r.maybe_start(&run, 1);
        assert!(r.task.is_none(), "metrics.jsonl not written yet");
        r.metrics_written(Some(27));
        r.maybe_start(&run, 1);
        r.task.take().expect("a pass").await.unwrap();
        let steps = checkpoint::list_steps(&run).await.unwrap();
        assert_eq!(steps, vec![50, 40, 30, 20]);
        // The same checkpoint recorded again starts no pass.
        r.maybe_start(&run, 1);
        assert!(r.task.is_none());
        r.metrics_written(Some(50));
        r.finish(&run, 1).await;
        assert_eq!(checkpoint::list_steps(&run).await.unwrap(), vec![50]);
    }
}
