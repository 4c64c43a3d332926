//! The SRT decoder (paper eq. 3): ray queries cross-attend into the slots through a few
//! transformer layers and an MLP maps the result straight to RGB. It mixes slots inside
//! attention, so it has no per-slot weights and yields no segmentation.

use crate::decoder::DecoderOutput;
use crate::nn::{Activation, Mlp, Transformer, TransformerConfig};
use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Config {
    pub query_hidden: usize,
    pub transformer: TransformerConfig,
    pub render_hidden: Vec<usize>,
}

impl Config {
    pub fn paper() -> Self {
        Self {
            query_hidden: 360,
            transformer: TransformerConfig {
                layers: 2,
                heads: 12,
                head_dim: 128,
                mlp_hidden: 3072,
            },
            render_hidden: vec![1536; 4],
        }
    }
}

#[derive(Debug, Clone)]
pub struct TransformerDecoder {
    query_mlp: Mlp,
    transformer: Transformer,
    render: Mlp,
}

impl TransformerDecoder {
    pub fn new(cfg: &Config, ray_dim: usize, slot_dim: usize, vb: VarBuilder) -> Result<Self> {
        let mut dims = vec![ray_dim];
        dims.extend(&cfg.render_hidden);
        dims.push(3);
        Ok(Self {
            query_mlp: Mlp::new(
                &[ray_dim, cfg.query_hidden, ray_dim],
                Activation::Relu,
                true,
                vb.pp("query_mlp"),
            )?,
            transformer: Transformer::new(
                ray_dim,
                slot_dim,
                &cfg.transformer,
                vb.pp("transformer"),
            )?,
            render: Mlp::new(&dims, Activation::Relu, true, vb.pp("render"))?,
        })
    }

    /// # Shapes
    /// `slots: [b, k, ds]`, `rays: [b, r, ray_dim]` → rgb `[b, r, 3]`, no weights
    pub fn forward(&self, slots: &Tensor, rays: &Tensor) -> Result<DecoderOutput> {
        let q = self.query_mlp.forward(rays)?;
        let q = self.transformer.forward(&q, Some(slots))?;
        // A segment whose activations a train step may make again in its backward pass
        // (`osrt_kernels::recompute`).
        let render = self.render.clone();
        let out = osrt_kernels::recompute(&[&q], move |t| render.forward(&t[0]))?;
        let rgb = candle_nn::ops::sigmoid(&out)?;
        Ok(DecoderOutput { rgb, weights: None })
    }
}
