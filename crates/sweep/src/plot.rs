//! Error against run time as line charts, written as SVG and PNG.
//!
//! Text is laid out with a font compiled into the binary (DejaVu Sans, see
//! `assets/DejaVuSans-LICENSE.txt`) so charts draw the same on a machine without
//! fontconfig or system fonts; PNGs are drawn into an RGB buffer and encoded by `image`.

use crate::results::Curve;
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

/// Which value of a curve a chart shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Metric {
    Psnr,
    FgAri,
}

impl Metric {
    pub fn file_stem(self) -> &'static str {
        match self {
            Metric::Psnr => "psnr",
            Metric::FgAri => "fg_ari",
        }
    }

    fn label(self) -> &'static str {
        match self {
            Metric::Psnr => "validation PSNR (dB)",
            Metric::FgAri => "validation FG-ARI",
        }
    }

    fn value(self, p: &crate::results::CurvePoint) -> Option<f64> {
        match self {
            Metric::Psnr => Some(p.psnr),
            Metric::FgAri => p.fg_ari,
        }
    }
}

/// The series of a chart: `(label, [(wall_s, value)])`, and a dashed reference line.
struct Chart {
    title: String,
    y_label: &'static str,
    series: Vec<(String, Vec<(f64, f64)>)>,
    reference: Option<(String, f64)>,
}

impl Chart {
    fn new(title: &str, metric: Metric, curves: &[Curve]) -> Self {
        let series: Vec<(String, Vec<(f64, f64)>)> = curves
            .iter()
            .map(|c| {
                let pts = c
                    .points
                    .iter()
                    .filter_map(|p| metric.value(p).map(|v| (p.wall_s, v)))
                    .filter(|(x, y)| x.is_finite() && y.is_finite())
                    .collect();
                (c.label.clone(), pts)
            })
            .collect();
        // PSNR is read against the mean-colour baseline (the same for every run of a
        // dataset); the mean over the curves' evaluations is drawn once.
        let baselines: Vec<f64> = curves
            .iter()
            .flat_map(|c| c.points.iter().filter_map(|p| p.baseline_psnr))
            .filter(|b| b.is_finite())
            .collect();
        let reference = (metric == Metric::Psnr && !baselines.is_empty()).then(|| {
            (
                "mean-colour baseline".to_string(),
                baselines.iter().sum::<f64>() / baselines.len() as f64,
            )
        });
        Self {
            title: title.to_string(),
            y_label: metric.label(),
            series,
            reference,
        }
    }

    fn ranges(&self) -> (f64, f64, f64) {
        let xs = self.series.iter().flat_map(|s| s.1.iter().map(|p| p.0));
        let ys: Vec<f64> = self
            .series
            .iter()
            .flat_map(|s| s.1.iter().map(|p| p.1))
            .chain(self.reference.iter().map(|r| r.1))
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
        for (i, (label, pts)) in self.series.iter().enumerate() {
            let colour = Palette99::pick(i).to_rgba();
            chart
                .draw_series(LineSeries::new(pts.iter().copied(), colour.stroke_width(2)))?
                .label(label.as_str())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2))
                });
            chart.draw_series(pts.iter().map(|&p| Circle::new(p, 3, colour.filled())))?;
        }
        if let Some((label, y)) = &self.reference {
            let grey = RGBColor(110, 110, 110);
            // Dashes drawn as short segments: plotters' dashed style needs a newer API.
            let n = 60;
            let dashes = (0..n).step_by(2).map(|k| {
                let a = x_max * k as f64 / n as f64;
                let b = x_max * (k + 1) as f64 / n as f64;
                PathElement::new(vec![(a, *y), (b, *y)], grey.stroke_width(1))
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

/// `metric` of every curve against wall-clock seconds, as SVG text and PNG bytes.
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

pub fn render(title: &str, metric: Metric, curves: &[Curve]) -> Result<(String, Vec<u8>)> {
    register_font();
    let chart = Chart::new(title, metric, curves);
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

/// Writes `{dir}/{stem}.svg` and `{dir}/{stem}.png`; returns the PNG's file name.
pub fn write(dir: &Path, title: &str, metric: Metric, curves: &[Curve]) -> Result<String> {
    let (svg, png) = render(title, metric, curves)?;
    let stem = metric.file_stem();
    crate::write_bytes(&dir.join(format!("{stem}.svg")), svg.as_bytes())?;
    crate::write_bytes(&dir.join(format!("{stem}.png")), &png)?;
    Ok(format!("{stem}.png"))
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

    #[test]
    fn an_empty_chart_still_draws() {
        let (svg, png) = render("nothing yet", Metric::FgAri, &[]).unwrap();
        assert!(svg.contains("nothing yet"));
        assert!(image::load_from_memory(&png).is_ok());
    }
}
