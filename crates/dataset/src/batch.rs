//! Builds training and evaluation batches from decoded scenes: choose input views, sample
//! target rays with a seeded RNG, and lay everything out as flat `f32` buffers ready to be
//! wrapped as tensors. Nothing is padded: every scene of a batch must have the same input
//! image size and the same number of target rays, and a mismatch is an error.

use crate::camera::Camera;
use crate::error::{DatasetError, Result};
use crate::rays::{pixel_ray, view_rays_strided};
use crate::scene::Scene;
use rand::Rng;
use rand::seq::index;
use serde::{Deserialize, Serialize};

/// Which views target rays are drawn from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum TargetViews {
    /// Every view of the scene, inputs included (OSRT's novel-view setup on CLEVR-3D).
    #[default]
    All,
    /// Only views that are not inputs.
    NonInput,
    /// Only the input views: 2D reconstruction training (paper §4.2).
    Input,
}

/// The coordinate frame of every ray of a batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum RayFrame {
    /// The dataset's world frame (posed models).
    #[default]
    World,
    /// The frame of the scene's first chosen input camera (Up-OSRT): every camera is
    /// [`crate::Camera::relative_to`] it before its rays are derived, so a rigid motion
    /// of the whole scene leaves the batch unchanged.
    FirstInput,
}

impl RayFrame {
    /// `camera` in this frame, where `reference` is the scene's first input camera.
    pub fn express(self, camera: &Camera, reference: &Camera) -> Camera {
        match self {
            RayFrame::World => *camera,
            RayFrame::FirstInput => camera.relative_to(reference),
        }
    }
}

/// How input views are chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum InputSelection {
    /// The first `input_views` views (evaluation: fixed and comparable).
    #[default]
    First,
    /// A seeded random subset, in random order (training).
    Random,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BatchConfig {
    pub input_views: usize,
    pub input_selection: InputSelection,
    pub target_views: TargetViews,
    /// Target rays per scene; `None` takes every pixel of the target views, in order
    /// (evaluation renders whole images).
    pub rays_per_scene: Option<usize>,
    /// Also gather the instance id of every target ray (needs masks; evaluation only).
    pub with_masks: bool,
    /// Fraction of the sampled rays drawn from *salient* pixels — pixels whose colour
    /// differs from their view's median colour by more than [`SALIENCE_THRESHOLD`] — the
    /// rest uniformly from the remaining pixels. 0 = uniform sampling (the paper). An
    /// explicit training option: it over-weights objects and shadows in the loss, and
    /// uses only the images (never masks).
    #[serde(default)]
    pub salient_fraction: f32,
    /// The frame rays are expressed in (inputs and targets alike).
    #[serde(default)]
    pub ray_frame: RayFrame,
    /// Input views point-sampled every `input_stride` pixels along both axes, from pixel
    /// `input_stride / 2` on, each kept pixel with its own ray; targets keep every pixel.
    /// 1 = the whole view. stelzner/osrt's `downsample: k` is `2^k`: its CLEVR-3D model
    /// reads 160 × 120 inputs beside 320 × 240 targets.
    #[serde(default = "one")]
    pub input_stride: usize,
}

fn one() -> usize {
    1
}

/// Pixels kept along a side of `len` at `stride` (from `stride / 2` on).
pub fn strided_len(len: usize, stride: usize) -> usize {
    (len.saturating_sub(stride / 2)).div_ceil(stride.max(1))
}

/// Summed absolute RGB difference (in `[0, 3]`) from the view's median colour above which
/// a pixel counts as salient.
pub const SALIENCE_THRESHOLD: f32 = 0.1;

/// Indices (into the concatenated target views) of salient pixels.
fn salient_pixels(scene: &Scene, targets: &[usize]) -> Vec<usize> {
    let mut out = Vec::new();
    let mut base = 0;
    for &t in targets {
        let v = &scene.views[t];
        let n = v.num_pixels();
        let mut median = [0u8; 3];
        for (c, m) in median.iter_mut().enumerate() {
            let mut ch: Vec<u8> = v.image.iter().skip(c).step_by(3).copied().collect();
            let mid = ch.len() / 2;
            *m = *ch.select_nth_unstable(mid).1;
        }
        for p in 0..n {
            let d: i32 = (0..3)
                .map(|c| (v.image[3 * p + c] as i32 - median[c] as i32).abs())
                .sum();
            if d as f32 / 255.0 > SALIENCE_THRESHOLD {
                out.push(base + p);
            }
        }
        base += n;
    }
    out
}

/// `k` distinct pixels of `total`: a salient share first, the rest uniform over the others.
fn sample_pixels(
    scene: &Scene,
    targets: &[usize],
    total: usize,
    k: usize,
    fraction: f32,
    rng: &mut impl Rng,
) -> Vec<usize> {
    if fraction <= 0.0 {
        return index::sample(rng, total, k).into_vec();
    }
    let salient = salient_pixels(scene, targets);
    let ks = ((fraction.min(1.0) * k as f32).round() as usize).min(salient.len());
    let mut picks: Vec<usize> = index::sample(rng, salient.len(), ks)
        .into_iter()
        .map(|i| salient[i])
        .collect();
    let mut taken = vec![false; total];
    for &p in &picks {
        taken[p] = true;
    }
    let rest: Vec<usize> = (0..total).filter(|&p| !taken[p]).collect();
    picks.extend(
        index::sample(rng, rest.len(), k - ks)
            .into_iter()
            .map(|i| rest[i]),
    );
    picks
}

/// A batch as flat row-major buffers. `b` scenes, `v` input views of `h × w` pixels,
/// `k` target rays per scene.
#[derive(Debug, Clone, PartialEq)]
pub struct Batch {
    pub scene_ids: Vec<u64>,
    pub batch_size: usize,
    pub input_views: usize,
    pub height: usize,
    pub width: usize,
    /// `[b, v, h, w, 3]`, RGB in `[0, 1]`.
    pub input_images: Vec<f32>,
    /// `[b, v, h, w, 3]`
    pub input_origins: Vec<f32>,
    /// `[b, v, h, w, 3]`, unit length.
    pub input_directions: Vec<f32>,
    pub rays_per_scene: usize,
    /// `[b, k, 3]`
    pub target_origins: Vec<f32>,
    /// `[b, k, 3]`, unit length.
    pub target_directions: Vec<f32>,
    /// `[b, k, 3]`, RGB in `[0, 1]`.
    pub target_rgb: Vec<f32>,
    /// `[b, k]` instance ids (0 = background), when asked for.
    pub target_masks: Option<Vec<u8>>,
    /// `[b, k]` `(view index in the scene, pixel index in that view)` of each target ray.
    pub target_pixels: Vec<(u32, u32)>,
}

fn choose_inputs(scene: &Scene, cfg: &BatchConfig, rng: &mut impl Rng) -> Result<Vec<usize>> {
    let n = scene.views.len();
    if cfg.input_views == 0 || cfg.input_views > n {
        return Err(DatasetError::Batch(format!(
            "scene {}: {} input views requested, the scene has {n}",
            scene.id, cfg.input_views
        )));
    }
    Ok(match cfg.input_selection {
        InputSelection::First => (0..cfg.input_views).collect(),
        InputSelection::Random => index::sample(rng, n, cfg.input_views).into_vec(),
    })
}

fn target_view_ids(scene: &Scene, inputs: &[usize], which: TargetViews) -> Result<Vec<usize>> {
    let ids: Vec<usize> = match which {
        TargetViews::All => (0..scene.views.len()).collect(),
        TargetViews::Input => inputs.to_vec(),
        TargetViews::NonInput => (0..scene.views.len())
            .filter(|v| !inputs.contains(v))
            .collect(),
    };
    if ids.is_empty() {
        return Err(DatasetError::Batch(format!(
            "scene {}: no target views left ({which:?} with {} of {} views as inputs)",
            scene.id,
            inputs.len(),
            scene.views.len()
        )));
    }
    Ok(ids)
}

impl Batch {
    /// Scenes `range` of this batch, with exactly their sampled rays (data-parallel
    /// workers' shares of one global batch).
    pub fn slice(&self, range: std::ops::Range<usize>) -> Batch {
        assert!(range.end <= self.batch_size && range.start <= range.end);
        let img = self.input_views * self.height * self.width * 3;
        let tgt = self.rays_per_scene * 3;
        let k = self.rays_per_scene;
        let cut = |v: &Vec<f32>, per: usize| v[range.start * per..range.end * per].to_vec();
        Batch {
            scene_ids: self.scene_ids[range.clone()].to_vec(),
            batch_size: range.len(),
            input_views: self.input_views,
            height: self.height,
            width: self.width,
            input_images: cut(&self.input_images, img),
            input_origins: cut(&self.input_origins, img),
            input_directions: cut(&self.input_directions, img),
            rays_per_scene: k,
            target_origins: cut(&self.target_origins, tgt),
            target_directions: cut(&self.target_directions, tgt),
            target_rgb: cut(&self.target_rgb, tgt),
            target_masks: self
                .target_masks
                .as_ref()
                .map(|m| m[range.start * k..range.end * k].to_vec()),
            target_pixels: self.target_pixels[range.start * k..range.end * k].to_vec(),
        }
    }
}

impl Batch {
    /// Appends the input views `inputs` of `scene` (cameras in the batch's frame), every
    /// `stride`-th pixel of each with its ray; every view must be `w0 × h0`.
    fn push_inputs(
        &mut self,
        scene: &Scene,
        inputs: &[usize],
        cameras: &[Camera],
        stride: usize,
        (w0, h0): (usize, usize),
    ) -> Result<()> {
        for &vi in inputs {
            let view = &scene.views[vi];
            if (view.width as usize, view.height as usize) != (w0, h0) {
                return Err(DatasetError::Batch(format!(
                    "scene {} view {vi} is {}x{}, the batch's input views are {w0}x{h0} (no padding)",
                    scene.id, view.width, view.height
                )));
            }
            let rays = view_rays_strided(&cameras[vi], view.width, view.height, stride);
            self.input_origins.extend(rays.origins);
            self.input_directions.extend(rays.directions);
            for y in (stride / 2..h0).step_by(stride) {
                for x in (stride / 2..w0).step_by(stride) {
                    let p = 3 * (y * w0 + x);
                    let rgb = &view.image[p..p + 3];
                    self.input_images
                        .extend(rgb.iter().map(|&c| c as f32 / 255.0));
                }
            }
        }
        Ok(())
    }

    /// Appends the target ray through pixel `rest` (row-major) of view `vi` of `scene`
    /// (`camera`: that view's camera in the batch's frame), with its colour, its mask
    /// label where the batch has masks, and where it came from.
    fn push_target(
        &mut self,
        scene: &Scene,
        vi: usize,
        camera: &Camera,
        rest: usize,
    ) -> Result<()> {
        let view = &scene.views[vi];
        let (u, row) = (
            (rest % view.width as usize) as u32,
            (rest / view.width as usize) as u32,
        );
        let (o, d) = pixel_ray(camera, u, row);
        self.target_origins.extend_from_slice(&o);
        self.target_directions.extend_from_slice(&d);
        self.target_rgb.extend(
            view.image[3 * rest..3 * rest + 3]
                .iter()
                .map(|&c| c as f32 / 255.0),
        );
        if let Some(m) = self.target_masks.as_mut() {
            let mask = view.mask.as_ref().ok_or_else(|| {
                DatasetError::Batch(format!(
                    "scene {} view {vi} has no mask: read the split with masks for evaluation",
                    scene.id
                ))
            })?;
            m.push(mask[rest]);
        }
        self.target_pixels.push((vi as u32, rest as u32));
        Ok(())
    }
}

/// Builds one batch. The RNG draws input views (when random) then target rays, scene by
/// scene in order, so the same RNG state and scenes give the same batch.
pub fn build_batch(scenes: &[&Scene], cfg: &BatchConfig, rng: &mut impl Rng) -> Result<Batch> {
    build_batch_each(scenes, cfg, std::slice::from_mut(rng))
}

/// [`build_batch`] with one RNG per scene: `rngs[i]` draws scene `i`'s input views and
/// target rays, so a scene's draws do not depend on the scenes beside it (a single RNG
/// draws for every scene, as [`build_batch`]).
pub fn build_batch_each<R: Rng>(
    scenes: &[&Scene],
    cfg: &BatchConfig,
    rngs: &mut [R],
) -> Result<Batch> {
    let first = scenes
        .first()
        .ok_or_else(|| DatasetError::Batch("a batch needs at least one scene".into()))?;
    if rngs.len() != 1 && rngs.len() != scenes.len() {
        return Err(DatasetError::Batch(format!(
            "{} random streams for {} scenes: one, or one per scene",
            rngs.len(),
            scenes.len()
        )));
    }
    let (w0, h0) = (
        first.views[0].width as usize,
        first.views[0].height as usize,
    );
    let stride = cfg.input_stride;
    if stride == 0 || stride > w0.min(h0) {
        return Err(DatasetError::Batch(format!(
            "input stride {stride}: must be 1 or more and at most the views' {w0}x{h0}"
        )));
    }
    let (wi, hi) = (strided_len(w0, stride), strided_len(h0, stride));
    let b = scenes.len();
    let v = cfg.input_views;
    let mut batch = Batch {
        scene_ids: Vec::with_capacity(b),
        batch_size: b,
        input_views: v,
        height: hi,
        width: wi,
        input_images: Vec::with_capacity(b * v * hi * wi * 3),
        input_origins: Vec::with_capacity(b * v * hi * wi * 3),
        input_directions: Vec::with_capacity(b * v * hi * wi * 3),
        rays_per_scene: 0,
        target_origins: Vec::new(),
        target_directions: Vec::new(),
        target_rgb: Vec::new(),
        target_masks: cfg.with_masks.then(Vec::new),
        target_pixels: Vec::new(),
    };
    for (si, scene) in scenes.iter().enumerate() {
        let rng = &mut rngs[si.min(rngs.len() - 1)];
        let inputs = choose_inputs(scene, cfg, rng)?;
        let reference = scene.views[inputs[0]].camera;
        // Each view's camera in the batch's frame, once per scene (not once per ray).
        let cameras: Vec<Camera> = scene
            .views
            .iter()
            .map(|v| cfg.ray_frame.express(&v.camera, &reference))
            .collect();
        batch.push_inputs(scene, &inputs, &cameras, stride, (w0, h0))?;

        let targets = target_view_ids(scene, &inputs, cfg.target_views)?;
        // Pixel index space over the target views, view after view.
        let sizes: Vec<usize> = targets
            .iter()
            .map(|&t| scene.views[t].num_pixels())
            .collect();
        let total: usize = sizes.iter().sum();
        let picks: Vec<usize> = match cfg.rays_per_scene {
            None => (0..total).collect(),
            Some(k) if k <= total => {
                sample_pixels(scene, &targets, total, k, cfg.salient_fraction, rng)
            }
            Some(k) => {
                return Err(DatasetError::Batch(format!(
                    "scene {}: {k} target rays requested, its target views have {total} pixels",
                    scene.id
                )));
            }
        };
        if si == 0 {
            batch.rays_per_scene = picks.len();
        } else if picks.len() != batch.rays_per_scene {
            return Err(DatasetError::Batch(format!(
                "scene {} has {} target rays, scene {} has {} (no padding: use rays_per_scene)",
                scene.id,
                picks.len(),
                first.id,
                batch.rays_per_scene
            )));
        }
        for p in picks {
            // Locate the pixel: which target view, which pixel inside it.
            let (mut t, mut rest) = (0, p);
            while rest >= sizes[t] {
                rest -= sizes[t];
                t += 1;
            }
            batch.push_target(scene, targets[t], &cameras[targets[t]], rest)?;
        }
        batch.scene_ids.push(scene.id);
    }
    Ok(batch)
}
