//! The report page: one static HTML file beside its PNGs. No scripts, no external
//! resources: it opens from disk with no server and no network.

use crate::Result;
use crate::plot::{self, Metric};
use crate::results::{self, Curve, PointResult};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

pub const PAGE: &str = "index.html";

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// What a report shows.
pub struct Report<'a> {
    pub title: String,
    /// A paragraph under the title (what was run, the budget, what is evaluated).
    pub note: String,
    /// Result rows (a sweep, or a run's final evaluation).
    pub rows: &'a [PointResult],
    /// Curves drawn against wall-clock time.
    pub curves: &'a [Curve],
    /// Images to show as strips (render frames), paths relative to the output folder.
    pub strips: Vec<(String, String)>,
    /// Seconds after which a browser showing the page loads it again (a page kept
    /// current while a job runs); `None`: a page that does not change.
    pub refresh_s: Option<u64>,
}

/// Writes the charts (SVG + PNG), `results.csv` / `results.md` when there are rows, and
/// `index.html` into `dir`; returns the page's path.
pub fn write(dir: &Path, report: &Report) -> Result<PathBuf> {
    std::fs::create_dir_all(dir).map_err(|e| crate::SweepError::Io {
        path: dir.display().to_string(),
        reason: e.to_string(),
    })?;
    let psnr = plot::write(
        dir,
        &format!("{}: PSNR", report.title),
        Metric::Psnr,
        report.curves,
    )?;
    let fg = plot::write(
        dir,
        &format!("{}: FG-ARI", report.title),
        Metric::FgAri,
        report.curves,
    )?;
    if !report.rows.is_empty() {
        crate::write_bytes(
            &dir.join("results.csv"),
            results::csv(report.rows).as_bytes(),
        )?;
        crate::write_bytes(
            &dir.join("results.md"),
            results::markdown(&report.title, &report.note, report.rows).as_bytes(),
        )?;
    }
    let mut h = String::new();
    let _ = write!(
        h,
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         {r}<title>{t}</title><style>\
         body{{font-family:sans-serif;margin:2em;max-width:1100px;color:#222}}\
         table{{border-collapse:collapse;font-size:13px}}\
         td,th{{border:1px solid #bbb;padding:3px 7px;text-align:right}}\
         th{{background:#eee}} td:first-child,th:first-child{{text-align:left}}\
         img{{max-width:100%;border:1px solid #ddd;margin:6px 0}}\
         .strip img{{height:96px;image-rendering:pixelated;margin-right:4px}}\
         </style></head><body>\n<h1>{t}</h1>\n<p>{n}</p>\n",
        t = escape(&report.title),
        n = escape(&report.note),
        r = report.refresh_s.map_or(String::new(), |s| format!(
            "<meta http-equiv=\"refresh\" content=\"{s}\">"
        )),
    );
    if !report.rows.is_empty() {
        let (header, body) = results::table(report.rows);
        h.push_str("<h2>Results</h2>\n<table>\n<tr>");
        for c in &header {
            let _ = write!(h, "<th>{}</th>", escape(c));
        }
        h.push_str("</tr>\n");
        for row in body {
            h.push_str("<tr>");
            for c in row {
                let c = if c.is_empty() { "n/a".to_string() } else { c };
                let _ = write!(h, "<td>{}</td>", escape(&c));
            }
            h.push_str("</tr>\n");
        }
        h.push_str(
            "</table>\n<p>Also as <a href=\"results.csv\">results.csv</a> and \
             <a href=\"results.md\">results.md</a>.</p>\n",
        );
    }
    h.push_str("<h2>Error against run time</h2>\n");
    for (png, alt) in [(&psnr, "PSNR"), (&fg, "FG-ARI")] {
        let svg = png.replace(".png", ".svg");
        let _ = writeln!(
            h,
            "<p><img src=\"{png}\" alt=\"{alt} against wall-clock seconds\"><br>\
             <a href=\"{svg}\">SVG</a></p>"
        );
    }
    if !report.strips.is_empty() {
        h.push_str("<h2>Renders</h2>\n");
        for (caption, path) in &report.strips {
            let _ = writeln!(
                h,
                "<p>{}</p><div class=\"strip\"><img src=\"{}\" alt=\"{}\"></div>",
                escape(caption),
                escape(path),
                escape(caption)
            );
        }
    }
    h.push_str("</body></html>\n");
    let page = dir.join(PAGE);
    crate::write_bytes(&page, h.as_bytes())?;
    Ok(page)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::results::CurvePoint;

    #[test]
    fn the_page_links_only_files_it_wrote() {
        let dir = tempfile::tempdir().unwrap();
        let curves = [Curve {
            label: "a<b".into(),
            points: vec![CurvePoint {
                step: 1,
                wall_s: 1.0,
                psnr: 20.0,
                baseline_psnr: None,
                fg_ari: None,
            }],
        }];
        let page = write(
            dir.path(),
            &Report {
                title: "run <x>".into(),
                note: "a & b".into(),
                rows: &[],
                curves: &curves,
                strips: Vec::new(),
                refresh_s: Some(7),
            },
        )
        .unwrap();
        let html = std::fs::read_to_string(&page).unwrap();
        assert!(html.contains("run &lt;x&gt;") && html.contains("a &amp; b"));
        assert!(html.contains("<meta http-equiv=\"refresh\" content=\"7\">"));
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".tmp"))
            .collect();
        assert!(left.is_empty(), "no temporary files stay: {left:?}");
        assert!(
            !html.contains("http://") && !html.contains("https://") && !html.contains("<script")
        );
        for link in html
            .split("src=\"")
            .skip(1)
            .chain(html.split("href=\"").skip(1))
        {
            let target = &link[..link.find('"').unwrap()];
            assert!(
                dir.path().join(target).exists()
                    || target.ends_with(".csv")
                    || target.ends_with(".md"),
                "{target}"
            );
        }
        assert!(
            !dir.path().join("results.csv").exists(),
            "no rows, no table files"
        );
    }
}
