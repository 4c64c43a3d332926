//! The Slot Mixer decoder (paper eqs. 4–6). Ray queries (an MLP of the ray encoding)
//! cross-attend into the slots in a small *allocation transformer*; a *mixing block*
//! computes single-head dot-product weights `w` over slots (softmax over slots) from the
//! transformer's output, and the mixed slot `wᵀS`; a *render MLP* maps (mixed slot ⊕
//! query) to RGB, where the query is the ray's MLP encoding before the transformer, so
//! colour depends on the slots only through the mixed slot. Exactly one render-MLP pass
//! per ray, whatever the slot count — the reason it is fast.

use crate::decoder::DecoderOutput;
use crate::nn::{Activation, Linear, Mlp, Transformer, TransformerConfig, linear};
use candle_core::{D, Module, Result, Tensor};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};
use std::cell::RefCell;
use std::rc::Rc;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Config {
    /// Hidden width of the query MLP (ray encoding → hidden → ray-encoding width).
    pub query_hidden: usize,
    pub allocation: TransformerConfig,
    /// Hidden widths of the render MLP.
    pub render_hidden: Vec<usize>,
}

impl Config {
    pub fn paper() -> Self {
        Self {
            query_hidden: 360,
            // Attention width follows the slots (12 × 128 = 1536), MLP 2 × 1536.
            allocation: TransformerConfig {
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
pub struct SlotMixer {
    query_mlp: Mlp,
    allocation: Transformer,
    mix_q: Linear,
    mix_k: Linear,
    render: Mlp,
    slot_dim: usize,
}

impl SlotMixer {
    pub fn new(cfg: &Config, ray_dim: usize, slot_dim: usize, vb: VarBuilder) -> Result<Self> {
        Self::with_outputs(cfg, ray_dim, slot_dim, 3, vb)
    }

    /// The same decoder with `outputs` values per query from its render MLP (the
    /// volumetric decoder's points: density and RGB).
    pub(crate) fn with_outputs(
        cfg: &Config,
        ray_dim: usize,
        slot_dim: usize,
        outputs: usize,
        vb: VarBuilder,
    ) -> Result<Self> {
        let mut render_dims = vec![slot_dim + ray_dim];
        render_dims.extend(&cfg.render_hidden);
        render_dims.push(outputs);
        Ok(Self {
            query_mlp: Mlp::new(
                &[ray_dim, cfg.query_hidden, ray_dim],
                Activation::Relu,
                true,
                vb.pp("query_mlp"),
            )?,
            allocation: Transformer::new(ray_dim, slot_dim, &cfg.allocation, vb.pp("allocation"))?,
            mix_q: linear(ray_dim, slot_dim, false, vb.pp("mix_q"))?,
            mix_k: linear(slot_dim, slot_dim, false, vb.pp("mix_k"))?,
            render: Mlp::new(&render_dims, Activation::LeakyRelu, true, vb.pp("render"))?,
            slot_dim,
        })
    }

    /// # Shapes
    /// `slots: [b, k, ds]`, `rays: [b, r, ray_dim]` (encoded) → rgb `[b, r, 3]`,
    /// weights `[b, r, k]`
    pub fn forward(&self, slots: &Tensor, rays: &Tensor) -> Result<DecoderOutput> {
        let (out, weights) = self.forward_raw(slots, rays)?;
        Ok(DecoderOutput {
            rgb: candle_nn::ops::sigmoid(&out)?,
            weights: Some(weights),
        })
    }

    /// Query MLP, allocation, mixing and render MLP, before any output activation.
    ///
    /// The slot weights are the metrics' (no loss reads them): they come without their
    /// graph.
    ///
    /// # Shapes
    /// `slots: [b, k, ds]`, `queries: [b, r, ray_dim]` (encoded) → render-MLP output
    /// `[b, r, outputs]`, weights `[b, r, k]`
    pub(crate) fn forward_raw(&self, slots: &Tensor, queries: &Tensor) -> Result<(Tensor, Tensor)> {
        let query = self.query_mlp.forward(queries)?; // [b, r, ray_dim]
        let allocated = self.allocation.forward(&query, Some(slots))?; // [b, r, ray_dim]
        let scale = 1.0 / (self.slot_dim as f64).sqrt();
        // The mixing block and the render MLP of (mixed ⊕ query), without materialising
        // the concatenation: a segment whose activations a train step may make again in
        // its backward pass (`osrt_kernels::recompute`), which hands the weights out of
        // its forward pass beside its output.
        let (mix_q, mix_k, render) = (self.mix_q.clone(), self.mix_k.clone(), self.render.clone());
        let weights = Rc::new(RefCell::new(None));
        let taken = weights.clone();
        let out = osrt_kernels::recompute(&[&allocated, slots, &query], move |t| {
            // [b, r, ds], [b, r, k]
            let (mixed, weights) = mix(&t[0], &t[1], &mix_q, &mix_k, scale)?;
            *taken.borrow_mut() = Some(weights.detach());
            render.forward_cat(&mixed, &t[2])
        })?;
        let weights = weights
            .borrow_mut()
            .take()
            .expect("the segment's forward pass ran");
        Ok((out, weights))
    }
}

/// The mixing block (eq. 5): weights `w = softmax_k((x W_qᵀ)(S W_kᵀ)ᵀ / √ds)` over the
/// slots for each ray and the mixed slot `wᵀS`; one graph node where the fused kernel
/// applies (`osrt_kernels::slot_mix`), else composed here.
///
/// # Shapes
/// `x: [b, r, ray_dim]` (the allocation transformer's output), `slots: [b, k, ds]` →
/// mixed `[b, r, ds]`, weights `[b, r, k]`
fn mix(
    x: &Tensor,
    slots: &Tensor,
    mix_q: &Linear,
    mix_k: &Linear,
    scale: f64,
) -> Result<(Tensor, Tensor)> {
    let (w_q, w_k) = (mix_q.weight(), mix_k.weight());
    if let Some(out) = osrt_kernels::slot_mix(x, slots, w_q, w_k, scale)? {
        return Ok(out);
    }
    // `q` and the mixed slot are read only by products (the logits', the render MLP's):
    // in bf16 they are stored in bf16 (`osrt_kernels::matmul_low`).
    let q = osrt_kernels::linear_low(x, w_q)?; // [b, r, ds]
    let k = osrt_kernels::linear(slots, w_k, None)?; // [b, k, ds]
    let logits = (osrt_kernels::matmul(&q, &k.t()?)? * scale)?; // [b, r, k]
    let weights = osrt_kernels::softmax(&logits, D::Minus1)?;
    Ok((osrt_kernels::matmul_low(&weights, slots)?, weights))
}
