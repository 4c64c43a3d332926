//! The run folder's writer: `job.json`, the metrics records ([`osrt_run::metrics_log`]),
//! the TensorBoard events, checkpoint retention and an abandoned timeline's discard. It
//! runs beside the monitor's ticks, not inside them: a slow or failing store delays
//! neither lost-worker detection nor lease renewal (a task of its own), only what it
//! writes.

use crate::error::CoordinatorError;
use crate::retention::Retention;
use crate::service::Shared;
use crate::timeline::{Timeline, Turn};
use osrt_retry::{Failing, RetryPolicy};
use osrt_run::{JOB_FILE, write_file};
use std::time::{Duration, Instant};

/// How long writes of `job.json` and `metrics.jsonl` may keep failing before the
/// coordinator gives up (the job's state stays in memory meanwhile, and workers train on).
pub const STORE_RETRY_BUDGET: Duration = Duration::from_secs(120);

/// How often records are flushed: a local file is appended to every second; an object
/// store gets the open part of the records again, so at most every five seconds (a
/// restarted coordinator replays the steps whose records had not reached the store).
const LOCAL_EVERY: Duration = Duration::from_secs(1);
const OBJECT_STORE_EVERY: Duration = Duration::from_secs(5);

/// Failed writes of the run folder, retried under [`RetryPolicy::backoff`] within
/// [`STORE_RETRY_BUDGET`].
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

pub(crate) struct Persister<'a> {
    shared: &'a Shared,
    store: StoreRetry,
    retention: Retention,
    timeline: Timeline,
    keep_last: usize,
    /// Flush the records at most this often.
    every: Duration,
    last_flush: Instant,
}

impl<'a> Persister<'a> {
    pub fn new(shared: &'a Shared, appends_in_place: bool) -> Self {
        Self {
            keep_last: shared.with(|c, _| c.spec.cluster.keep_last),
            shared,
            store: StoreRetry::default(),
            retention: Retention::default(),
            timeline: Timeline::default(),
            every: if appends_in_place {
                LOCAL_EVERY
            } else {
                OBJECT_STORE_EVERY
            },
            last_flush: Instant::now(),
        }
    }

    /// Writes what changed until the job is over (and `linger` has passed with nothing
    /// left to write) or `shutdown` resolves; then writes the rest once more and releases
    /// the lease.
    pub async fn run(
        mut self,
        linger: Duration,
        shutdown: impl std::future::Future<Output = ()>,
    ) -> Result<(), CoordinatorError> {
        tokio::pin!(shutdown);
        let mut over_since: Option<Instant> = None;
        loop {
            tokio::select! {
                _ = &mut shutdown => break,
                _ = tokio::time::sleep(Duration::from_millis(100)) => {}
            }
            self.discard_abandoned().await;
            if self.store.due() {
                match self.write(false).await {
                    Ok(true) => self.store.succeeded(),
                    Ok(false) => {}
                    Err(e) => {
                        self.store.failed(e)?;
                        continue;
                    }
                }
            }
            self.retention.maybe_start(&self.shared.run, self.keep_last);
            if self.shared.with(|c, _| c.is_over()) {
                let since = *over_since.get_or_insert_with(Instant::now);
                if since.elapsed() >= linger && !self.pending().await {
                    break;
                }
            }
        }
        self.write(true).await?;
        self.retention
            .finish(&self.shared.run, self.keep_last)
            .await;
        if let Some(lease) = self.shared.lease.lock().await.take() {
            lease.release().await?;
        }
        Ok(())
    }

    /// Whether anything is not written yet.
    async fn pending(&self) -> bool {
        let events = self.shared.events.lock().await.is_dirty();
        let log = self.shared.metrics.lock().await.is_dirty();
        let c = self.shared.core.lock().expect("state");
        c.dirty_job || c.dirty_metrics || c.events_pending() || events || log
    }

    /// One round of writes: `job.json` if it changed, the records when their flush is
    /// due (`last`: now), then the events once the records they follow are written.
    /// `Ok(true)`: something was written.
    async fn write(&mut self, last: bool) -> Result<bool, CoordinatorError> {
        let shared = self.shared;
        let mut events = shared.events.lock().await;
        let mut log = shared.metrics.lock().await;
        let (job, over) = shared.with(|c, _| {
            let job = std::mem::take(&mut c.dirty_job).then(|| c.persisted());
            // Records go to the log at once (memory), and to the store when flushed.
            if c.dirty_metrics {
                let w = c.metrics_write();
                if let Some(keep) = w.cut_after {
                    log.cut_after(keep);
                }
                log.push(w.lines);
            }
            (job, c.is_over())
        });
        let mut wrote = false;
        if let Some(p) = job {
            let bytes = serde_json::to_vec_pretty(&p).expect("serialises");
            if let Err(e) = write_file(&shared.run, JOB_FILE, bytes).await {
                shared.with(|c, _| c.dirty_job = true);
                return Err(e.into());
            }
            self.retention.job_written(p.last_checkpoint);
            wrote = true;
        }
        let flush_due = last || over || self.last_flush.elapsed() >= self.every;
        if log.is_dirty() && flush_due {
            log.flush().await?;
            self.last_flush = Instant::now();
            self.retention.metrics_written(log.last_step());
            wrote = true;
        }
        // Events follow what the records' store holds.
        let work = shared.with(|c, _| {
            (!log.is_dirty()
                && (c.events_pending() || events.is_dirty())
                && (last || events.due(over)))
            .then(|| c.events_work())
        });
        drop(log);
        if let Some(w) = work {
            // Added to the log even if this write fails: its next write has them.
            events.write(w).await?;
            wrote = true;
        }
        Ok(wrote)
    }

    /// Fences off older generations in the lease, then discards the checkpoints past the
    /// new generation's starting point (verified first) before its plans go out; a
    /// discard that cannot be made fails the job.
    async fn discard_abandoned(&mut self) {
        let shared = self.shared;
        let (pending, resume_step, generation) = shared.with(|c, _| {
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
        let token = match shared.lease.lock().await.as_ref() {
            Some(k) if k.fence(generation) => k.token().to_string(),
            _ => return,
        };
        match self.timeline.turn(&shared.run, &token, resume_step).await {
            Turn::Pending => {}
            Turn::Done => shared.with(|c, _| {
                if c.resume_step == resume_step {
                    c.discarded();
                }
            }),
            Turn::Fatal(reason) => {
                shared.with(|c, _| c.fail(format!("the generation could not start: {reason}")))
            }
        }
    }
}
