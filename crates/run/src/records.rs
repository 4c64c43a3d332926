//! The records of `RUN/metrics.jsonl`, one JSON object per line: a [`TrainRecord`] every
//! `log_every` steps and an [`EvalRecord`] at every validation. Workers write them, the
//! coordinator orders and persists them by step, and reports, sweeps and the CLI read
//! them back; all through these types.
//!
//! Fields are declared in alphabetical order: that is the order the lines have always
//! had on disk, so files written before the types existed read the same. A record needs
//! its `step` and its kind's defining field (`loss` or `psnr`); the rest default.

use serde::{Deserialize, Deserializer, Serialize};

/// A float that may be written as `null`: JSON has no NaN, and serde_json writes a
/// non-finite float as `null` (a skipped step's loss, a failed evaluation).
fn nan_if_null<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Option::<f64>::deserialize(d).map(|v| v.unwrap_or(f64::NAN))
}

/// Training progress over the last `log_every` steps (rank 0).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainRecord {
    /// The data epoch in progress.
    #[serde(default)]
    pub epoch: u64,
    /// Mean gradient norm (before clipping) over the window's applied steps; absent when
    /// every step of the window was skipped.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grad_norm: Option<f64>,
    /// Mean training loss over the window.
    #[serde(deserialize_with = "nan_if_null")]
    pub loss: f64,
    /// Learning rate of the window's last step.
    #[serde(default, deserialize_with = "nan_if_null")]
    pub lr: f64,
    /// Forward and backward passes each step's share took on this rank (rank 0's:
    /// `train.micro_batch_size`); absent where one pass took it whole.
    #[serde(default, skip_serializing_if = "is_one_or_less")]
    pub micro_batches: u32,
    /// The worker's peak resident memory so far (where the OS tells).
    #[serde(default)]
    pub peak_rss_mb: Option<f64>,
    /// Generations the coordinator had to form again (a member lost, a coordinator
    /// restarted) before the one that took this step.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub restarts: u32,
    #[serde(default, deserialize_with = "nan_if_null")]
    pub scenes_per_s: f64,
    /// Steps skipped for a non-finite loss or gradient, since the start.
    #[serde(default)]
    pub skipped: u64,
    pub step: u64,
    /// Seconds spent in train steps and in the whole job, up to this step.
    #[serde(default, deserialize_with = "nan_if_null")]
    pub train_s: f64,
    #[serde(default, deserialize_with = "nan_if_null")]
    pub wall_s: f64,
    #[serde(default)]
    pub workers: usize,
}

/// A validation: reconstruction and segmentation on the fixed validation subset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalRecord {
    #[serde(default)]
    pub ari: Option<f64>,
    /// PSNR of predicting each scene's mean input-view colour everywhere.
    #[serde(default)]
    pub baseline_psnr: Option<f64>,
    /// Segmentation scores per number of objects in the scene (ascending), where scored.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub by_objects: Vec<ObjectCountRecord>,
    #[serde(default)]
    pub eval_scenes: usize,
    #[serde(default)]
    pub fg_ari: Option<f64>,
    #[serde(default)]
    pub fg_ari_2d: Option<f64>,
    #[serde(deserialize_with = "nan_if_null")]
    pub psnr: f64,
    #[serde(default)]
    pub ratio: Option<f64>,
    /// Target views rendered per second of decoding.
    #[serde(default, deserialize_with = "nan_if_null")]
    pub render_fps: f64,
    pub step: u64,
    #[serde(default, deserialize_with = "nan_if_null")]
    pub train_s: f64,
    #[serde(default, deserialize_with = "nan_if_null")]
    pub wall_s: f64,
}

/// FG-ARI of the validation scenes with one object count.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObjectCountRecord {
    #[serde(default)]
    pub fg_ari: Option<f64>,
    pub objects: usize,
    pub scenes: usize,
}

fn is_zero(n: &u32) -> bool {
    *n == 0
}

fn is_one_or_less(n: &u32) -> bool {
    *n <= 1
}

/// One line of `metrics.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum MetricsRecord {
    Train(TrainRecord),
    Eval(EvalRecord),
}

impl MetricsRecord {
    pub fn step(&self) -> u64 {
        match self {
            Self::Train(r) => r.step,
            Self::Eval(r) => r.step,
        }
    }

    pub fn wall_s(&self) -> f64 {
        match self {
            Self::Train(r) => r.wall_s,
            Self::Eval(r) => r.wall_s,
        }
    }

    /// One line of `metrics.jsonl` (no newline).
    pub fn to_line(&self) -> String {
        serde_json::to_string(self).expect("records serialise")
    }

    /// A line of `metrics.jsonl`; `None` for anything else (a torn last line, a foreign
    /// object).
    pub fn parse(line: &str) -> Option<Self> {
        serde_json::from_str(line).ok()
    }
}

/// Why a line cannot be stored as a line of `metrics.jsonl`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LineError {
    /// Stored, it would split into lines that are no records, and a restarted coordinator
    /// reading the file back would lose the record and the steps it bounds.
    #[error("the metrics record holds a line break at byte {at}: a record is one line")]
    LineBreak { at: usize },
    #[error(
        "the metrics record is not one JSON object with a `step` and a `loss` or `psnr`: {reason}"
    )]
    NotARecord { reason: String },
}

/// Characters that some reader of `metrics.jsonl` ends a line at: JSON whitespace
/// between tokens may be `\n` or `\r`, and string values may hold the rest raw (Python's
/// `str.splitlines` splits at all of them).
fn is_line_break(c: char) -> bool {
    matches!(
        c,
        '\n' | '\r' | '\u{0b}' | '\u{0c}' | '\u{1c}'
            ..='\u{1e}' | '\u{85}' | '\u{2028}' | '\u{2029}'
    )
}

/// `line` as a line of `metrics.jsonl`, checked before it is stored: one JSON object of a
/// record's kind, on one line.
pub fn validate_line(line: &str) -> Result<MetricsRecord, LineError> {
    if let Some(at) = line.find(is_line_break) {
        return Err(LineError::LineBreak { at });
    }
    serde_json::from_str(line).map_err(|e| LineError::NotARecord {
        reason: e.to_string(),
    })
}

impl From<TrainRecord> for MetricsRecord {
    fn from(r: TrainRecord) -> Self {
        Self::Train(r)
    }
}

impl From<EvalRecord> for MetricsRecord {
    fn from(r: EvalRecord) -> Self {
        Self::Eval(r)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Records print exactly as the untyped records workers wrote before these types
    /// existed (`serde_json::json!`, keys sorted), and read back as their kind.
    #[test]
    fn records_print_as_before_and_read_back_as_their_kind() {
        let train = TrainRecord {
            epoch: 0,
            grad_norm: None,
            loss: 0.008278974890708923,
            lr: 2e-4 * 0.1,
            micro_batches: 0,
            peak_rss_mb: Some(147.37109375),
            restarts: 0,
            scenes_per_s: 87.52540294216084,
            skipped: 0,
            step: 10,
            train_s: 1.2891337010000001,
            wall_s: 1.8280415780000001,
            workers: 2,
        };
        let before = serde_json::json!({
            "step": train.step, "wall_s": train.wall_s, "train_s": train.train_s,
            "loss": train.loss, "scenes_per_s": train.scenes_per_s, "lr": train.lr,
            "skipped": train.skipped, "epoch": train.epoch, "workers": train.workers,
            "peak_rss_mb": train.peak_rss_mb,
        });
        let line = MetricsRecord::from(train.clone()).to_line();
        assert_eq!(line, before.to_string());
        let eval = EvalRecord {
            ari: None,
            baseline_psnr: Some(21.882636289774595),
            by_objects: Vec::new(),
            eval_scenes: 32,
            fg_ari: Some(0.028622414207576715),
            fg_ari_2d: Some(0.06106365945622926),
            psnr: 20.722854643347453,
            ratio: Some(0.468730738748034),
            render_fps: 155.63452208026965,
            step: 0,
            train_s: 0.0,
            wall_s: 0.0,
        };
        let before = serde_json::json!({
            "step": eval.step, "wall_s": eval.wall_s, "train_s": eval.train_s,
            "psnr": eval.psnr, "baseline_psnr": eval.baseline_psnr, "fg_ari": eval.fg_ari,
            "fg_ari_2d": eval.fg_ari_2d, "ari": eval.ari, "ratio": eval.ratio,
            "render_fps": eval.render_fps, "eval_scenes": eval.eval_scenes,
        });
        let eline = MetricsRecord::from(eval.clone()).to_line();
        assert_eq!(eline, before.to_string());
        let (t, e) = (MetricsRecord::parse(&line), MetricsRecord::parse(&eline));
        assert!(matches!(t, Some(MetricsRecord::Train(r)) if r.step == 10 && r.workers == 2));
        assert!(
            matches!(e, Some(MetricsRecord::Eval(r)) if r.ari.is_none() && r.eval_scenes == 32)
        );
    }

    /// Non-finite figures (a skipped step's loss, a failed evaluation) are written as
    /// `null` and read back as NaN: such a record is still a record.
    #[test]
    fn non_finite_figures_round_trip_as_null() {
        let train = r#"{"epoch":0,"loss":null,"lr":0.001,"peak_rss_mb":null,"scenes_per_s":3.0,"skipped":4,"step":9,"train_s":1.0,"wall_s":null,"workers":2}"#;
        let Some(MetricsRecord::Train(t)) = MetricsRecord::parse(train) else {
            panic!("a train record")
        };
        assert!(t.loss.is_nan() && t.wall_s.is_nan());
        assert_eq!(MetricsRecord::Train(t).to_line(), train);
        let eval = r#"{"psnr":null,"step":4}"#;
        let Some(MetricsRecord::Eval(e)) = MetricsRecord::parse(eval) else {
            panic!("an eval record")
        };
        assert!(e.psnr.is_nan());
    }

    /// The figures added later (gradient norm, restarts, FG-ARI by object count) are
    /// left out of a line while absent and read back when present.
    #[test]
    fn later_figures_round_trip_and_stay_out_while_absent() {
        let train = r#"{"epoch":1,"grad_norm":0.5,"loss":0.25,"lr":0.001,"peak_rss_mb":null,"restarts":2,"scenes_per_s":3.0,"skipped":0,"step":9,"train_s":1.0,"wall_s":2.0,"workers":2}"#;
        let Some(MetricsRecord::Train(t)) = MetricsRecord::parse(train) else {
            panic!("a train record")
        };
        assert_eq!((t.grad_norm, t.restarts), (Some(0.5), 2));
        assert_eq!(MetricsRecord::Train(t).to_line(), train);
        let eval = r#"{"ari":null,"baseline_psnr":null,"by_objects":[{"fg_ari":0.75,"objects":3,"scenes":4}],"eval_scenes":4,"fg_ari":null,"fg_ari_2d":null,"psnr":20.0,"ratio":null,"render_fps":1.0,"step":4,"train_s":0.0,"wall_s":0.0}"#;
        let Some(MetricsRecord::Eval(e)) = MetricsRecord::parse(eval) else {
            panic!("an eval record")
        };
        assert_eq!(e.by_objects[0].objects, 3);
        assert_eq!(MetricsRecord::Eval(e).to_line(), eval);
    }

    /// A record split over lines (JSON allows a line break between tokens) would split
    /// `metrics.jsonl`: refused before it is stored, as is anything but one record.
    #[test]
    fn a_line_to_store_is_one_record_on_one_line() {
        let one = r#"{"loss":0.5,"step":3}"#;
        assert_eq!(validate_line(one).unwrap().step(), 3);
        for (line, at) in [
            ("{\"loss\":0.5,\n\"step\":3}", 12),
            ("{\"loss\":0.5,\"step\":3}\n", 21),
            ("{\"loss\":0.5,\r\"step\":3}", 12),
            ("{\"loss\":0.5,\"step\":3,\"note\":\"a\u{2028}b\"}", 30),
        ] {
            assert!(
                MetricsRecord::parse(line).is_some(),
                "{line:?} parses as JSON"
            );
            assert_eq!(
                validate_line(line),
                Err(LineError::LineBreak { at }),
                "{line:?}"
            );
        }
        for line in [
            r#"{"step":3}"#,
            "[]",
            "",
            r#"{"loss":0.5,"step":3}{"step":4}"#,
        ] {
            let e = validate_line(line).unwrap_err();
            assert!(matches!(e, LineError::NotARecord { .. }), "{line:?}: {e}");
        }
    }

    #[test]
    fn lines_without_a_step_or_a_kind_are_not_records() {
        for line in [
            r#"{"psnr":20.0}"#,
            r#"{"step":3}"#,
            r#"{"step":3,"wal"#,
            "",
            "[]",
        ] {
            assert_eq!(MetricsRecord::parse(line), None, "{line}");
        }
        let partial = MetricsRecord::parse(r#"{"step":2,"wall_s":2.5,"psnr":20.0}"#).unwrap();
        assert_eq!((partial.step(), partial.wall_s()), (2, 2.5));
    }
}
