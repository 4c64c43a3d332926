//! The report page: one static HTML file beside its PNGs. No scripts, no external
//! resources: it opens from disk with no server and no network.

use crate::Result;
use crate::plot::{self, Metric, SeedLines};
use crate::results::{self, Curve, PointResult};
use crate::seeds::{self, GroupSummary, SeedReport};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

pub const PAGE: &str = "index.html";
/// The seed groups' table, one figure per cell.
pub const GROUPS_CSV: &str = "groups.csv";

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
    write_page(dir, report, None)
}

/// [`write`], and the seed groups: their table on the page, in `groups.csv` and as a
/// section of `results.md`, and, where a group has several seeds, a chart per group and
/// metric (each seed thin, the mean thick over its spread, the targets dashed) and one
/// of every group's mean.
pub fn write_with_seeds(dir: &Path, report: &Report, seeds: &SeedReport) -> Result<PathBuf> {
    write_page(dir, report, Some(seeds))
}

fn write_page(dir: &Path, report: &Report, seeds: Option<&SeedReport>) -> Result<PathBuf> {
    std::fs::create_dir_all(dir).map_err(|e| crate::SweepError::Io {
        path: dir.display().to_string(),
        reason: e.to_string(),
    })?;
    let mut charts = Vec::new();
    for metric in [Metric::Psnr, Metric::FgAri] {
        let title = format!("{}: {}", report.title, metric.name());
        charts.push((
            plot::write(dir, &title, metric, report.curves)?,
            metric.name(),
        ));
    }
    let seeds = seeds.filter(|s| !s.groups.is_empty());
    write_tables(dir, report, seeds)?;
    let mut h = head(report);
    if !report.rows.is_empty() {
        let (header, body) = results::table(report.rows);
        h.push_str("<h2>Results</h2>\n");
        html_table(&mut h, &header, &body);
        h.push_str(
            "<p>Also as <a href=\"results.csv\">results.csv</a> and \
             <a href=\"results.md\">results.md</a>.</p>\n",
        );
    }
    if let Some(seeds) = seeds {
        seeds_section(&mut h, dir, &report.title, seeds)?;
    }
    h.push_str("<h2>Error against run time</h2>\n");
    for (png, alt) in &charts {
        image_link(&mut h, png, &format!("{alt} against wall-clock seconds"));
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

/// `results.csv` and `results.md` when there are rows (the seed groups' section in the
/// latter), `groups.csv` when there are groups.
fn write_tables(dir: &Path, report: &Report, seeds: Option<&SeedReport>) -> Result<()> {
    if let Some(seeds) = seeds {
        crate::write_bytes(&dir.join(GROUPS_CSV), seeds.csv().as_bytes())?;
    }
    if report.rows.is_empty() {
        return Ok(());
    }
    crate::write_bytes(
        &dir.join("results.csv"),
        results::csv(report.rows).as_bytes(),
    )?;
    let mut md = results::markdown(&report.title, &report.note, report.rows);
    if let Some(seeds) = seeds {
        md.push('\n');
        md.push_str(&seeds.markdown());
    }
    crate::write_bytes(&dir.join("results.md"), md.as_bytes())
}

/// The page up to its first section: title, note, style.
fn head(report: &Report) -> String {
    format!(
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
    )
}

fn html_table(h: &mut String, header: &[String], body: &[Vec<String>]) {
    h.push_str("<table>\n<tr>");
    for c in header {
        let _ = write!(h, "<th>{}</th>", escape(c));
    }
    h.push_str("</tr>\n");
    for row in body {
        h.push_str("<tr>");
        for c in row {
            let c = if c.is_empty() { "n/a" } else { c.as_str() };
            let _ = write!(h, "<td>{}</td>", escape(c));
        }
        h.push_str("</tr>\n");
    }
    h.push_str("</table>\n");
}

/// A chart's PNG with a link to its SVG.
fn image_link(h: &mut String, png: &str, alt: &str) {
    let svg = png.replace(".png", ".svg");
    let _ = writeln!(
        h,
        "<p><img src=\"{}\" alt=\"{}\"><br><a href=\"{}\">SVG</a></p>",
        escape(png),
        escape(alt),
        escape(&svg)
    );
}

/// A group's seeds and mean curve of `metric` for a chart; `None` if no seed has it.
fn lines(g: &GroupSummary, metric: Metric) -> Option<SeedLines<'_>> {
    let mean = g.mean(metric);
    (mean.seeds > 0).then(|| SeedLines {
        label: g.name.clone(),
        seeds: &g.curves,
        mean: mean
            .points
            .iter()
            .map(|p| (p.wall_s, p.value.mean))
            .collect(),
        band: mean
            .points
            .iter()
            .map(|p| (p.wall_s, p.value.min, p.value.max))
            .collect(),
    })
}

/// The seed groups' section: how they are computed, their table and their charts.
fn seeds_section(h: &mut String, dir: &Path, title: &str, seeds: &SeedReport) -> Result<()> {
    let (header, body) = seeds.table();
    let _ = writeln!(h, "<h2>Seed groups</h2>\n<p>{}</p>", escape(seeds::METHOD));
    html_table(h, &header, &body);
    let _ = writeln!(
        h,
        "<p>Also as <a href=\"{GROUPS_CSV}\">{GROUPS_CSV}</a>.</p>"
    );
    if !seeds.has_seeds() {
        return Ok(());
    }
    for metric in Metric::ALL {
        let targets: Vec<f64> = seeds
            .targets
            .iter()
            .filter(|t| t.metric == metric)
            .map(|t| t.value)
            .collect();
        let (stem, name) = (metric.file_stem(), metric.name());
        let all: Vec<SeedLines> = seeds
            .groups
            .iter()
            .filter_map(|g| lines(g, metric))
            .collect();
        if seeds.groups.len() > 1 && !all.is_empty() {
            let chart_title = format!("{title}: {name}, mean of each group");
            let png = plot::write_seeds(
                dir,
                &format!("groups-{stem}"),
                &chart_title,
                metric,
                &all,
                &targets,
            )?;
            image_link(
                h,
                &png,
                &format!("{name} of every group's mean against wall-clock seconds"),
            );
        }
        for (i, g) in seeds
            .groups
            .iter()
            .enumerate()
            .filter(|(_, g)| g.curves.len() > 1)
        {
            let Some(one) = lines(g, metric) else {
                continue;
            };
            let chart_title = format!("{}: {name} over seeds", g.name);
            let file = format!("group-{i}-{stem}");
            let png = plot::write_seeds(dir, &file, &chart_title, metric, &[one], &targets)?;
            image_link(
                h,
                &png,
                &format!("{name} of {} against wall-clock seconds", g.name),
            );
        }
    }
    Ok(())
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
