//! Result rows of a sweep, their tables, and the curves of a run's `metrics.jsonl`.

use crate::Result;
use osrt_run::MetricsRecord;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::Path;

/// Written into a point's run folder when it is trained and evaluated: the marker that
/// the point is finished (a re-run of the sweep skips it).
pub const RESULT_FILE: &str = "result.json";

/// One finished sweep point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PointResult {
    pub point: String,
    pub settings: Vec<(String, String)>,
    /// Wall-clock seconds of training (the last record of the run).
    pub train_wall_s: f64,
    pub steps: u64,
    /// Mean training throughput over the run's log records.
    pub scenes_per_s: f64,
    pub eval_split: String,
    pub eval_scenes: usize,
    pub psnr: f64,
    pub baseline_psnr: f64,
    pub fg_ari: Option<f64>,
    pub ari: Option<f64>,
    pub fg_ari_2d: Option<f64>,
    pub ratio: Option<f64>,
    pub render_fps: f64,
    /// Largest peak resident set of a worker (rank 0's records), MiB.
    pub peak_rss_mb: Option<f64>,
}

impl PointResult {
    pub fn load(path: &Path) -> Result<Self> {
        let text = crate::read_text(path)?;
        serde_json::from_str(&text).map_err(|e| crate::SweepError::Io {
            path: path.display().to_string(),
            reason: format!("not a sweep result: {e}"),
        })
    }

    pub fn save(&self, path: &Path) -> Result<()> {
        let text = serde_json::to_string_pretty(self).expect("serialisable");
        crate::write_bytes(path, text.as_bytes())
    }
}

/// One evaluation of a run's validation subset during training.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CurvePoint {
    pub step: u64,
    pub wall_s: f64,
    pub psnr: f64,
    pub baseline_psnr: Option<f64>,
    pub fg_ari: Option<f64>,
}

/// Error against run time of one run.
#[derive(Debug, Clone, PartialEq)]
pub struct Curve {
    pub label: String,
    pub points: Vec<CurvePoint>,
}

/// What a run's `metrics.jsonl` says about its training as a whole.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunSummary {
    pub steps: u64,
    pub wall_s: f64,
    pub scenes_per_s: f64,
    pub peak_rss_mb: Option<f64>,
    pub evaluations: Vec<CurvePoint>,
}

impl RunSummary {
    /// Parses `metrics.jsonl` text (`origin` names it in errors). A torn last line (a
    /// crash mid-write) is ignored; any other unparsable line is an error.
    pub fn parse(text: &str, origin: &str) -> Result<Self> {
        let mut s = RunSummary::default();
        let (mut rate_sum, mut rate_n) = (0.0, 0usize);
        let lines: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
        for (i, line) in lines.iter().enumerate() {
            let record: MetricsRecord = match serde_json::from_str(line) {
                Ok(v) => v,
                Err(_) if i + 1 == lines.len() => break,
                Err(e) => {
                    return Err(crate::SweepError::Io {
                        path: origin.to_string(),
                        reason: format!("line {}: not a metrics record: {e}", i + 1),
                    });
                }
            };
            s.steps = s.steps.max(record.step());
            s.wall_s = s.wall_s.max(record.wall_s());
            match record {
                MetricsRecord::Train(r) => {
                    rate_sum += r.scenes_per_s;
                    rate_n += 1;
                    if let Some(m) = r.peak_rss_mb {
                        s.peak_rss_mb = Some(s.peak_rss_mb.map_or(m, |p: f64| p.max(m)));
                    }
                }
                // A failed evaluation (`null` PSNR) has no point on the curve.
                MetricsRecord::Eval(r) if !r.psnr.is_finite() => {}
                MetricsRecord::Eval(r) => s.evaluations.push(CurvePoint {
                    step: r.step,
                    wall_s: r.wall_s,
                    psnr: r.psnr,
                    baseline_psnr: r.baseline_psnr,
                    fg_ari: r.fg_ari,
                }),
            }
        }
        if rate_n > 0 {
            s.scenes_per_s = rate_sum / rate_n as f64;
        }
        // A resumed run logs the steps after its checkpoint again: keep the last word.
        s.evaluations.sort_by_key(|a| a.step);
        s.evaluations.dedup_by(|later, earlier| {
            let same = later.step == earlier.step;
            if same {
                *earlier = *later;
            }
            same
        });
        Ok(s)
    }

    /// The records of the run folder `run_dir`; none yet (no `metrics.jsonl` beside its
    /// `config.toml`: a job before its first record, a model just imported) is an empty
    /// summary.
    pub fn load(run_dir: &Path) -> Result<Self> {
        let path = run_dir.join(osrt_run::METRICS_FILE);
        if !path.exists() && run_dir.join(osrt_run::CONFIG_FILE).exists() {
            return Self::parse("", &path.display().to_string());
        }
        Self::parse(&crate::read_text(&path)?, &path.display().to_string())
    }

    pub fn curve(&self, label: &str) -> Curve {
        Curve {
            label: label.to_string(),
            points: self.evaluations.clone(),
        }
    }
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or(String::new(), |v| format!("{v:.digits$}"))
}

/// The axes named by any row, in first-seen order (the table's first columns).
fn axes(rows: &[PointResult]) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for r in rows {
        for (k, _) in &r.settings {
            if !out.contains(k) {
                out.push(k.clone());
            }
        }
    }
    out
}

fn cells(r: &PointResult, axes: &[String]) -> Vec<String> {
    let mut c: Vec<String> = axes
        .iter()
        .map(|a| {
            r.settings
                .iter()
                .find(|(k, _)| k == a)
                .map(|(_, v)| v.clone())
                .unwrap_or_default()
        })
        .collect();
    c.extend([
        format!("{:.0}", r.train_wall_s),
        r.steps.to_string(),
        format!("{:.2}", r.scenes_per_s),
        format!("{:.2}", r.psnr),
        format!("{:.2}", r.baseline_psnr),
        opt(r.fg_ari, 3),
        opt(r.ari, 3),
        opt(r.fg_ari_2d, 3),
        opt(r.ratio, 3),
        format!("{:.1}", r.render_fps),
        opt(r.peak_rss_mb, 0),
    ]);
    c
}

const COLUMNS: [&str; 11] = [
    "train_wall_s",
    "steps",
    "scenes_per_s",
    "psnr",
    "baseline_psnr",
    "fg_ari",
    "ari",
    "fg_ari_2d",
    "ratio",
    "render_fps",
    "peak_rss_mb",
];

/// The header and rows of the results table.
pub fn table(rows: &[PointResult]) -> (Vec<String>, Vec<Vec<String>>) {
    let axes = axes(rows);
    let mut header = axes.clone();
    header.extend(COLUMNS.iter().map(|s| s.to_string()));
    (header, rows.iter().map(|r| cells(r, &axes)).collect())
}

/// CSV text of a header and rows (RFC 4180 quoting where a cell needs it).
pub(crate) fn csv_text(header: &[String], body: &[Vec<String>]) -> String {
    let quote = |s: &str| {
        if s.contains([',', '"', '\n']) {
            format!("\"{}\"", s.replace('"', "\"\""))
        } else {
            s.to_string()
        }
    };
    let mut out = String::new();
    for line in std::iter::once(header).chain(body.iter().map(Vec::as_slice)) {
        let cells: Vec<String> = line.iter().map(|c| quote(c)).collect();
        let _ = writeln!(out, "{}", cells.join(","));
    }
    out
}

/// A Markdown table of a header and rows; an empty cell reads `n/a`.
pub(crate) fn markdown_table(header: &[String], body: &[Vec<String>]) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "| {} |", header.join(" | "));
    let _ = writeln!(
        out,
        "|{}|",
        header.iter().map(|_| "---").collect::<Vec<_>>().join("|")
    );
    for line in body {
        let cells: Vec<&str> = line
            .iter()
            .map(|c| if c.is_empty() { "n/a" } else { c.as_str() })
            .collect();
        let _ = writeln!(out, "| {} |", cells.join(" | "));
    }
    out
}

/// `results.csv` text (RFC 4180 quoting where a cell needs it).
pub fn csv(rows: &[PointResult]) -> String {
    let (header, body) = table(rows);
    csv_text(&header, &body)
}

/// `results.md` text: a note on the evaluation and the table.
pub fn markdown(title: &str, note: &str, rows: &[PointResult]) -> String {
    let (header, body) = table(rows);
    format!("# {title}\n\n{note}\n\n{}", markdown_table(&header, &body))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(point: &str, fg: Option<f64>) -> PointResult {
        PointResult {
            point: point.into(),
            settings: vec![("decoder".into(), point.into())],
            train_wall_s: 60.4,
            steps: 10,
            scenes_per_s: 3.25,
            eval_split: "test".into(),
            eval_scenes: 4,
            psnr: 20.5,
            baseline_psnr: 18.25,
            fg_ari: fg,
            ari: fg,
            fg_ari_2d: fg,
            ratio: fg.map(|_| 1.0),
            render_fps: 12.0,
            peak_rss_mb: Some(300.0),
        }
    }

    #[test]
    fn metrics_are_summarised_and_a_torn_last_line_ignored() {
        let text = r#"{"step":1,"wall_s":1.0,"loss":0.1,"scenes_per_s":2.0,"peak_rss_mb":100}
{"step":2,"wall_s":2.0,"loss":0.1,"scenes_per_s":4.0,"peak_rss_mb":120}
{"step":2,"wall_s":2.5,"psnr":20.0,"baseline_psnr":18.0,"fg_ari":0.5}
{"step":1,"wall_s":3.0,"psnr":19.0}
{"step":1,"wall_s":3.5,"psnr":19.5}
{"step":3,"wall_"#;
        let s = RunSummary::parse(text, "m").unwrap();
        assert_eq!(s.steps, 2);
        assert_eq!(s.wall_s, 3.5);
        assert_eq!(s.scenes_per_s, 3.0);
        assert_eq!(s.peak_rss_mb, Some(120.0));
        // Step 1 was evaluated twice (a resume): the later evaluation wins.
        let steps: Vec<(u64, f64)> = s.evaluations.iter().map(|p| (p.step, p.psnr)).collect();
        assert_eq!(steps, vec![(1, 19.5), (2, 20.0)]);
        assert!(RunSummary::parse("{\nnot json\n{}\n", "m").is_err());
    }

    #[test]
    fn tables_name_every_column_and_mark_missing_values() {
        let rows = vec![row("slot_mixer", Some(0.25)), row("tr,ans\"former", None)];
        let csv = csv(&rows);
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(
            lines[0],
            "decoder,train_wall_s,steps,scenes_per_s,psnr,baseline_psnr,fg_ari,ari,fg_ari_2d,ratio,render_fps,peak_rss_mb"
        );
        assert_eq!(
            lines[1],
            "slot_mixer,60,10,3.25,20.50,18.25,0.250,0.250,0.250,1.000,12.0,300"
        );
        assert_eq!(
            lines[2],
            "\"tr,ans\"\"former\",60,10,3.25,20.50,18.25,,,,,12.0,300"
        );
        let md = markdown("T", "note", &rows);
        assert!(
            md.contains("| tr,ans\"former | 60 | 10 | 3.25 | 20.50 | 18.25 | n/a | n/a |"),
            "{md}"
        );
    }
}
