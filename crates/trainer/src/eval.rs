//! Evaluation: render whole target views of each scene, score PSNR (and a mean-colour
//! baseline), ARI / FG-ARI / 2D-FG-ARI from the argmax of the slot weights, and the
//! decoder's render speed.

use crate::error::Result;
use crate::render::{Decoded, decode_rays};
use crate::step::BatchTensors;
use osrt_dataset::{BatchConfig, InputSelection, Scene, TargetViews, build_batch};
use osrt_kernels::Kernels;
use osrt_model::Osrt;
use osrt_model::metrics::{Psnr, Segmentation};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::time::Instant;

/// Evaluation scores; segmentation scores are `None` for decoders without slot weights
/// (the transformer decoder) or data without masks.
#[derive(Debug, Clone, Serialize)]
pub struct EvalResult {
    pub scenes: usize,
    pub psnr: f64,
    /// PSNR of predicting each scene's mean input-view colour everywhere.
    pub baseline_psnr: f64,
    pub ari: Option<f64>,
    pub fg_ari: Option<f64>,
    pub fg_ari_2d: Option<f64>,
    pub ratio: Option<f64>,
    /// Target views rendered per second of decoding (slots → image).
    pub render_fps: f64,
    pub segmentation: bool,
    /// Slot-attention iterations the scenes were encoded with (the trained count unless
    /// `osrt eval --slot-iterations` changed it).
    pub slot_iterations: usize,
    /// FG-ARI per number of objects in the scene (ascending), where segmentation is scored.
    pub by_objects: Vec<ObjectCountScore>,
    /// The protocol the scores follow, in words: input views, targets, what FG-ARI pools.
    pub protocol: String,
    /// The first scene's first target view, for pictures.
    #[serde(skip)]
    pub sample: Option<EvalSample>,
}

/// One rendered target view beside its inputs, from the first validation scene.
#[derive(Debug, Clone)]
pub struct EvalSample {
    /// The scene's first input view (RGB8, its own size).
    pub input: osrt_dataset::View,
    /// The target view: its ground truth image and mask.
    pub target: osrt_dataset::View,
    /// The render of the target view: `[h * w * 3]` in `[0, 1]`, row-major.
    pub rgb: Vec<f32>,
    /// The slot each pixel was assigned (argmax of the slot weights), if the decoder has
    /// them.
    pub labels: Option<Vec<u32>>,
}

/// The evaluation protocol of `opts`, in words.
pub fn protocol(opts: &EvalOptions) -> String {
    let inputs = match opts.input_views {
        1 => "view 0".to_string(),
        k => format!("views 0..{}", k - 1),
    };
    let targets = match opts.target_views {
        TargetViews::NonInput => "every pixel of every other view",
        _ => "every pixel of every view, the input ones included",
    };
    format!(
        "input: {inputs}{}; targets: {targets}; PSNR per scene, averaged; FG-ARI over all \
         target pixels of a scene (background excluded), averaged over scenes",
        if opts.grayscale { " (grey)" } else { "" }
    )
}

/// Segmentation scores of the scenes with one object count.
#[derive(Debug, Clone, Serialize)]
pub struct ObjectCountScore {
    pub objects: usize,
    pub scenes: usize,
    pub fg_ari: Option<f64>,
    pub ari: Option<f64>,
}

pub struct EvalOptions {
    pub input_views: usize,
    /// Input views point-sampled every this many pixels (`train.input_stride`).
    pub input_stride: usize,
    pub target_views: TargetViews,
    /// Replace the input images by their grey level (robustness study).
    pub grayscale: bool,
    /// Seed of the slot noise for random slot init.
    pub seed: u64,
    /// The job's kernels (`train.kernels`).
    pub kernels: Kernels,
}

/// Scores `scenes`, on candle's thread pool (see `osrt_kernels::on_device_pool`).
pub fn evaluate(model: &Osrt, scenes: &[Scene], opts: &EvalOptions) -> Result<EvalResult> {
    osrt_kernels::with_kernels(opts.kernels, || {
        osrt_kernels::on_device_pool(model.device(), || evaluate_here(model, scenes, opts))
    })
}

fn evaluate_here(model: &Osrt, scenes: &[Scene], opts: &EvalOptions) -> Result<EvalResult> {
    let mut psnr = Psnr::default();
    let mut baseline = Psnr::default();
    let mut seg = Segmentation::default();
    let mut seg_by_objects: std::collections::BTreeMap<usize, (usize, Segmentation)> =
        Default::default();
    let mut has_weights = true;
    let mut decode_s = 0.0;
    let mut frames = 0usize;
    let mut sample = None;
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    let cfg = BatchConfig {
        input_views: opts.input_views,
        input_selection: InputSelection::First,
        target_views: opts.target_views,
        rays_per_scene: None,
        with_masks: scenes
            .iter()
            .all(|s| s.views.iter().all(|v| v.mask.is_some())),
        salient_fraction: 0.0,
        ray_frame: crate::config::ray_frame(&model.cfg),
        input_stride: opts.input_stride,
    };
    for scene in scenes {
        // Scenes with fewer views than needed for novel views fall back to all views.
        let cfg = if opts.target_views == TargetViews::NonInput
            && scene.views.len() <= opts.input_views
        {
            BatchConfig {
                target_views: TargetViews::All,
                ..cfg
            }
        } else {
            cfg
        };
        let mut batch = build_batch(&[scene], &cfg, &mut rng)?;
        if opts.grayscale {
            for px in batch.input_images.chunks_mut(3) {
                let g = 0.299 * px[0] + 0.587 * px[1] + 0.114 * px[2];
                px.fill(g);
            }
        }
        let t = BatchTensors::new(&batch, model.device())?;
        let noise = model.slot_noise(1, &mut rng)?;
        let slots = model
            .encode(&t.images, &t.origins, &t.directions, noise.as_ref())?
            .slots;
        let r = batch.rays_per_scene;
        let start = Instant::now();
        let Decoded { rgb, labels, .. } =
            decode_rays(model, &slots, &t.target_origins, &t.target_directions)?;
        decode_s += start.elapsed().as_secs_f64();
        if sample.is_none() {
            sample = first_view_sample(scene, &batch.target_pixels[..r], &rgb, labels.as_deref());
        }
        let n_views: std::collections::BTreeSet<u32> =
            batch.target_pixels.iter().map(|p| p.0).collect();
        frames += n_views.len();
        psnr.update(&rgb, &batch.target_rgb);

        baseline.update(&mean_colour(&batch.input_images, r), &batch.target_rgb);
        match (labels, &batch.target_masks) {
            (Some(labels), Some(masks)) => {
                let views = by_view(&batch.target_pixels[..r], masks, &labels);
                seg.update(&views);
                if let Some(n) = scene.num_objects() {
                    let (count, s) = seg_by_objects.entry(n).or_default();
                    *count += 1;
                    s.update(&views);
                }
            }
            // No slot weights (transformer decoder) or no masks: no segmentation scores.
            _ => has_weights = false,
        }
    }
    let scores = seg.compute();
    let segmentation = has_weights && !scenes.is_empty();
    Ok(EvalResult {
        scenes: scenes.len(),
        psnr: psnr.compute().unwrap_or(f64::NAN),
        baseline_psnr: baseline.compute().unwrap_or(f64::NAN),
        ari: scores.ari.filter(|_| segmentation),
        fg_ari: scores.fg_ari.filter(|_| segmentation),
        fg_ari_2d: scores.fg_ari_2d.filter(|_| segmentation),
        ratio: scores.ratio.filter(|_| segmentation),
        render_fps: per_second(frames, decode_s),
        segmentation,
        slot_iterations: model.cfg.slot_attention.iterations,
        protocol: protocol(opts),
        sample,
        by_objects: if segmentation {
            by_object_count(seg_by_objects)
        } else {
            Vec::new()
        },
    })
}

/// `n` per second of `s` seconds; 0 where nothing was timed.
fn per_second(n: usize, s: f64) -> f64 {
    if s > 0.0 { n as f64 / s } else { 0.0 }
}

/// Segmentation scores per object count, from each count's scenes and their pooled
/// segmentation.
fn by_object_count(
    seg: std::collections::BTreeMap<usize, (usize, Segmentation)>,
) -> Vec<ObjectCountScore> {
    seg.into_iter()
        .map(|(objects, (scenes, s))| {
            let c = s.compute();
            ObjectCountScore {
                objects,
                scenes,
                fg_ari: c.fg_ari,
                ari: c.ari,
            }
        })
        .collect()
}

/// The first target view of a whole-view batch of `scene` as a sample (its rays are the
/// batch's first ones; `pixels`: each ray's view and pixel index).
fn first_view_sample(
    scene: &Scene,
    pixels: &[(u32, u32)],
    rgb: &[f32],
    labels: Option<&[u32]>,
) -> Option<EvalSample> {
    let v = pixels.first()?.0;
    let target = scene.views.get(v as usize)?;
    let n = target.num_pixels();
    let rays = pixels.iter().take_while(|p| p.0 == v).count();
    if rays != n || rgb.len() < 3 * n {
        return None;
    }
    // Placed by pixel index: the picture does not rely on the batch's ray order.
    let mut image = vec![0f32; 3 * n];
    let mut slots = labels.map(|_| vec![0u32; n]);
    for (i, &(_, p)) in pixels[..n].iter().enumerate() {
        let p = p as usize;
        image[3 * p..3 * p + 3].copy_from_slice(&rgb[3 * i..3 * i + 3]);
        if let (Some(s), Some(l)) = (slots.as_mut(), labels) {
            s[p] = l[i];
        }
    }
    Some(EvalSample {
        input: scene.views[0].clone(),
        target: target.clone(),
        rgb: image,
        labels: slots,
    })
}

/// The baseline's prediction for `rays` rays: the mean colour of the input views.
fn mean_colour(input_images: &[f32], rays: usize) -> Vec<f32> {
    let mut mean = [0f64; 3];
    for px in input_images.chunks(3) {
        for c in 0..3 {
            mean[c] += px[c] as f64;
        }
    }
    let npx = (input_images.len() / 3) as f64;
    (0..rays * 3).map(|i| (mean[i % 3] / npx) as f32).collect()
}

/// Masks and slot labels of a whole-view batch, grouped by view (in a whole-view batch a
/// view's rays are contiguous). `pixels`: each ray's view first.
fn by_view<'a>(
    pixels: &[(u32, u32)],
    masks: &'a [u8],
    labels: &'a [u32],
) -> Vec<(&'a [u8], &'a [u32])> {
    let mut views = Vec::new();
    let mut s = 0;
    while s < pixels.len() {
        let v = pixels[s].0;
        let e = s + pixels[s..].iter().take_while(|p| p.0 == v).count();
        views.push((&masks[s..e], &labels[s..e]));
        s = e;
    }
    views
}
