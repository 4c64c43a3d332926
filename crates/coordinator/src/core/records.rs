//! Rank 0's metrics records on their way to `metrics.jsonl` and the TensorBoard event
//! log: taking them from reports, handing each writer what it lacks, and cutting those of
//! an abandoned timeline.

use super::Core;
use osrt_proto::MAX_RECORDS_PER_REPORT;
use osrt_run::MetricsRecord;
use tonic::Status;

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
    pub(super) fn drop_records_after(&mut self, keep: Option<u64>) {
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

    /// Stores rank 0's record lines, in order, skipping those already held.
    pub(super) fn take_records(&mut self, records: Vec<String>) -> Result<(), Status> {
        // Every line is checked before any is stored: a line that would split
        // `metrics.jsonl` (and lose records past it when a restart reads the file) is
        // refused, and a refused report stores none of its records.
        let mut steps = Vec::with_capacity(records.len());
        for (i, line) in records.iter().enumerate() {
            let record = osrt_run::validate_line(line)
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
}
