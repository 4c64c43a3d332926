//! The spatial-broadcast decoder (paper eqs. 7–8, as in ObSuRF/uORF-style models): the
//! render MLP runs once per (ray, slot) on raw ray encoding ⊕ slot and returns a colour and
//! a logit per slot; a softmax over slots gives the weights and the colour is their
//! weighted sum. Its cost grows linearly with the slot count — kept as the baseline.

use crate::decoder::DecoderOutput;
use crate::nn::{Activation, Mlp};
use candle_core::{D, Module, Result, Tensor};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Config {
    pub hidden: Vec<usize>,
}

impl Config {
    pub fn paper() -> Self {
        Self {
            hidden: vec![1536; 4],
        }
    }
}

#[derive(Debug, Clone)]
pub struct SpatialBroadcast {
    mlp: Mlp,
}

impl SpatialBroadcast {
    pub fn new(cfg: &Config, ray_dim: usize, slot_dim: usize, vb: VarBuilder) -> Result<Self> {
        let mut dims = vec![ray_dim + slot_dim];
        dims.extend(&cfg.hidden);
        dims.push(4);
        Ok(Self {
            mlp: Mlp::new(&dims, Activation::LeakyRelu, true, vb.pp("mlp"))?,
        })
    }

    /// # Shapes
    /// `slots: [b, k, ds]`, `rays: [b, r, ray_dim]` → rgb `[b, r, 3]`, weights `[b, r, k]`
    pub fn forward(&self, slots: &Tensor, rays: &Tensor) -> Result<DecoderOutput> {
        let (b, k, ds) = slots.dims3()?;
        let (_, r, e) = rays.dims3()?;
        // The (ray, slot) rows and the MLP over them: a segment whose activations a train
        // step may make again in its backward pass (`osrt_kernels::recompute`).
        let mlp = self.mlp.clone();
        let out = osrt_kernels::recompute(&[rays, slots], move |t| {
            let rays = t[0].unsqueeze(2)?.broadcast_as((b, r, k, e))?;
            let slots = t[1].unsqueeze(1)?.broadcast_as((b, r, k, ds))?;
            // One flat matrix of (ray, slot) rows: [b·r·k, e + ds].
            let x = Tensor::cat(&[&rays, &slots], D::Minus1)?.reshape((b * r * k, e + ds))?;
            mlp.forward(&x)?.reshape((b, r, k, 4))
        })?;
        let logits = out.narrow(D::Minus1, 0, 1)?.squeeze(D::Minus1)?; // [b, r, k]
        let colours = candle_nn::ops::sigmoid(&out.narrow(D::Minus1, 1, 3)?)?; // [b, r, k, 3]
        let weights = osrt_kernels::softmax(&logits, D::Minus1)?;
        let rgb = colours
            .broadcast_mul(&weights.unsqueeze(D::Minus1)?)?
            .sum(2)?; // [b, r, 3]
        Ok(DecoderOutput {
            rgb,
            weights: Some(weights),
        })
    }
}
