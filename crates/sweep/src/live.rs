//! Where a running job stands, for a report page kept current while it runs
//! (`osrt report RUN --watch`): its step and state, how long it has run, its restarts,
//! its newest validation and an ETA, read from the run folder's `metrics.jsonl` and
//! `job.json` (local or in an object store).

use crate::results::CurvePoint;
use osrt_run::MetricsRecord;
use serde::Deserialize;

/// The fields of the coordinator's `job.json` a watcher needs.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
pub struct JobView {
    /// `waiting`, `running`, `done` or `failed`.
    #[serde(default)]
    pub state: String,
    #[serde(default)]
    pub message: String,
    #[serde(default)]
    pub restarts: u32,
    #[serde(default)]
    pub max_steps: Option<u64>,
    #[serde(default)]
    pub deadline_unix_s: Option<f64>,
}

impl JobView {
    /// Whether the job will write nothing more.
    pub fn is_over(&self) -> bool {
        self.state == "done" || self.state == "failed"
    }
}

/// Where a job stands.
#[derive(Debug, Clone, PartialEq)]
pub struct Live {
    pub step: u64,
    pub job: JobView,
    /// The job's wall-clock seconds so far (across restarts and resumes).
    pub wall_s: f64,
    /// Steps per second over the newest training records (`None` before two).
    pub steps_per_s: Option<f64>,
    pub newest_eval: Option<CurvePoint>,
    /// Seconds left: to the step limit at the recent rate, or to the deadline, whichever
    /// comes first.
    pub eta_s: Option<f64>,
}

/// Training records the step rate is measured over.
const RATE_WINDOW: usize = 20;

impl Live {
    /// The state of a job from its records (`metrics.jsonl`'s lines, a torn last line
    /// ignored) and `job.json`; `now_unix_s` for the deadline.
    pub fn of(metrics: &str, job: JobView, now_unix_s: f64) -> Self {
        let records: Vec<MetricsRecord> =
            metrics.lines().filter_map(MetricsRecord::parse).collect();
        let step = records.iter().map(MetricsRecord::step).max().unwrap_or(0);
        let wall_s = records
            .iter()
            .map(MetricsRecord::wall_s)
            .filter(|w| w.is_finite())
            .fold(0.0, f64::max);
        let train: Vec<(u64, f64)> = records
            .iter()
            .filter_map(|r| match r {
                MetricsRecord::Train(t) if t.wall_s.is_finite() => Some((t.step, t.wall_s)),
                _ => None,
            })
            .collect();
        let window = &train[train.len().saturating_sub(RATE_WINDOW)..];
        let steps_per_s = match (window.first(), window.last()) {
            (Some(a), Some(b)) if b.0 > a.0 && b.1 > a.1 => Some((b.0 - a.0) as f64 / (b.1 - a.1)),
            _ => None,
        };
        let newest_eval = records.iter().rev().find_map(|r| match r {
            MetricsRecord::Eval(e) if e.psnr.is_finite() => Some(CurvePoint {
                step: e.step,
                wall_s: e.wall_s,
                psnr: e.psnr,
                baseline_psnr: e.baseline_psnr,
                fg_ari: e.fg_ari,
            }),
            _ => None,
        });
        let by_steps = job
            .max_steps
            .zip(steps_per_s)
            .map(|(m, r)| m.saturating_sub(step) as f64 / r);
        let by_deadline = job.deadline_unix_s.map(|d| (d - now_unix_s).max(0.0));
        let eta_s = match (by_steps, by_deadline) {
            _ if job.is_over() => Some(0.0),
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        Self {
            step,
            job,
            wall_s,
            steps_per_s,
            newest_eval,
            eta_s,
        }
    }

    /// The page's paragraph: state, step, run time, restarts, ETA, newest validation.
    pub fn note(&self) -> String {
        let limit = self
            .job
            .max_steps
            .map_or(String::new(), |m| format!(" of {m}"));
        let state = if self.job.state.is_empty() {
            "starting".to_string()
        } else if self.job.message.is_empty() {
            self.job.state.clone()
        } else {
            format!("{} ({})", self.job.state, self.job.message)
        };
        let eta = match self.eta_s {
            _ if self.job.is_over() => String::new(),
            Some(s) => format!("; ETA {}", clock(s)),
            None => "; ETA unknown".to_string(),
        };
        let rate = self
            .steps_per_s
            .map_or(String::new(), |r| format!(" at {r:.2} steps/s"));
        let eval = self
            .newest_eval
            .map_or("no validation yet".to_string(), |e| {
                format!(
                    "newest validation at step {}: PSNR {:.2} dB{}, FG-ARI {}",
                    e.step,
                    e.psnr,
                    e.baseline_psnr.map_or(String::new(), |b| format!(
                        " (mean-colour baseline {b:.2} dB)"
                    )),
                    e.fg_ari.map_or("n/a".into(), |v| format!("{v:.3}"))
                )
            });
        format!(
            "Job {state}: step {}{limit}{rate}, run time {}, {} restart{}{eta}; {eval}.",
            self.step,
            clock(self.wall_s),
            self.job.restarts,
            if self.job.restarts == 1 { "" } else { "s" },
        )
    }
}

/// Seconds as `H:MM:SS`.
pub fn clock(s: f64) -> String {
    let s = if s.is_finite() {
        s.max(0.0).round() as u64
    } else {
        0
    };
    format!("{}:{:02}:{:02}", s / 3600, s / 60 % 60, s % 60)
}

/// A Unix time as `YYYY-MM-DD HH:MM:SS UTC` (the proleptic Gregorian calendar).
pub fn utc(unix_s: f64) -> String {
    let s = if unix_s.is_finite() {
        unix_s.max(0.0) as i64
    } else {
        0
    };
    let (days, rest) = (s.div_euclid(86_400), s.rem_euclid(86_400));
    // Days since 1970-01-01 to a civil date, counting in 400-year eras from 0000-03-01.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1_460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02} {:02}:{:02}:{:02} UTC",
        rest / 3600,
        rest / 60 % 60,
        rest % 60
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utc_dates_match_known_instants() {
        assert_eq!(utc(0.0), "1970-01-01 00:00:00 UTC");
        assert_eq!(utc(951_782_400.0), "2000-02-29 00:00:00 UTC", "a leap day");
        assert_eq!(utc(1_795_757_419.9), "2026-11-27 05:30:19 UTC");
        assert_eq!(clock(3_725.0), "1:02:05");
    }

    const METRICS: &str = r#"{"epoch":0,"loss":0.5,"lr":0.001,"peak_rss_mb":null,"scenes_per_s":3.0,"skipped":0,"step":10,"train_s":1.0,"wall_s":10.0,"workers":2}
{"epoch":0,"loss":0.4,"lr":0.001,"peak_rss_mb":null,"scenes_per_s":3.0,"skipped":0,"step":20,"train_s":2.0,"wall_s":15.0,"workers":2}
{"psnr":21.5,"baseline_psnr":20.0,"fg_ari":0.25,"step":20,"wall_s":16.0}
{"epoch":0,"loss":0.3,"lr":0.001,"peak_rss_mb":null,"scenes_per_s":3.0,"skipped":0,"step":30,"train_s":3.0,"wall_s":20.0,"workers":2}
{"epoch":0,"loss":0.3,"lr":0.0"#;

    #[test]
    fn a_running_job_has_a_rate_an_eta_and_its_newest_validation() {
        let job = JobView {
            state: "running".into(),
            restarts: 1,
            max_steps: Some(130),
            ..Default::default()
        };
        let live = Live::of(METRICS, job, 0.0);
        assert_eq!(live.step, 30);
        assert_eq!(live.steps_per_s, Some(2.0), "20 steps in 10 s");
        assert_eq!(live.eta_s, Some(50.0), "100 steps left at 2 steps/s");
        assert_eq!(live.newest_eval.unwrap().step, 20);
        assert_eq!(
            live.note(),
            "Job running: step 30 of 130 at 2.00 steps/s, run time 0:00:20, 1 restart; \
             ETA 0:00:50; newest validation at step 20: PSNR 21.50 dB (mean-colour \
             baseline 20.00 dB), FG-ARI 0.250."
        );
    }

    #[test]
    fn a_deadline_nearer_than_the_step_limit_decides_the_eta() {
        let job = JobView {
            state: "running".into(),
            max_steps: Some(10_000),
            deadline_unix_s: Some(1_000.0),
            ..Default::default()
        };
        assert_eq!(Live::of(METRICS, job.clone(), 990.0).eta_s, Some(10.0));
        assert_eq!(Live::of(METRICS, job, 2_000.0).eta_s, Some(0.0));
    }

    #[test]
    fn a_job_before_its_first_record_or_after_its_end_says_so() {
        let live = Live::of("", JobView::default(), 0.0);
        assert_eq!(
            live.note(),
            "Job starting: step 0, run time 0:00:00, 0 restarts; ETA unknown; \
             no validation yet."
        );
        let done = JobView {
            state: "done".into(),
            ..Default::default()
        };
        let live = Live::of(METRICS, done, 0.0);
        assert!(
            live.note()
                .starts_with("Job done: step 30 at 2.00 steps/s, run time 0:00:20"),
            "{}",
            live.note()
        );
        assert!(!live.note().contains("ETA"));
    }
}
