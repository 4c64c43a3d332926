//! A batch's host buffers as tensors on the model's device, the whole batch or a
//! micro-batch's scenes: what the step, evaluation and the benchmarks feed the model. Its
//! own file because it knows the batch's layout and nothing of the step.

use crate::error::Result;
use candle_core::{Device, Tensor};
use osrt_dataset::Batch;

/// Tensors of a batch.
pub struct BatchTensors {
    pub images: Tensor,
    pub origins: Tensor,
    pub directions: Tensor,
    pub target_origins: Tensor,
    pub target_directions: Tensor,
    pub target_rgb: Tensor,
}

impl BatchTensors {
    pub fn new(b: &Batch, dev: &Device) -> Result<Self> {
        Self::scenes(b, 0..b.batch_size, dev)
    }

    /// The tensors of the batch's scenes `scenes` only (a micro-batch: nothing of the
    /// other scenes reaches the device).
    pub fn scenes(b: &Batch, scenes: std::ops::Range<usize>, dev: &Device) -> Result<Self> {
        let n = scenes.len();
        let per_image = b.input_views * b.height * b.width * 3;
        let per_target = b.rays_per_scene * 3;
        let img = (n, b.input_views, b.height, b.width, 3);
        let tgt = (n, b.rays_per_scene, 3);
        let image = |v: &[f32]| {
            Tensor::from_slice(
                &v[scenes.start * per_image..scenes.end * per_image],
                img,
                dev,
            )
        };
        let target = |v: &[f32]| {
            Tensor::from_slice(
                &v[scenes.start * per_target..scenes.end * per_target],
                tgt,
                dev,
            )
        };
        Ok(Self {
            images: image(&b.input_images)?,
            origins: image(&b.input_origins)?,
            directions: image(&b.input_directions)?,
            target_origins: target(&b.target_origins)?,
            target_directions: target(&b.target_directions)?,
            target_rgb: target(&b.target_rgb)?,
        })
    }
}
