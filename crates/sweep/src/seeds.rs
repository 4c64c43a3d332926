//! Time to quality over seeds: the points of a sweep that differ only in their `seed`
//! form a *group*, one configuration measured several times. A group is summarised by
//! its seeds' validation curves, their mean and spread against wall-clock seconds, its
//! final test figures over the seeds, and how long each seed took to reach a target
//! (`--target fg_ari=0.85`).
//!
//! **Spread** is min–max over the seeds throughout (curves, test figures): sweeps run a
//! handful of seeds, where a standard deviation is a poor estimate and hides the worst
//! seed; the range says where every seed fell.
//!
//! **Alignment.** Seeds evaluate every `train.eval_every_s` seconds at a step boundary,
//! so their evaluations fall near each other but not at equal times, and one seed may
//! have an evaluation more or fewer than another (a failed evaluation is no point, a
//! resumed run keeps its own clock). Pairing evaluations by index would then pair
//! unrelated times, so each seed's curve is read as linear between its evaluations and
//! the seeds are compared at the union of their evaluation times, within the span every
//! seed covers (from the latest first evaluation to the earliest last one: nothing is
//! extrapolated). A mean of piecewise-linear curves is piecewise linear with its corners
//! at exactly that union, so these points draw it exactly.
//!
//! **Time to target** is the earliest evaluation at or above the target (both metrics
//! are better higher): a time some evaluation saw, resolved to `eval_every_s`, not a
//! crossing interpolated between evaluations. A group's time is the mean over the seeds
//! that reached the target, always shown with how many did.

use crate::grid::Point;
use crate::plot::Metric;
use crate::results::{self, Curve, CurvePoint, PointResult};
use osrt_run::tensorboard::proto::summary;
use std::fmt;
use std::str::FromStr;

/// The axis whose values make the members of a group.
pub const SEED_AXIS: &str = "seed";

/// How the figures of a group are computed, for the notes under its tables.
pub const METHOD: &str = "Spread is min–max over a group's seeds. Mean curves: each seed's \
    validation curve read as linear between its evaluations, averaged at the union of the \
    seeds' evaluation times within the span every seed covers. Time to a target: the \
    earliest evaluation at or above it (resolved to the evaluation interval); a group's \
    time is the mean over the seeds that reached it.";

/// Why a `--target` cannot be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TargetError {
    #[error("target `{0}`: expected METRIC=VALUE, such as fg_ari=0.85 or psnr=28")]
    Syntax(String),
    #[error("target `{spec}`: unknown metric `{metric}` (expected fg_ari or psnr)")]
    UnknownMetric { spec: String, metric: String },
    #[error("target `{spec}`: `{value}` is not a finite number")]
    NotANumber { spec: String, value: String },
}

/// A validation figure to reach: `metric` at or above `value`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Target {
    pub metric: Metric,
    pub value: f64,
}

impl FromStr for Target {
    type Err = TargetError;

    /// `fg_ari=0.85`, `psnr=28` (spaces around either side allowed).
    fn from_str(spec: &str) -> Result<Self, TargetError> {
        let Some((name, value)) = spec.split_once('=') else {
            return Err(TargetError::Syntax(spec.to_string()));
        };
        let (name, value) = (name.trim(), value.trim());
        let metric = Metric::from_name(name).ok_or_else(|| TargetError::UnknownMetric {
            spec: spec.to_string(),
            metric: name.to_string(),
        })?;
        match value.parse::<f64>() {
            Ok(value) if value.is_finite() => Ok(Self { metric, value }),
            _ => Err(TargetError::NotANumber {
                spec: spec.to_string(),
                value: value.to_string(),
            }),
        }
    }
}

impl fmt::Display for Target {
    /// `fg_ari>=0.85`: the target as a column name.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}>={}", self.metric.file_stem(), self.value)
    }
}

/// When a seed first reached a target.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    pub wall_s: f64,
    pub step: u64,
}

impl Target {
    /// The earliest evaluation of `curve` whose value is at or above the target; `None`
    /// if none is.
    pub fn first_hit(&self, curve: &Curve) -> Option<Hit> {
        curve
            .points
            .iter()
            .filter(|p| self.metric.value(p).is_some_and(|v| v >= self.value))
            .min_by(|a, b| a.wall_s.total_cmp(&b.wall_s))
            .map(|p| Hit {
                wall_s: p.wall_s,
                step: p.step,
            })
    }
}

/// Mean and min–max of some figures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spread {
    pub mean: f64,
    pub min: f64,
    pub max: f64,
    /// How many figures.
    pub n: usize,
}

impl Spread {
    /// Of the finite `values`; `None` if there are none.
    pub fn of(values: impl IntoIterator<Item = f64>) -> Option<Self> {
        let v: Vec<f64> = values.into_iter().filter(|v| v.is_finite()).collect();
        let first = *v.first()?;
        Some(Self {
            mean: v.iter().sum::<f64>() / v.len() as f64,
            min: v.iter().copied().fold(first, f64::min),
            max: v.iter().copied().fold(first, f64::max),
            n: v.len(),
        })
    }
}

/// The seeds of a group at one time of their common grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BandPoint {
    pub wall_s: f64,
    /// The seeds' steps at that time, interpolated like their values, averaged.
    pub step: f64,
    pub value: Spread,
}

/// A metric's mean and spread over a group's seeds against wall-clock seconds.
#[derive(Debug, Clone, PartialEq)]
pub struct MeanCurve {
    pub metric: Metric,
    /// Seeds that have the metric at all (a seed without it, such as FG-ARI of a decoder
    /// without slots, is left out rather than counted as zero).
    pub seeds: usize,
    pub points: Vec<BandPoint>,
}

/// `(wall_s, step, value)` of a seed's finite evaluations of `metric`, in time order.
fn series(curve: &Curve, metric: Metric) -> Vec<(f64, f64, f64)> {
    let mut s: Vec<(f64, f64, f64)> = curve
        .points
        .iter()
        .filter_map(|p: &CurvePoint| Some((p.wall_s, p.step as f64, metric.value(p)?)))
        .filter(|(t, _, v)| t.is_finite() && v.is_finite())
        .collect();
    s.sort_by(|a, b| a.0.total_cmp(&b.0));
    // Two evaluations at one second (a resume) would make a vertical step: keep the later.
    s.dedup_by(|later, earlier| {
        let same = later.0 == earlier.0;
        if same {
            *earlier = *later;
        }
        same
    });
    s
}

/// `(step, value)` of a series at `t` inside its span, linear between evaluations.
fn at(s: &[(f64, f64, f64)], t: f64) -> (f64, f64) {
    let j = s.partition_point(|p| p.0 <= t);
    let a = s[j.saturating_sub(1)];
    match s.get(j) {
        Some(b) if a.0 < t => {
            let f = (t - a.0) / (b.0 - a.0);
            (a.1 + f * (b.1 - a.1), a.2 + f * (b.2 - a.2))
        }
        _ => (a.1, a.2),
    }
}

impl MeanCurve {
    /// The mean and spread of `metric` over `curves`, at the union of their evaluation
    /// times within the span all of them cover (the module's doc says why).
    pub fn new(curves: &[Curve], metric: Metric) -> Self {
        let all: Vec<_> = curves
            .iter()
            .map(|c| series(c, metric))
            .filter(|s| !s.is_empty())
            .collect();
        let from = all.iter().map(|s| s[0].0).fold(f64::NEG_INFINITY, f64::max);
        let to = all
            .iter()
            .map(|s| s[s.len() - 1].0)
            .fold(f64::INFINITY, f64::min);
        let mut grid: Vec<f64> = all
            .iter()
            .flat_map(|s| s.iter().map(|p| p.0))
            .filter(|t| (from..=to).contains(t))
            .collect();
        grid.sort_by(f64::total_cmp);
        grid.dedup();
        let points = grid
            .into_iter()
            .map(|t| {
                let (steps, values): (Vec<f64>, Vec<f64>) = all.iter().map(|s| at(s, t)).unzip();
                BandPoint {
                    wall_s: t,
                    step: steps.iter().sum::<f64>() / steps.len() as f64,
                    value: Spread::of(values).expect("every seed has a finite value"),
                }
            })
            .collect();
        Self {
            metric,
            seeds: all.len(),
            points,
        }
    }
}

/// One seed of a group.
#[derive(Debug, Clone, PartialEq)]
pub struct Member {
    /// Names the seed within its group (`seed=1`, or a run's name).
    pub label: String,
    /// Its validation curve against wall-clock seconds.
    pub curve: Curve,
    /// Its final evaluation, once finished.
    pub result: Option<PointResult>,
}

/// Points or runs that differ only in their seed, in the order first seen.
#[derive(Debug, Clone, PartialEq)]
pub struct Group {
    pub name: String,
    pub members: Vec<Member>,
}

/// The group name of a point's settings: the settings without the seed, named as a point
/// is (`lr=0.0006`; `base` when the seed was all there was).
pub fn group_name(settings: &[(String, String)]) -> String {
    Point {
        settings: settings
            .iter()
            .filter(|(k, _)| k != SEED_AXIS)
            .cloned()
            .collect(),
    }
    .name()
}

impl Group {
    /// Members under their group names, grouped by equal names in first-seen order.
    pub fn by_name(members: impl IntoIterator<Item = (String, Member)>) -> Vec<Self> {
        let mut groups: Vec<Self> = Vec::new();
        for (name, m) in members {
            match groups.iter_mut().find(|g| g.name == name) {
                Some(g) => g.members.push(m),
                None => groups.push(Self {
                    name,
                    members: vec![m],
                }),
            }
        }
        groups
    }

    /// Sweep points `(point, curve, result)` grouped by their settings without the seed;
    /// a member is labelled `seed=N`, or by its point's name in a sweep without a seed
    /// axis (groups of one).
    pub fn by_settings(
        points: impl IntoIterator<Item = (Point, Curve, Option<PointResult>)>,
    ) -> Vec<Self> {
        Self::by_name(points.into_iter().map(|(point, curve, result)| {
            let label = point
                .get(SEED_AXIS)
                .map_or_else(|| point.name(), |s| format!("{SEED_AXIS}={s}"));
            let member = Member {
                label,
                curve,
                result,
            };
            (group_name(&point.settings), member)
        }))
    }
}

/// One target over a group's seeds.
#[derive(Debug, Clone, PartialEq)]
pub struct TargetTimes {
    pub target: Target,
    /// Each seed's first hit, in member order.
    pub hits: Vec<Option<Hit>>,
}

impl TargetTimes {
    /// Seeds that reached the target.
    pub fn reached(&self) -> usize {
        self.hits.iter().flatten().count()
    }

    /// Mean wall-clock seconds and mean step to the target over the seeds that reached it.
    pub fn mean(&self) -> Option<(f64, f64)> {
        let n = self.reached();
        (n > 0).then(|| {
            let (s, k) = self
                .hits
                .iter()
                .flatten()
                .fold((0.0, 0.0), |(s, k), h| (s + h.wall_s, k + h.step as f64));
            (s / n as f64, k / n as f64)
        })
    }
}

/// What a report shows of one group.
#[derive(Debug, Clone, PartialEq)]
pub struct GroupSummary {
    pub name: String,
    /// The members' curves, each labelled as its member.
    pub curves: Vec<Curve>,
    /// Mean validation curves, one per metric in [`Metric::ALL`] order.
    pub means: Vec<MeanCurve>,
    /// Each member's final test figures (`None`: not finished or not scored), per metric
    /// in [`Metric::ALL`] order.
    pub tests: Vec<(Metric, Vec<Option<f64>>)>,
    pub targets: Vec<TargetTimes>,
}

impl GroupSummary {
    pub fn new(group: &Group, targets: &[Target]) -> Self {
        let curves: Vec<Curve> = group
            .members
            .iter()
            .map(|m| Curve {
                label: m.label.clone(),
                points: m.curve.points.clone(),
            })
            .collect();
        let test = |metric: Metric, r: &PointResult| match metric {
            Metric::Psnr => Some(r.psnr),
            Metric::FgAri => r.fg_ari,
        };
        let tests = Metric::ALL
            .iter()
            .map(|&m| {
                let each = group.members.iter();
                (
                    m,
                    each.map(|x| x.result.as_ref().and_then(|r| test(m, r)))
                        .collect(),
                )
            })
            .collect();
        let targets = targets
            .iter()
            .map(|t| TargetTimes {
                target: *t,
                hits: curves.iter().map(|c| t.first_hit(c)).collect(),
            })
            .collect();
        Self {
            name: group.name.clone(),
            means: Metric::ALL
                .iter()
                .map(|&m| MeanCurve::new(&curves, m))
                .collect(),
            curves,
            tests,
            targets,
        }
    }

    /// The mean curve of `metric`.
    pub fn mean(&self, metric: Metric) -> &MeanCurve {
        self.means
            .iter()
            .find(|c| c.metric == metric)
            .expect("a mean curve per metric")
    }

    /// The test figures of `metric` over the members that have one.
    pub fn test(&self, metric: Metric) -> Option<Spread> {
        let (_, each) = self.tests.iter().find(|(m, _)| *m == metric)?;
        Spread::of(each.iter().flatten().copied())
    }

    /// The group's name as a folder name: a point's name already is one; a name made of
    /// run paths has its separators replaced.
    pub fn folder_name(&self) -> String {
        let name = self.name.replace(['/', '\\'], "_");
        match name.strip_prefix('.') {
            Some(rest) => format!("_{rest}"),
            None => name,
        }
    }

    /// The mean curves as TensorBoard scalars (`fg_ari/mean`, `fg_ari/min`, `fg_ari/max`,
    /// `psnr/…`), one event `(step, wall_time, values)` per time of the grid. The step is
    /// the seeds' mean step there, kept strictly increasing (TensorBoard drops the events
    /// of a file after a step that goes back); the event's time is the seconds of training,
    /// so TensorBoard's relative axis counts from the first evaluation.
    pub fn tensorboard_events(&self) -> Vec<(u64, f64, Vec<summary::Value>)> {
        let mut at: Vec<(f64, f64, Metric, Spread)> = self
            .means
            .iter()
            .flat_map(|c| {
                c.points
                    .iter()
                    .map(|p| (p.wall_s, p.step, c.metric, p.value))
            })
            .collect();
        at.sort_by(|a, b| a.0.total_cmp(&b.0));
        let scalar = |tag: String, v: f64| summary::Value {
            tag,
            value: Some(summary::value::Value::SimpleValue(v as f32)),
        };
        let mut events: Vec<(u64, f64, Vec<summary::Value>)> = Vec::new();
        let mut last_t = None;
        for (t, step, metric, v) in at {
            let name = metric.file_stem();
            let values = [("mean", v.mean), ("min", v.min), ("max", v.max)]
                .map(|(k, x)| scalar(format!("{name}/{k}"), x));
            match events.last_mut() {
                Some(e) if last_t == Some(t) => e.2.extend(values),
                last => {
                    let after = last.map_or(0, |e| e.0 + 1);
                    events.push(((step.round() as u64).max(after), t, values.into()));
                }
            }
            last_t = Some(t);
        }
        events
    }
}

/// The seed groups of a report and the targets they are timed against.
#[derive(Debug, Clone, PartialEq)]
pub struct SeedReport {
    pub targets: Vec<Target>,
    pub groups: Vec<GroupSummary>,
}

fn figure(metric: Metric, v: f64) -> String {
    match metric {
        Metric::FgAri => format!("{v:.3}"),
        Metric::Psnr => format!("{v:.2}"),
    }
}

impl SeedReport {
    pub fn new(groups: &[Group], targets: &[Target]) -> Self {
        Self {
            targets: targets.to_vec(),
            groups: groups
                .iter()
                .map(|g| GroupSummary::new(g, targets))
                .collect(),
        }
    }

    /// Whether any group has more than one seed (else the groups are the points, and
    /// their charts would repeat the points' chart).
    pub fn has_seeds(&self) -> bool {
        self.groups.iter().any(|g| g.curves.len() > 1)
    }

    /// The table people read (`results.md`, the page): mean (min–max) and each seed's
    /// figure in one cell, empty where there is none.
    pub fn table(&self) -> (Vec<String>, Vec<Vec<String>>) {
        let mut header = vec!["group".to_string(), "seeds".to_string()];
        for m in Metric::ALL {
            let name = m.file_stem();
            header.push(format!("test {name} mean (min–max)"));
            header.push(format!("test {name} each seed"));
        }
        for t in &self.targets {
            header.push(format!("time to {t}: mean s (reached)"));
            header.push(format!("time to {t}: each seed"));
        }
        let rows = self.groups.iter().map(|g| {
            let labels: Vec<&str> = g.curves.iter().map(|c| c.label.as_str()).collect();
            let mut row = vec![
                g.name.clone(),
                format!("{}: {}", labels.len(), labels.join(", ")),
            ];
            for (m, each) in &g.tests {
                row.push(g.test(*m).map_or(String::new(), |s| {
                    let (lo, hi) = (figure(*m, s.min), figure(*m, s.max));
                    format!("{} ({lo}–{hi})", figure(*m, s.mean))
                }));
                let each = each
                    .iter()
                    .map(|v| v.map_or("n/a".into(), |v| figure(*m, v)));
                row.push(each.collect::<Vec<_>>().join(" / "));
            }
            for t in &g.targets {
                let n = format!("({}/{})", t.reached(), t.hits.len());
                row.push(
                    t.mean()
                        .map_or(format!("never {n}"), |(s, _)| format!("{s:.1} {n}")),
                );
                let each = t.hits.iter().map(|h| {
                    h.map_or("never".into(), |h| {
                        format!("{:.1} s @ step {}", h.wall_s, h.step)
                    })
                });
                row.push(each.collect::<Vec<_>>().join(" / "));
            }
            row
        });
        (header, rows.collect())
    }

    /// `groups.csv` text: one figure per cell where a program reads it (each seed's
    /// figures `;`-separated in member order, empty where there is none).
    pub fn csv(&self) -> String {
        let mut header = vec!["group".to_string(), "seeds".into(), "members".into()];
        for m in Metric::ALL {
            let n = m.file_stem();
            header.extend(["mean", "min", "max", "each"].map(|k| format!("test_{n}_{k}")));
        }
        for t in &self.targets {
            let k = ["reached", "mean_s", "mean_step", "each_s", "each_step"];
            header.extend(k.map(|k| format!("{t}_{k}")));
        }
        let opt = |v: Option<String>| v.unwrap_or_default();
        let join = |v: Vec<String>| v.join(";");
        let body = self.groups.iter().map(|g| {
            let labels = g.curves.iter().map(|c| c.label.clone()).collect();
            let mut row = vec![g.name.clone(), g.curves.len().to_string(), join(labels)];
            for (m, each) in &g.tests {
                let s = g.test(*m);
                row.push(opt(s.map(|s| figure(*m, s.mean))));
                row.push(opt(s.map(|s| figure(*m, s.min))));
                row.push(opt(s.map(|s| figure(*m, s.max))));
                row.push(join(
                    each.iter().map(|v| opt(v.map(|v| figure(*m, v)))).collect(),
                ));
            }
            for t in &g.targets {
                let mean = t.mean();
                row.push(t.reached().to_string());
                row.push(opt(mean.map(|(s, _)| format!("{s:.1}"))));
                row.push(opt(mean.map(|(_, k)| format!("{k:.0}"))));
                let each = |f: &dyn Fn(Hit) -> String| {
                    join(t.hits.iter().map(|h| opt(h.map(f))).collect())
                };
                row.push(each(&|h| format!("{:.1}", h.wall_s)));
                row.push(each(&|h| h.step.to_string()));
            }
            row
        });
        results::csv_text(&header, &body.collect::<Vec<_>>())
    }

    /// The section of `results.md`: a heading, how the figures are computed, the table.
    pub fn markdown(&self) -> String {
        let (header, body) = self.table();
        format!(
            "## Seed groups\n\n{METHOD}\n\n{}",
            results::markdown_table(&header, &body)
        )
    }
}
