//! The job's records as TensorBoard events in `RUN/tb/` ([`osrt_run::tensorboard`]):
//! the coordinator turns each record it persists in `metrics.jsonl` into an event, with
//! the pictures rank 0 left in `RUN/eval/` for a validation, and keeps the events to one
//! per record as records are dropped and replayed.

use crate::core::{Core, EventsWork};
use crate::error::CoordinatorError;
use osrt_run::tensorboard::{self, EVAL_PICTURES, EventLog, eval_picture};
use osrt_run::{MetricsRecord, read_file};
use osrt_store::Location;
use std::time::{Duration, Instant};

/// How often events are written to an object store, which cannot append: each write puts
/// the open event file whole. A local run folder gets them with `metrics.jsonl`.
const OBJECT_STORE_EVERY: Duration = Duration::from_secs(10);

pub struct Events {
    log: EventLog,
    run: Location,
    every: Duration,
    last_write: Instant,
}

impl Events {
    /// The event log of `run`, matched to `core`'s records: events past its checkpoint
    /// are cut, and so is its last step's (a crash may have cut its events short), and
    /// the records from there on are written again.
    pub async fn open(
        run: &Location,
        core: &mut Core,
        can_append: bool,
    ) -> Result<Self, CoordinatorError> {
        let (mut log, last) = EventLog::open(run, can_append).await?;
        let from = match last {
            None => 0,
            Some(l) => l.min(core.last_checkpoint.map_or(0, |c| c + 1)),
        };
        if last.is_some() {
            log.cut_after(from.checked_sub(1));
        }
        // The records the event log lacks, read back from the run folder: those from
        // `from` up to the checkpoint (past it they are about to be cut), and the
        // training record before them.
        let mut backlog = Vec::new();
        let mut previous = None;
        if let Some(k) = core.last_checkpoint {
            osrt_run::metrics_log::for_each_line(run, |l| match MetricsRecord::parse(l) {
                Some(r) if (from..=k).contains(&r.step()) => backlog.push((r.step(), l.into())),
                Some(MetricsRecord::Train(t)) if t.step < from => {
                    previous = Some((t.step, l.to_string()))
                }
                _ => {}
            })
            .await?;
        }
        core.events_resume(backlog, previous);
        Ok(Self {
            log,
            run: run.clone(),
            every: if can_append {
                Duration::ZERO
            } else {
                OBJECT_STORE_EVERY
            },
            last_write: Instant::now(),
        })
    }

    /// Whether a write is due (`over`: the job is over, nothing waits any longer).
    pub fn due(&self, over: bool) -> bool {
        over || self.last_write.elapsed() >= self.every
    }

    /// Whether something written before still waits (a failed write).
    pub fn is_dirty(&self) -> bool {
        self.log.is_dirty()
    }

    /// Applies `work` and writes it. A failed write is retried whole by the next one.
    pub async fn write(&mut self, work: EventsWork) -> Result<(), CoordinatorError> {
        if let Some(keep) = work.cut_after {
            self.log.cut_after(keep);
        }
        let mut previous = work
            .previous_train
            .and_then(|l| match MetricsRecord::parse(&l) {
                Some(MetricsRecord::Train(t)) => Some(t),
                _ => None,
            });
        let now = osrt_run::unix_now();
        for line in &work.records {
            let Some(record) = MetricsRecord::parse(line) else {
                continue;
            };
            let mut values = tensorboard::scalars(&record, previous.as_ref());
            match &record {
                MetricsRecord::Train(t) => previous = Some(t.clone()),
                MetricsRecord::Eval(e) => values.extend(self.pictures(e.step).await),
            }
            self.log.add(record.step(), now, values);
        }
        self.last_write = Instant::now();
        Ok(self.log.flush().await?)
    }

    /// Image summaries of the pictures rank 0 left for the validation at `step` (before
    /// it sent the record); a missing or unreadable one is left out.
    async fn pictures(&self, step: u64) -> Vec<tensorboard::proto::summary::Value> {
        let mut out = Vec::new();
        for name in EVAL_PICTURES {
            match read_file(&self.run, &eval_picture(step, name)).await {
                Ok(Some(png)) => {
                    out.extend(tensorboard::image(&format!("eval/{name}"), png.to_vec()))
                }
                Ok(None) => {}
                Err(e) => tracing::warn!(error = %e, step, "reading a validation picture"),
            }
        }
        out
    }
}
