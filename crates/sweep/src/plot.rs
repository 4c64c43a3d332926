//! Error against run time as line charts, written as SVG and PNG.
//!
//! Text is laid out with a font compiled into the binary (DejaVu Sans, see
//! `assets/DejaVuSans-LICENSE.txt`) so charts draw the same on a machine without
//! fontconfig or system fonts; PNGs are drawn into an RGB buffer and encoded by `image`.

use crate::results::{Curve, CurvePoint};
use crate::{Result, SweepError};
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::Path;
use std::sync::Once;

const FONT: &str = "sans-serif";
static FONT_BYTES: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");
static REGISTER: Once = Once::new();

fn register_font() {
    REGISTER.call_once(|| {
        plotters::style::register_font(FONT, FontStyle::Normal, FONT_BYTES)
            .unwrap_or_else(|_| panic!("the embedded font is a valid TrueType file"));
    });
}

/// Which value of a curve a chart shows (and a `--target` names).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Metric {
    Psnr,
    FgAri,
}

impl Metric {
    /// Every metric, in the order charts and tables show them.
    pub const ALL: [Metric; 2] = [Metric::FgAri, Metric::Psnr];

    /// The metric's name in files, tables and `--target` (`psnr`, `fg_ari`).
    pub fn file_stem(self) -> &'static str {
        match self {
            Metric::Psnr => "psnr",
            Metric::FgAri => "fg_ari",
        }
    }

    /// The metric named `name` as [`Metric::file_stem`] spells it.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|m| m.file_stem() == name)
    }

    /// The metric as people write it (`PSNR`, `FG-ARI`).
    pub fn name(self) -> &'static str {
        match self {
            Metric::Psnr => "PSNR",
            Metric::FgAri => "FG-ARI",
        }
    }

    fn label(self) -> &'static str {
        match self {
            Metric::Psnr => "validation PSNR (dB)",
            Metric::FgAri => "validation FG-ARI",
        }
    }

    /// The metric's value at an evaluation (`None`: not scored there, such as FG-ARI of a
    /// decoder without slots).
    pub fn value(self, p: &CurvePoint) -> Option<f64> {
        match self {
            Metric::Psnr => Some(p.psnr),
            Metric::FgAri => p.fg_ari,
        }
    }
}

/// One seed group on a chart: every seed's curve drawn thin, their mean thick over the
/// band of their spread.
#[derive(Debug, Clone, PartialEq)]
pub struct SeedLines<'a> {
    pub label: String,
    /// Each seed's curve as it was evaluated.
    pub seeds: &'a [Curve],
    /// `(wall_s, mean)` of the seeds at each time of their common grid.
    pub mean: Vec<(f64, f64)>,
    /// `(wall_s, low, high)` of the spread at the same times.
    pub band: Vec<(f64, f64, f64)>,
}

/// A line of a chart: its points `(wall_s, value)`, and how it is drawn.
struct Line {
    /// In the legend; `None`: not listed (a seed among many).
    label: Option<String>,
    colour: RGBAColor,
    width: u32,
    markers: bool,
    pts: Vec<(f64, f64)>,
}

/// A filled band between two lines: `(wall_s, low, high)` points.
struct Band {
    colour: RGBAColor,
    pts: Vec<(f64, f64, f64)>,
}

/// What a chart draws: filled bands under lines, and dashed reference lines.
struct Chart {
    title: String,
    y_label: &'static str,
    bands: Vec<Band>,
    lines: Vec<Line>,
    /// `(label, y, colour)`.
    references: Vec<(String, f64, RGBColor)>,
}

/// `metric`'s finite points of `curve`.
fn points(metric: Metric, curve: &Curve) -> Vec<(f64, f64)> {
    curve
        .points
        .iter()
        .filter_map(|p| metric.value(p).map(|v| (p.wall_s, v)))
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .collect()
}

/// PSNR is read against the mean-colour baseline (the same for every run of a dataset):
/// the mean over the curves' evaluations, drawn once.
fn baseline<'a>(
    metric: Metric,
    curves: impl Iterator<Item = &'a Curve>,
) -> Option<(String, f64, RGBColor)> {
    let baselines: Vec<f64> = curves
        .flat_map(|c| c.points.iter().filter_map(|p| p.baseline_psnr))
        .filter(|b| b.is_finite())
        .collect();
    (metric == Metric::Psnr && !baselines.is_empty()).then(|| {
        (
            "mean-colour baseline".to_string(),
            baselines.iter().sum::<f64>() / baselines.len() as f64,
            RGBColor(110, 110, 110),
        )
    })
}

impl Chart {
    fn new(title: &str, metric: Metric, curves: &[Curve]) -> Self {
        let lines = curves
            .iter()
            .enumerate()
            .map(|(i, c)| Line {
                label: Some(c.label.clone()),
                colour: Palette99::pick(i).to_rgba(),
                width: 2,
                markers: true,
                pts: points(metric, c),
            })
            .collect();
        Self {
            title: title.to_string(),
            y_label: metric.label(),
            bands: Vec::new(),
            lines,
            references: baseline(metric, curves.iter()).into_iter().collect(),
        }
    }

    /// Seed groups in a colour each: seeds thin and pale, the mean thick over the band;
    /// `targets` are dashed lines. The seeds are named in the legend only on a chart of
    /// one group (with several, the legend names each group's mean).
    fn seeds(title: &str, metric: Metric, groups: &[SeedLines], targets: &[f64]) -> Self {
        let (mut bands, mut lines) = (Vec::new(), Vec::new());
        for (i, g) in groups.iter().enumerate() {
            let colour = Palette99::pick(i).to_rgba();
            bands.push(Band {
                colour: colour.mix(0.15),
                pts: g.band.clone(),
            });
            for (k, c) in g.seeds.iter().enumerate() {
                let label =
                    (groups.len() == 1 && k == 0).then(|| format!("each seed ({})", g.seeds.len()));
                lines.push(Line {
                    label,
                    colour: colour.mix(0.45),
                    width: 1,
                    markers: false,
                    pts: points(metric, c),
                });
            }
            lines.push(Line {
                label: Some(format!("{} (mean of {})", g.label, g.seeds.len())),
                colour,
                width: 3,
                markers: false,
                pts: g.mean.clone(),
            });
        }
        let mut references: Vec<(String, f64, RGBColor)> =
            baseline(metric, groups.iter().flat_map(|g| g.seeds.iter()))
                .into_iter()
                .collect();
        let dark = RGBColor(40, 40, 40);
        references.extend(targets.iter().map(|&t| (format!("target {t}"), t, dark)));
        Self {
            title: title.to_string(),
            y_label: metric.label(),
            bands,
            lines,
            references,
        }
    }

    fn ranges(&self) -> (f64, f64, f64) {
        let band_pts = self.bands.iter().flat_map(|b| b.pts.iter());
        let xs = self
            .lines
            .iter()
            .flat_map(|l| l.pts.iter().map(|p| p.0))
            .chain(band_pts.clone().map(|p| p.0));
        let ys: Vec<f64> = self
            .lines
            .iter()
            .flat_map(|l| l.pts.iter().map(|p| p.1))
            .chain(band_pts.flat_map(|p| [p.1, p.2]))
            .chain(self.references.iter().map(|r| r.1))
            .collect();
        let x_max = xs.fold(0.0f64, f64::max).max(1.0) * 1.02;
        let (lo, hi) = ys
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &y| {
                (l.min(y), h.max(y))
            });
        if !lo.is_finite() {
            return (x_max, 0.0, 1.0);
        }
        let pad = ((hi - lo) * 0.08).max(0.05);
        (x_max, lo - pad, hi + pad)
    }

    fn draw<DB: DrawingBackend>(
        &self,
        root: DrawingArea<DB, Shift>,
    ) -> std::result::Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
        root.fill(&WHITE)?;
        let (x_max, y_lo, y_hi) = self.ranges();
        let mut chart = ChartBuilder::on(&root)
            .caption(&self.title, (FONT, 20))
            .margin(14)
            .x_label_area_size(44)
            .y_label_area_size(60)
            .build_cartesian_2d(0f64..x_max, y_lo..y_hi)?;
        chart
            .configure_mesh()
            .x_desc("wall-clock seconds of training")
            .y_desc(self.y_label)
            .label_style((FONT, 13))
            .x_label_formatter(&|x| seconds_label(*x, x_max))
            .axis_desc_style((FONT, 14))
            .light_line_style(WHITE.mix(0.0))
            .draw()?;
        for band in self.bands.iter().filter(|b| b.pts.len() > 1) {
            // The band's outline: along its top, then back along its bottom.
            let outline: Vec<(f64, f64)> = band
                .pts
                .iter()
                .map(|p| (p.0, p.2))
                .chain(band.pts.iter().rev().map(|p| (p.0, p.1)))
                .collect();
            let fill = band.colour.filled();
            chart.draw_series(std::iter::once(Polygon::new(outline, fill)))?;
        }
        for line in &self.lines {
            let style = line.colour.stroke_width(line.width);
            let series = chart.draw_series(LineSeries::new(line.pts.iter().copied(), style))?;
            if let Some(label) = &line.label {
                series
                    .label(label.as_str())
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], style));
            }
            if line.markers {
                let dots = line
                    .pts
                    .iter()
                    .map(|&p| Circle::new(p, 3, line.colour.filled()));
                chart.draw_series(dots)?;
            }
        }
        for &(ref label, y, grey) in &self.references {
            // Dashes drawn as short segments: plotters' dashed style needs a newer API.
            let n = 60;
            let dashes = (0..n).step_by(2).map(|k| {
                let a = x_max * k as f64 / n as f64;
                let b = x_max * (k + 1) as f64 / n as f64;
                PathElement::new(vec![(a, y), (b, y)], grey.stroke_width(1))
            });
            chart
                .draw_series(dashes)?
                .label(label.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], grey));
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.4))
            .label_font((FONT, 12))
            .draw()?;
        root.present()?;
        Ok(())
    }
}

const SIZE: (u32, u32) = (900, 520);

/// Tick label of `x` seconds on an axis up to `x_max`: whole seconds on long runs, enough
/// decimals that neighbouring ticks (about a tenth of the axis apart) differ on short ones.
fn seconds_label(x: f64, x_max: f64) -> String {
    let decimals = match x_max {
        m if m >= 20.0 => 0,
        m if m >= 2.0 => 1,
        _ => 2,
    };
    format!("{x:.decimals$}")
}

/// A chart as SVG text and PNG bytes.
fn encode(chart: &Chart, metric: Metric) -> Result<(String, Vec<u8>)> {
    register_font();
    let err = |reason: String| SweepError::Plot {
        what: format!("{} chart", metric.file_stem()),
        reason,
    };
    let mut svg = String::new();
    chart
        .draw(SVGBackend::with_string(&mut svg, SIZE).into_drawing_area())
        .map_err(|e| err(e.to_string()))?;
    let mut rgb = vec![0u8; (SIZE.0 * SIZE.1 * 3) as usize];
    chart
        .draw(BitMapBackend::with_buffer(&mut rgb, SIZE).into_drawing_area())
        .map_err(|e| err(e.to_string()))?;
    let img = image::RgbImage::from_raw(SIZE.0, SIZE.1, rgb).expect("buffer of the chart's size");
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .map_err(|e| err(e.to_string()))?;
    Ok((svg, png))
}

/// `metric` of every curve against wall-clock seconds, as SVG text and PNG bytes.
pub fn render(title: &str, metric: Metric, curves: &[Curve]) -> Result<(String, Vec<u8>)> {
    encode(&Chart::new(title, metric, curves), metric)
}

/// `metric` of seed groups against wall-clock seconds (each seed thin, the mean thick
/// over its spread, `targets` dashed), as SVG text and PNG bytes.
pub fn render_seeds(
    title: &str,
    metric: Metric,
    groups: &[SeedLines],
    targets: &[f64],
) -> Result<(String, Vec<u8>)> {
    encode(&Chart::seeds(title, metric, groups, targets), metric)
}

/// Writes `{dir}/{stem}.svg` and `{dir}/{stem}.png`; returns the PNG's file name.
fn write_files(dir: &Path, stem: &str, (svg, png): (String, Vec<u8>)) -> Result<String> {
    crate::write_bytes(&dir.join(format!("{stem}.svg")), svg.as_bytes())?;
    crate::write_bytes(&dir.join(format!("{stem}.png")), &png)?;
    Ok(format!("{stem}.png"))
}

/// Writes [`render`]'s chart as `{dir}/{metric}.svg` and `.png`; returns the PNG's name.
pub fn write(dir: &Path, title: &str, metric: Metric, curves: &[Curve]) -> Result<String> {
    write_files(dir, metric.file_stem(), render(title, metric, curves)?)
}

/// Writes [`render_seeds`]'s chart as `{dir}/{stem}.svg` and `.png`; returns the PNG's
/// name.
pub fn write_seeds(
    dir: &Path,
    stem: &str,
    title: &str,
    metric: Metric,
    groups: &[SeedLines],
    targets: &[f64],
) -> Result<String> {
    write_files(dir, stem, render_seeds(title, metric, groups, targets)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::results::CurvePoint;

    fn curve(label: &str, shift: f64) -> Curve {
        Curve {
            label: label.into(),
            points: (0..5)
                .map(|i| CurvePoint {
                    step: i * 10,
                    wall_s: i as f64 * 30.0,
                    psnr: 18.0 + shift + i as f64,
                    baseline_psnr: Some(18.0),
                    fg_ari: Some(0.1 * i as f64),
                })
                .collect(),
        }
    }

    #[test]
    fn charts_have_the_lines_labels_and_a_decodable_png() {
        let curves = [
            curve("decoder=slot_mixer", 0.0),
            curve("decoder=transformer", 2.0),
        ];
        let (svg, png) = render("decoders", Metric::Psnr, &curves).unwrap();
        for text in [
            "decoder=slot_mixer",
            "decoder=transformer",
            "mean-colour baseline",
            "wall-clock seconds",
        ] {
            assert!(svg.contains(text), "SVG lacks `{text}`");
        }
        assert!(svg.matches("<polyline").count() >= 2, "two lines drawn");
        let img = image::load_from_memory(&png).unwrap().to_rgb8();
        assert_eq!((img.width(), img.height()), SIZE);
        // Not a blank canvas: the lines' colours are there, not only white and greys.
        let coloured = img
            .pixels()
            .filter(|p| {
                let [r, g, b] = p.0;
                r.max(g).max(b) - r.min(g).min(b) > 60
            })
            .count();
        assert!(coloured > 500, "{coloured} coloured pixels");
    }

    #[test]
    fn tick_labels_of_short_runs_keep_decimals() {
        assert_eq!(seconds_label(300.4, 600.0), "300");
        assert_eq!(seconds_label(0.4, 5.0), "0.4");
        assert_eq!(seconds_label(0.25, 1.02), "0.25");
        // Ticks a tenth of the axis apart stay distinct.
        for max in [1.02, 3.0, 15.0, 40.0, 900.0] {
            let labels: Vec<String> = (0..10)
                .map(|i| seconds_label(max * i as f64 / 10.0, max))
                .collect();
            let mut d = labels.clone();
            d.dedup();
            assert_eq!(d.len(), labels.len(), "{labels:?}");
        }
    }

    /// A seed group: its band filled, each seed thin and listed once, the mean thick and
    /// named, the target dashed.
    #[test]
    fn seed_charts_draw_the_band_the_seeds_the_mean_and_the_target() {
        let seeds = [curve("seed=0", 0.0), curve("seed=1", 2.0)];
        let group = SeedLines {
            label: "lr=0.001".into(),
            seeds: &seeds,
            mean: (0..5).map(|i| (i as f64 * 30.0, 19.0 + i as f64)).collect(),
            band: (0..5)
                .map(|i| (i as f64 * 30.0, 18.0 + i as f64, 20.0 + i as f64))
                .collect(),
        };
        let (svg, png) = render_seeds("seeds", Metric::Psnr, &[group], &[21.5]).unwrap();
        for text in [
            "each seed (2)",
            "lr=0.001 (mean of 2)",
            "target 21.5",
            "mean-colour baseline",
        ] {
            assert!(svg.contains(text), "SVG lacks `{text}`");
        }
        assert_eq!(svg.matches("<polygon").count(), 1, "one band");
        assert!(!svg.contains("seed=0"), "seeds are not named one by one");
        // Two seeds and the mean, plus their legend samples.
        assert!(svg.matches("<polyline").count() >= 3);
        assert!(image::load_from_memory(&png).is_ok());
    }

    #[test]
    fn an_empty_chart_still_draws() {
        let (svg, png) = render("nothing yet", Metric::FgAri, &[]).unwrap();
        assert!(svg.contains("nothing yet"));
        assert!(image::load_from_memory(&png).is_ok());
    }
}
