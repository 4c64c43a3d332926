//! A sweep file: a base job (preset or job config), optional explicit points
//! (`[[points]]`, each a table of axis settings: rows that are no product, like a paper's
//! table) and axes. The points are the explicit ones (or the base job alone) crossed with
//! the Cartesian product of the axes, in the fixed axis order of [`Axes`], first axis
//! slowest; each point is named by its settings (`decoder=slot_mixer,slots=6`), which is
//! also its run folder's name.

use crate::{Result, SweepError};
use osrt_dataset::TargetViews;
use osrt_model::slot_attention::SlotInit;
use osrt_trainer::JobConfig;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct SweepFile {
    /// Names the output folder (`runs/sweeps/<name>` by default).
    pub name: String,
    /// Named job preset for the base job, unless `config` is given.
    #[serde(default = "default_preset")]
    pub preset: String,
    /// A job config (TOML) for the base job; relative to the sweep file.
    #[serde(default)]
    pub config: Option<PathBuf>,
    /// Dataset directory or URL (the default `data` is generated if absent).
    #[serde(default = "default_data")]
    pub data: String,
    /// Local worker processes per point.
    #[serde(default = "default_workers")]
    pub workers: usize,
    /// Compute threads per worker (default: cores / workers).
    #[serde(default)]
    pub threads: Option<usize>,
    /// Training budget per point: every point gets the same one.
    #[serde(default)]
    pub max_minutes: Option<f64>,
    #[serde(default)]
    pub max_steps: Option<u64>,
    /// Split each finished point is evaluated on.
    #[serde(default = "default_split")]
    pub eval_split: String,
    /// Evaluate at most this many scenes of it (default: all).
    #[serde(default)]
    pub eval_scenes: Option<usize>,
    /// Explicit points, each a table of axis settings (`input_views = 3`,
    /// `decoder = "transformer"`, …), crossed with the axes.
    #[serde(default)]
    pub points: Vec<toml::Table>,
    #[serde(default)]
    pub axes: Axes,
}

/// The settings a point may make, in the order names list them.
const AXES: [&str; 17] = [
    "decoder",
    "poses",
    "input_views",
    "slots",
    "iterations",
    "slot_init",
    "ray_input",
    "targets",
    "seed",
    "lr",
    "batch_size",
    "micro_batch_size",
    "rays_per_scene",
    "warmup_steps",
    "horizon",
    "slot_gradient",
    "precision",
];

/// An explicit point's settings as text, in [`AXES`] order; `i` names it in errors.
fn explicit_point(table: &toml::Table, i: usize) -> std::result::Result<Point, String> {
    if let Some(k) = table.keys().find(|k| !AXES.contains(&k.as_str())) {
        return Err(format!(
            "points[{i}]: unknown setting `{k}` (expected one of {AXES:?})"
        ));
    }
    let mut settings = Vec::new();
    for axis in AXES {
        let Some(v) = table.get(axis) else { continue };
        let text = match v {
            toml::Value::String(s) => s.clone(),
            toml::Value::Integer(n) => n.to_string(),
            toml::Value::Float(x) => x.to_string(),
            other => return Err(format!("points[{i}].{axis}: `{other}` is not a value")),
        };
        settings.push((axis.to_string(), text));
    }
    if settings.is_empty() {
        return Err(format!("points[{i}] sets nothing"));
    }
    Ok(Point { settings })
}

fn default_preset() -> String {
    "clevr-lite-cpu".into()
}
fn default_data() -> String {
    "data".into()
}
fn default_workers() -> usize {
    2
}
fn default_split() -> String {
    "test".into()
}

/// What a point is trained to reconstruct (paper §4.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Targets {
    /// Novel-view synthesis: targets are drawn from every view of the scene.
    Novel,
    /// 2D reconstruction: targets are the input views only.
    Input,
}

/// The axes a sweep can vary; an empty list leaves the base job's setting.
#[derive(Debug, Clone, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Axes {
    #[serde(default)]
    pub decoder: Vec<String>,
    /// Input poses: `absolute` (OSRT) or `unposed` (Up-OSRT).
    #[serde(default)]
    pub poses: Vec<String>,
    #[serde(default)]
    pub input_views: Vec<usize>,
    #[serde(default)]
    pub slots: Vec<usize>,
    #[serde(default)]
    pub iterations: Vec<usize>,
    #[serde(default)]
    pub slot_init: Vec<String>,
    /// How the encoder reads the rays: `concat` (paper) or `add`.
    #[serde(default)]
    pub ray_input: Vec<String>,
    #[serde(default)]
    pub targets: Vec<Targets>,
    #[serde(default)]
    pub seed: Vec<u64>,
    #[serde(default)]
    pub lr: Vec<f64>,
    /// Scenes per optimiser step, and per forward and backward pass.
    #[serde(default)]
    pub batch_size: Vec<usize>,
    #[serde(default)]
    pub micro_batch_size: Vec<usize>,
    /// Target rays per scene and step.
    #[serde(default)]
    pub rays_per_scene: Vec<usize>,
    #[serde(default)]
    pub warmup_steps: Vec<u64>,
    /// Where the learning rate's decay ends: `fixed`, `budget` or a step count.
    #[serde(default)]
    pub horizon: Vec<String>,
    /// How the gradient flows through the slot iterations: `full`, `implicit`, `bilevel`.
    #[serde(default)]
    pub slot_gradient: Vec<String>,
    /// The products' precision (`train.precision`): `f32`, or `bf16` (bf16 operands, f32
    /// sums, where the device has bf16 products).
    #[serde(default)]
    pub precision: Vec<String>,
}

impl Axes {
    /// `(axis, values as text)` in the fixed order, empty axes left out.
    fn listed(&self) -> Vec<(&'static str, Vec<String>)> {
        fn text<T: ToString>(v: &[T]) -> Vec<String> {
            v.iter().map(|x| x.to_string()).collect()
        }
        let targets = self
            .targets
            .iter()
            .map(|t| match t {
                Targets::Novel => "novel".to_string(),
                Targets::Input => "input".to_string(),
            })
            .collect();
        [
            ("decoder", self.decoder.clone()),
            ("poses", self.poses.clone()),
            ("input_views", text(&self.input_views)),
            ("slots", text(&self.slots)),
            ("iterations", text(&self.iterations)),
            ("slot_init", self.slot_init.clone()),
            ("ray_input", self.ray_input.clone()),
            ("targets", targets),
            ("seed", text(&self.seed)),
            ("lr", text(&self.lr)),
            ("batch_size", text(&self.batch_size)),
            ("micro_batch_size", text(&self.micro_batch_size)),
            ("rays_per_scene", text(&self.rays_per_scene)),
            ("warmup_steps", text(&self.warmup_steps)),
            ("horizon", self.horizon.clone()),
            ("slot_gradient", self.slot_gradient.clone()),
            ("precision", self.precision.clone()),
        ]
        .into_iter()
        .filter(|(_, v)| !v.is_empty())
        .collect()
    }
}

/// One grid point: `(axis, value)` settings applied over the base job.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Point {
    pub settings: Vec<(String, String)>,
}

impl Point {
    /// `axis=value,…`, or `base` for a sweep without axes. Also the run folder's name.
    pub fn name(&self) -> String {
        if self.settings.is_empty() {
            return "base".into();
        }
        self.settings
            .iter()
            .map(|(k, v)| format!("{k}={v}"))
            .collect::<Vec<_>>()
            .join(",")
    }

    /// Value of `axis` at this point, if the sweep varies it.
    pub fn get(&self, axis: &str) -> Option<&str> {
        self.settings
            .iter()
            .find(|(k, _)| k == axis)
            .map(|(_, v)| v.as_str())
    }

    /// The base job with this point's settings.
    pub fn apply(&self, base: &JobConfig) -> Result<JobConfig> {
        let err = |reason: String| SweepError::Point {
            point: self.name(),
            reason,
        };
        let mut job = base.clone();
        for (axis, value) in &self.settings {
            let int = || {
                value
                    .parse::<usize>()
                    .map_err(|e| err(format!("{axis} = {value}: {e}")))
            };
            match axis.as_str() {
                "decoder" => {
                    job.model = job.model.clone().with_decoder(value).ok_or_else(|| {
                        err(format!(
                            "unknown decoder `{value}`: expected slot_mixer, spatial_broadcast, \
                             transformer or volumetric"
                        ))
                    })?
                }
                "poses" => job.model.encoder.poses = value.parse().map_err(err)?,
                "input_views" => job.train.input_views = int()?,
                "batch_size" => job.train.batch_size = int()?,
                "micro_batch_size" => job.train.micro_batch_size = Some(int()?),
                "rays_per_scene" => job.train.rays_per_scene = int()?,
                "warmup_steps" => job.train.warmup_steps = int()? as u64,
                "horizon" => job.train.horizon = value.parse().map_err(err)?,
                "slot_gradient" => {
                    job.model.slot_attention.gradient = value.parse().map_err(err)?
                }
                "precision" => job.train.precision = value.parse().map_err(err)?,
                "slots" => job.model.slot_attention.num_slots = int()?,
                "iterations" => job.model.slot_attention.iterations = int()?,
                "slot_init" => {
                    job.model.slot_attention.init = value.parse::<SlotInit>().map_err(err)?
                }
                "ray_input" => job.model.encoder.ray_input = value.parse().map_err(err)?,
                "targets" => {
                    job.train.target_views = match value.as_str() {
                        "novel" => TargetViews::All,
                        "input" => TargetViews::Input,
                        other => return Err(err(format!("unknown targets `{other}`"))),
                    }
                }
                "seed" => {
                    job.train.seed = value
                        .parse()
                        .map_err(|e| err(format!("seed = {value}: {e}")))?
                }
                "lr" => {
                    job.train.lr = value
                        .parse()
                        .map_err(|e| err(format!("lr = {value}: {e}")))?
                }
                other => return Err(err(format!("unknown axis `{other}`"))),
            }
        }
        job.validate().map_err(|e| err(e.to_string()))?;
        Ok(job)
    }
}

impl SweepFile {
    /// Whether this file is `earlier` with points added: every setting outside the points
    /// and axes the same, and every point of `earlier` among this file's (compared by
    /// name, which is how a sweep's folder names its points' runs). A sweep folder of
    /// `earlier` then keeps its finished points for this file.
    pub fn extends(&self, earlier: &SweepFile) -> bool {
        let base = |f: &SweepFile| {
            let mut f = f.clone();
            f.points.clear();
            f.axes = Axes::default();
            toml::to_string(&f).ok()
        };
        let names = |f: &SweepFile| f.points().iter().map(Point::name).collect::<Vec<_>>();
        let now = names(self);
        base(self).is_some()
            && base(self) == base(earlier)
            && names(earlier).iter().all(|n| now.contains(n))
    }

    pub fn load(path: &Path) -> Result<Self> {
        let text = crate::read_text(path)?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses and checks a sweep file's text; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<Self> {
        let err = |reason: String| SweepError::File {
            path: origin.to_string(),
            reason,
        };
        let file: Self = toml::from_str(text).map_err(|e| err(e.to_string()))?;
        if file.name.is_empty() || file.name.contains(['/', '\\']) || file.name.starts_with('.') {
            return Err(err(format!(
                "name `{}` must be a plain folder name",
                file.name
            )));
        }
        if file.max_minutes.is_none() && file.max_steps.is_none() {
            return Err(err(
                "set max_minutes or max_steps: every point needs the same, finite budget".into(),
            ));
        }
        if file.workers == 0 {
            return Err(err("workers must be at least 1".into()));
        }
        for (i, t) in file.points.iter().enumerate() {
            let p = explicit_point(t, i).map_err(err)?;
            if file.axes.listed().iter().any(|(a, _)| p.get(a).is_some()) {
                return Err(err(format!(
                    "points[{i}] sets a setting the axes vary too: {}",
                    p.name()
                )));
            }
        }
        Ok(file)
    }

    /// The base job: `config` (relative to `dir`, the sweep file's folder) or `preset`.
    pub fn base_job(&self, dir: &Path) -> Result<JobConfig> {
        let err = |reason: String| SweepError::File {
            path: self.name.clone(),
            reason,
        };
        match &self.config {
            Some(p) => JobConfig::load(&dir.join(p)).map_err(|e| err(e.to_string())),
            None => JobConfig::preset(&self.preset).map_err(|e| err(e.to_string())),
        }
    }

    /// Every point: the explicit ones (or the base job) crossed with the axes, first
    /// axis slowest.
    pub fn points(&self) -> Vec<Point> {
        let mut points: Vec<Point> = match self.points.is_empty() {
            true => vec![Point {
                settings: Vec::new(),
            }],
            false => self
                .points
                .iter()
                .enumerate()
                .map(|(i, t)| explicit_point(t, i).expect("checked when parsed"))
                .collect(),
        };
        for (axis, values) in self.axes.listed() {
            points = points
                .into_iter()
                .flat_map(|p| {
                    values.iter().map(move |v| {
                        let mut settings = p.settings.clone();
                        settings.push((axis.to_string(), v.clone()));
                        Point { settings }
                    })
                })
                .collect();
        }
        points
    }

    /// Checks every point's job, and that `views` (the dataset's fewest views per scene)
    /// can feed its input views, before any training starts.
    pub fn check(&self, base: &JobConfig, views: usize) -> Result<Vec<(Point, JobConfig)>> {
        self.points()
            .into_iter()
            .map(|p| {
                let job = p.apply(base)?;
                if job.train.input_views > views {
                    return Err(SweepError::Point {
                        point: p.name(),
                        reason: format!(
                            "{} input views, but the dataset has only {views} views per scene",
                            job.train.input_views
                        ),
                    });
                }
                Ok((p, job))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests;
