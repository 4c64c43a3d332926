//! Predictions as arrays (`osrt predict`): for each scene the exact inputs the model was
//! given and what it made of them, float32, channels last, for NumPy.
//!
//! | name | shape | |
//! |---|---|---|
//! | `input_images` | `[S, V, H, W, 3]` | RGB in `[0, 1]` |
//! | `input_origins`, `input_directions` | `[S, V, H, W, 3]` | every input pixel's ray, unit directions |
//! | `target_origins`, `target_directions` | `[S, …, 3]` | target rays (`…`: `T, H, W` for a dataset's target views, `R` for given rays) |
//! | `rgb` | `[S, …, 3]` | predicted colour |
//! | `slot_weights` | `[S, …, K]` | per-ray weights over slots (sum 1); absent for the transformer decoder |
//! | `slots` | `[S, K, D]` | the slot latents |
//! | `target_rgb` | `[S, …, 3]` | ground truth, where known |
//! | `target_masks` | `[S, …]` | ground-truth instance ids (0 = background), where known |
//! | `scene_ids` | `[S]` | dataset scenes only |
//!
//! Rays are in the frame the model takes them in: the world for posed models, the first
//! input camera's for unposed ones.

use crate::error::{Result, TrainError};
use crate::render::decode_rays;
use candle_core::Tensor;
use osrt_dataset::import::npy::{Values, read_npz};
use osrt_dataset::{BatchConfig, InputSelection, Scene, TargetViews, build_batch};
use osrt_interop::npz::NamedArray;
use osrt_model::Osrt;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// The model's inputs for `S` scenes.
#[derive(Debug, Clone)]
pub struct PredictInputs {
    /// `[S, V, H, W]`
    pub views: [usize; 4],
    /// `[S, V, H, W, 3]` each.
    pub images: Vec<f32>,
    pub origins: Vec<f32>,
    pub directions: Vec<f32>,
    /// Target rays per scene, as a shape (`[R]` or `[T, H, W]`).
    pub target_shape: Vec<usize>,
    /// `[S, …, 3]` each.
    pub target_origins: Vec<f32>,
    pub target_directions: Vec<f32>,
    pub target_rgb: Option<Vec<f32>>,
    /// `[S, …]`
    pub target_masks: Option<Vec<f32>>,
    pub scene_ids: Option<Vec<f32>>,
}

impl PredictInputs {
    fn rays_per_scene(&self) -> usize {
        self.target_shape.iter().product()
    }

    /// Scene `s` as a one-scene batch: images, origins, directions `[1, V, H, W, 3]`,
    /// target origins and directions `[1, R, 3]`.
    fn scene(&self, s: usize, dev: &candle_core::Device) -> Result<[Tensor; 5]> {
        let [_, v, h, w] = self.views;
        let n = v * h * w * 3;
        let r = self.rays_per_scene();
        let view = |x: &[f32]| Tensor::from_slice(&x[s * n..(s + 1) * n], (1, v, h, w, 3), dev);
        let ray = |x: &[f32]| Tensor::from_slice(&x[s * r * 3..(s + 1) * r * 3], (1, r, 3), dev);
        Ok([
            view(&self.images)?,
            view(&self.origins)?,
            view(&self.directions)?,
            ray(&self.target_origins)?,
            ray(&self.target_directions)?,
        ])
    }
}

/// Inputs given as arrays (the names and shapes of the table above; `target_rgb`
/// optional), e.g. written by another implementation to compare outputs with.
pub fn inputs_from_npz(path: &std::path::Path) -> Result<PredictInputs> {
    let shown = path.display().to_string();
    let file = std::fs::File::open(path).map_err(|e| TrainError::io(&shown, e))?;
    let names = [
        "input_images",
        "input_origins",
        "input_directions",
        "target_origins",
        "target_directions",
        "target_rgb",
    ];
    let bad = |reason: String| TrainError::Config {
        path: shown.clone(),
        reason,
    };
    let mut arrays = std::collections::BTreeMap::new();
    for (name, a) in read_npz(std::io::BufReader::new(file), &shown, &names)? {
        let Values::Numbers(v) = a.values else {
            return Err(bad(format!("`{name}` holds text, not numbers")));
        };
        arrays.insert(
            name,
            (a.shape, v.into_iter().map(|x| x as f32).collect::<Vec<_>>()),
        );
    }
    let take = |name: &str, want: Option<&[usize]>| -> Result<Option<(Vec<usize>, Vec<f32>)>> {
        match arrays.get(name) {
            Some((got, _)) if want.is_some_and(|w| w != got.as_slice()) => Err(bad(format!(
                "`{name}` is {got:?}, expected {:?}",
                want.expect("checked")
            ))),
            other => Ok(other.cloned()),
        }
    };
    let need = |name: &str, want: Option<&[usize]>| {
        take(name, want)?.ok_or_else(|| bad(format!("no array `{name}`")))
    };
    let (shape, images) = need("input_images", None)?;
    let [s, v, h, w, 3] = shape[..] else {
        return Err(bad(format!(
            "`input_images` is {shape:?}, expected [S, V, H, W, 3]"
        )));
    };
    let (_, origins) = need("input_origins", Some(&shape))?;
    let (_, directions) = need("input_directions", Some(&shape))?;
    let (tshape, target_origins) = need("target_origins", None)?;
    if tshape.len() < 3 || tshape[0] != s || tshape.last() != Some(&3) {
        return Err(bad(format!(
            "`target_origins` is {tshape:?}, expected [{s}, …, 3]"
        )));
    }
    let (_, target_directions) = need("target_directions", Some(&tshape))?;
    let target_rgb = take("target_rgb", Some(&tshape))?.map(|(_, x)| x);
    Ok(PredictInputs {
        views: [s, v, h, w],
        images,
        origins,
        directions,
        target_shape: tshape[1..tshape.len() - 1].to_vec(),
        target_origins,
        target_directions,
        target_rgb,
        target_masks: None,
        scene_ids: None,
    })
}

/// Inputs of dataset scenes under the evaluation protocol: the first `input_views` views
/// in, every pixel of the `target_views` out (all scenes need the same view count and
/// image size, to stack).
pub fn inputs_from_scenes(
    model: &Osrt,
    scenes: &[Scene],
    input_views: usize,
    input_stride: usize,
    target_views: TargetViews,
) -> Result<PredictInputs> {
    let masks = scenes
        .iter()
        .all(|s| s.views.iter().all(|v| v.mask.is_some()));
    let cfg = BatchConfig {
        input_views,
        input_selection: InputSelection::First,
        target_views,
        rays_per_scene: None,
        with_masks: masks,
        salient_fraction: 0.0,
        ray_frame: crate::config::ray_frame(&model.cfg),
        input_stride,
    };
    // Nothing is drawn with the first inputs and every target pixel; the RNG is a formality.
    let scenes: Vec<&Scene> = scenes.iter().collect();
    let batch = build_batch(&scenes, &cfg, &mut ChaCha8Rng::seed_from_u64(0))?;
    // Targets keep every pixel of the views (inputs may be strided).
    let view = &scenes[0].views[0];
    let (th, tw) = (view.height as usize, view.width as usize);
    let targets = batch.rays_per_scene / (th * tw).max(1);
    let one = |x: Vec<u8>| x.into_iter().map(f32::from).collect();
    Ok(PredictInputs {
        views: [
            batch.batch_size,
            batch.input_views,
            batch.height,
            batch.width,
        ],
        images: batch.input_images,
        origins: batch.input_origins,
        directions: batch.input_directions,
        target_shape: vec![targets, th, tw],
        target_origins: batch.target_origins,
        target_directions: batch.target_directions,
        target_rgb: Some(batch.target_rgb),
        target_masks: batch.target_masks.map(one),
        scene_ids: Some(batch.scene_ids.iter().map(|&i| i as f32).collect()),
    })
}

/// Runs `model` on every scene of `inputs`, one scene at a time (the decoder in chunks of
/// rays); returns the table's arrays. `seed` draws the slot noise of random slot init;
/// `done` is called after each scene with the count so far (a progress bar).
pub fn predict(
    model: &Osrt,
    inputs: &PredictInputs,
    seed: u64,
    done: &dyn Fn(usize),
) -> Result<Vec<NamedArray>> {
    let [s, v, h, w] = inputs.views;
    let k = model.cfg.slot_attention.num_slots;
    let d = model.cfg.slot_attention.slot_dim;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (mut rgb, mut weights, mut slots) = (Vec::new(), Some(Vec::new()), Vec::new());
    for i in 0..s {
        let [images, origins, directions, t_origins, t_directions] =
            inputs.scene(i, model.device())?;
        let noise = model.slot_noise(1, &mut rng)?;
        let z = osrt_kernels::on_device_pool(model.device(), || {
            model.encode(&images, &origins, &directions, noise.as_ref())
        })?
        .slots;
        slots.extend(z.flatten_all()?.to_vec1::<f32>()?);
        let out = decode_rays(model, &z, &t_origins, &t_directions)?;
        rgb.extend(out.rgb);
        weights = weights.zip(out.weights).map(|(mut all, w)| {
            all.extend(w);
            all
        });
        done(i + 1);
    }
    let rays = |last: usize| -> Vec<usize> {
        let mut shape = vec![s];
        shape.extend(&inputs.target_shape);
        shape.push(last);
        shape
    };
    let views = vec![s, v, h, w, 3];
    let mut out = vec![
        NamedArray::new("input_images", views.clone(), inputs.images.clone()),
        NamedArray::new("input_origins", views.clone(), inputs.origins.clone()),
        NamedArray::new("input_directions", views, inputs.directions.clone()),
        NamedArray::new("target_origins", rays(3), inputs.target_origins.clone()),
        NamedArray::new(
            "target_directions",
            rays(3),
            inputs.target_directions.clone(),
        ),
        NamedArray::new("rgb", rays(3), rgb),
        NamedArray::new("slots", vec![s, k, d], slots),
    ];
    if let Some(w) = weights {
        out.push(NamedArray::new("slot_weights", rays(k), w));
    }
    if let Some(x) = &inputs.target_rgb {
        out.push(NamedArray::new("target_rgb", rays(3), x.clone()));
    }
    if let Some(x) = &inputs.target_masks {
        let mut shape = rays(0);
        shape.pop();
        out.push(NamedArray::new("target_masks", shape, x.clone()));
    }
    if let Some(x) = &inputs.scene_ids {
        out.push(NamedArray::new("scene_ids", vec![s], x.clone()));
    }
    debug_assert!(
        out.iter()
            .all(|a| a.values.len() == a.shape.iter().product::<usize>())
    );
    Ok(out)
}
