//! Rendering whole images from a trained model: a scene's slots, decoded for every pixel of
//! any camera (novel views along a path, or the dataset's own cameras), with the per-pixel
//! slot assignment, and scene editing on the slot set (paper Fig. 6).

use crate::error::{Result, TrainError};
use candle_core::{D, Tensor};
use osrt_dataset::math::Vec3;
use osrt_dataset::rays::view_rays;
use osrt_dataset::{BatchConfig, Camera, InputSelection, Scene, TargetViews, build_batch};
use osrt_model::Osrt;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Rays decoded per forward pass (bounds memory on large images).
pub const CHUNK: usize = 4096;

/// Colours and slot assignment of a set of rays.
#[derive(Debug, Clone, PartialEq)]
pub struct Decoded {
    /// `[r * 3]`, as the decoder outputs them (nominally in `[0, 1]`).
    pub rgb: Vec<f32>,
    /// Argmax of the slot weights per ray, `None` for decoders without slot weights.
    pub labels: Option<Vec<u32>>,
    /// Slot weights `[r * k]`, `None` for decoders without them.
    pub weights: Option<Vec<f32>>,
}

/// Decodes rays in chunks of [`CHUNK`].
///
/// # Shapes
/// `slots: [1, k, d]`, `origins`, `directions: [1, r, 3]`
pub fn decode_rays(
    model: &Osrt,
    slots: &Tensor,
    origins: &Tensor,
    directions: &Tensor,
) -> Result<Decoded> {
    // On candle's pool, with the fused ops: since the step moved there and candle's
    // elementwise pool lost its spinning workers, they render faster than candle's
    // composed ops too (docs/performance.md).
    osrt_kernels::on_device_pool(model.device(), || {
        decode_here(model, slots, origins, directions)
    })
}

fn decode_here(
    model: &Osrt,
    slots: &Tensor,
    origins: &Tensor,
    directions: &Tensor,
) -> Result<Decoded> {
    let r = origins.dim(1)?;
    let mut rgb = Vec::with_capacity(r * 3);
    let mut labels: Option<Vec<u32>> = Some(Vec::with_capacity(r));
    let mut weights: Option<Vec<f32>> = Some(Vec::new());
    let mut off = 0;
    while off < r {
        let len = CHUNK.min(r - off);
        let out = model.decode(
            slots,
            &origins.narrow(1, off, len)?,
            &directions.narrow(1, off, len)?,
        )?;
        rgb.extend(out.rgb.flatten_all()?.to_vec1::<f32>()?);
        match (&out.weights, labels.as_mut(), weights.as_mut()) {
            (Some(w), Some(l), Some(ws)) => {
                l.extend(w.argmax(D::Minus1)?.flatten_all()?.to_vec1::<u32>()?);
                ws.extend(w.flatten_all()?.to_vec1::<f32>()?);
            }
            _ => {
                labels = None;
                weights = None;
            }
        }
        off += len;
    }
    Ok(Decoded {
        rgb,
        labels,
        weights,
    })
}

/// The slots of one scene from its first `input_views` views (slot noise, for random init,
/// from `seed`).
///
/// # Shapes
/// → `[1, k, d]`
pub fn encode_scene(
    model: &Osrt,
    scene: &Scene,
    input_views: usize,
    input_stride: usize,
    seed: u64,
) -> Result<Tensor> {
    if scene.views.len() < input_views {
        return Err(TrainError::Config {
            path: format!("scene {}", scene.id),
            reason: format!(
                "has {} views, the model takes {input_views} input views",
                scene.views.len()
            ),
        });
    }
    let cfg = BatchConfig {
        input_views,
        input_selection: InputSelection::First,
        target_views: TargetViews::All,
        rays_per_scene: Some(1),
        with_masks: false,
        salient_fraction: 0.0,
        ray_frame: crate::config::ray_frame(&model.cfg),
        input_stride,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let batch = build_batch(&[scene], &cfg, &mut rng)?;
    let img = (1, input_views, batch.height, batch.width, 3);
    let dev = model.device();
    let images = Tensor::from_slice(&batch.input_images, img, dev)?;
    let origins = Tensor::from_slice(&batch.input_origins, img, dev)?;
    let directions = Tensor::from_slice(&batch.input_directions, img, dev)?;
    let noise = model.slot_noise(1, &mut rng)?;
    let out = osrt_kernels::on_device_pool(dev, || {
        model.encode(&images, &origins, &directions, noise.as_ref())
    })?;
    Ok(out.slots)
}

/// `camera` in the frame `model` takes its rays in, for a scene encoded by
/// [`encode_scene`]: itself for posed models, relative to the scene's first view for
/// Up-OSRT (whose slots know the scene only as seen from that camera).
pub fn scene_camera(model: &Osrt, scene: &Scene, camera: &Camera) -> Camera {
    crate::config::ray_frame(&model.cfg).express(camera, &scene.views[0].camera)
}

/// One rendered image.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub decoded: Decoded,
}

/// Every pixel of `camera` at `width × height`, decoded from `slots: [1, k, d]`; the
/// camera is in the model's frame ([`scene_camera`]).
pub fn render_view(
    model: &Osrt,
    slots: &Tensor,
    camera: &Camera,
    width: u32,
    height: u32,
) -> Result<Frame> {
    let rays = view_rays(camera, width, height);
    let n = width as usize * height as usize;
    let dev = model.device();
    let origins = Tensor::from_vec(rays.origins, (1, n, 3), dev)?;
    let directions = Tensor::from_vec(rays.directions, (1, n, 3), dev)?;
    Ok(Frame {
        width,
        height,
        decoded: decode_rays(model, slots, &origins, &directions)?,
    })
}

/// `frames` cameras on a circle about the vertical axis through the point `start` looks
/// at (where its optical axis meets the floor `z = 0`, or the origin if it never does), at
/// `start`'s height and distance, beginning at `start` itself.
pub fn orbit(start: &Camera, frames: usize) -> Result<Vec<Camera>> {
    let p = start.position();
    let fwd = start.axis(2);
    let target = if fwd.z < -1e-6 {
        let t = -p.z / fwd.z;
        Vec3::new(p.x + t * fwd.x, p.y + t * fwd.y, 0.0)
    } else {
        Vec3::new(0.0, 0.0, 0.0)
    };
    let (dx, dy) = (p.x - target.x, p.y - target.y);
    let radius = (dx * dx + dy * dy).sqrt();
    let phase = dy.atan2(dx);
    (0..frames)
        .map(|i| {
            let a = phase + std::f64::consts::TAU * i as f64 / frames as f64;
            let pos = Vec3::new(
                target.x + radius * a.cos(),
                target.y + radius * a.sin(),
                p.z,
            );
            Camera::look_at(pos, target, start.intrinsics).map_err(|reason| TrainError::Config {
                path: "orbit".into(),
                reason,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::JobConfig;
    use crate::step::Trainer;
    use candle_core::Device;
    use osrt_dataset::generator::{GeneratorConfig, generate_scene};
    use osrt_model::drop_slot;

    fn trainer(decoder: &str) -> Trainer {
        let mut job = JobConfig::preset("tiny").unwrap();
        job.model = job.model.with_decoder(decoder).unwrap();
        Trainer::new(job, Device::Cpu).unwrap()
    }

    fn scene() -> Scene {
        let cfg = GeneratorConfig {
            image_size: 16,
            ..GeneratorConfig::clevr_lite()
        };
        generate_scene(&cfg, 3, "test", 0).unwrap()
    }

    #[test]
    fn orbit_starts_at_the_camera_and_keeps_height_and_distance() {
        let s = scene();
        let cam = s.views[0].camera;
        let path = orbit(&cam, 8).unwrap();
        assert_eq!(path.len(), 8);
        let d = |a: Vec3, b: Vec3| (a - b).norm();
        assert!(d(path[0].position(), cam.position()) < 1e-4);
        let r0 = d(path[0].position(), Vec3::new(0.0, 0.0, 0.0));
        for c in &path {
            assert!((c.position().z - cam.position().z).abs() < 1e-4);
            // Every camera looks at the same floor point: its axis passes through it.
            assert!(c.axis(2).z < 0.0);
            let _ = r0;
        }
        // Half way round the camera is on the opposite side of the orbit centre.
        let (a, b) = (path[0].position(), path[4].position());
        assert!(d(a, b) > 1.0, "the path moves: {a:?} vs {b:?}");
        assert!(orbit(&cam, 0).unwrap().is_empty());
    }

    #[test]
    fn a_dataset_camera_renders_as_many_pixels_as_the_view() {
        let t = trainer("slot_mixer");
        let s = scene();
        let slots = encode_scene(&t.model, &s, 1, 1, 0).unwrap();
        let v = &s.views[1];
        let f = render_view(&t.model, &slots, &v.camera, v.width, v.height).unwrap();
        assert_eq!(f.decoded.rgb.len(), v.num_pixels() * 3);
        let labels = f.decoded.labels.unwrap();
        assert_eq!(labels.len(), v.num_pixels());
        let k = t.cfg.model.slot_attention.num_slots as u32;
        assert!(labels.iter().all(|&l| l < k));
        assert!(f.decoded.rgb.iter().all(|x| x.is_finite()));
        // Too few views for the model's inputs: a clear error naming the scene.
        let err = encode_scene(&t.model, &s, 9, 1, 0).unwrap_err().to_string();
        assert!(
            err.contains("scene 0") && err.contains("9 input views"),
            "{err}"
        );
    }

    /// With a decoder that decides (near one-hot slot weights), dropping a slot changes the
    /// image where that slot was assigned and leaves the rest alone: the spatial broadcast
    /// decoder renormalises the remaining slots' weights per pixel, so the change at a pixel
    /// is bounded by the dropped slot's weight there.
    #[test]
    fn dropping_a_slot_changes_only_its_pixels() {
        let t = trainer("spatial_broadcast");
        // Sharpen the alpha logits (output 0 of the last decoder layer) and saturate the
        // colours (outputs 1..4), so slots decide pixels and differ in colour.
        for (name, var) in t.params.vars() {
            if name.starts_with("decoder.mlp.") && name.ends_with("weight") {
                let w = var.as_tensor();
                if w.dim(0).unwrap() == 4 {
                    let scale = Tensor::new(&[5000f32, 50.0, 50.0, 50.0], w.device())
                        .unwrap()
                        .unsqueeze(1)
                        .unwrap();
                    var.set(&w.broadcast_mul(&scale).unwrap()).unwrap();
                }
            }
        }
        let s = scene();
        let slots = encode_scene(&t.model, &s, 1, 1, 0).unwrap();
        let v = &s.views[0];
        let full = render_view(&t.model, &slots, &v.camera, v.width, v.height).unwrap();
        let labels = full.decoded.labels.clone().unwrap();
        let weights = full.decoded.weights.clone().unwrap();
        let mut counts = [0usize; 3];
        for &l in &labels {
            counts[l as usize] += 1;
        }
        let k = (0..3).max_by_key(|&i| counts[i]).unwrap();
        assert!(
            counts[k] < labels.len(),
            "one slot owns every pixel: {counts:?}"
        );
        let edited = drop_slot(&slots, k).unwrap();
        let e = render_view(&t.model, &edited, &v.camera, v.width, v.height).unwrap();
        let (mut inside, mut outside, mut n_in, mut n_out) = (0f64, 0f64, 0, 0);
        let mut worst_outside = 0f32;
        for (p, &l) in labels.iter().enumerate() {
            let d: f32 = (0..3)
                .map(|c| (full.decoded.rgb[3 * p + c] - e.decoded.rgb[3 * p + c]).abs())
                .sum();
            // Exact for this decoder: Δ = w_k · (new colour − slot k's colour), |·|₁ ≤ 3 w_k.
            let wk = weights[3 * p + k];
            assert!(
                d <= 3.0 * wk + 1e-4,
                "pixel {p}: changed by {d} with weight {wk}"
            );
            if l as usize == k {
                inside += d as f64;
                n_in += 1;
            } else {
                outside += d as f64;
                n_out += 1;
                worst_outside = worst_outside.max(d);
            }
        }
        let (inside, outside) = (inside / n_in as f64, outside / n_out as f64);
        // Outside the mask pixels stay close (the largest changes sit on the mask's border,
        // where the dropped slot still had some weight).
        assert!(
            outside < 0.01,
            "outside pixels changed by {outside} on average"
        );
        assert!(
            worst_outside < 0.1,
            "a pixel outside the slot changed by {worst_outside}"
        );
        assert!(
            inside > 10.0 * outside.max(1e-6),
            "inside {inside} outside {outside}"
        );
    }
}
