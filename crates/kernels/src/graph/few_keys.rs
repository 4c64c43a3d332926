//! Cross-attention over few keys (the decoder's rays over the slots) as products of the
//! queries, where they lie, with block-diagonal keys and values: one graph node built
//! from tensor ops for the device graph, beside `attention_node`'s.
//!
//! Why: split into heads, every query-side tensor (`q`, the output, their gradients:
//! `[b, n, h·dh]`, 8,192 rays × 1,536 in the `paper` decoder) is copied into head-major
//! order and back, 12 such copies per layer and step — 0.3 GB of the `paper` preset's
//! bf16 step per scene (`osrt bench model --ledger`). Here the heads stay side by side:
//! with `K̂ = blockdiag(K₁ᵀ, …, K_hᵀ)` (`[h·dh, h·m]`) the logits of all heads are one
//! product `Q K̂` (`[b, n, h·m]`), the softmax runs over each head's `m` columns, and
//! with `V̂ = blockdiag(V₁, …, V_h)` (`[h·m, h·dh]`) the output `A V̂` comes out with its
//! heads merged. The price is `h` times the products' FLOPs (the zero blocks), cheap
//! where `h·m` is small ([`FEW_KEYS`]): on the `paper` decoder 3 % more of the step's
//! FLOPs for none of the query side's copies. The zero blocks add exact zeros, so each
//! logit is the same sum as the split product's up to the order of its terms (equal
//! within rounding, not bit for bit); a non-finite query value spreads to the other
//! heads' logits of its row (the step is skipped either way).

use super::attention_node::{Heads, f32_of};
use super::handover::Handover;
use super::matmul::{matmul, matmul_low, stores_low};
use super::node::{Node, TensorNode};
use crate::cpu::softmax::{softmax_grad_scaled, softmax_no_grad};
use crate::kept::Kept;
use crate::ledger;
use candle_core::{DType, Result, Tensor};

/// The most keys over all heads (`h·m`) for which attention takes this node.
pub(crate) const FEW_KEYS: usize = 128;

struct FewKeysNode {
    out: Handover,
    /// Attention weights `[b, n, h·m]` (f32), kept for the backward pass.
    weights: Kept<Tensor>,
    heads: Heads,
    scale: f64,
    /// The types of `q`, `k`, `v` (their gradients' types).
    dtypes: [DType; 3],
}

impl Heads {
    /// `[h, h]` identity, shaped to mask `[b, h, x, h, y]` blocks.
    fn eye(&self, dtype: DType, device: &candle_core::Device) -> Result<Tensor> {
        Tensor::eye(self.h, dtype, device)?.reshape((1, self.h, 1, self.h, 1))
    }

    /// `t: [b, m, h·dh]` → `[b, h·dh, h·m]`, head `j`'s `tᵀ` on the diagonal (keys), or with
    /// `transposed` off `[b, h·m, h·dh]`, head `j`'s `t` on it (values); small (`m` keys).
    fn block_diagonal(&self, t: &Tensor, transposed: bool) -> Result<Tensor> {
        let m = t.dim(1)?;
        let (b, h, dh) = (self.b, self.h, self.dh);
        let heads = t.reshape((b, m, h, dh))?;
        let (blocks, rows, cols) = match transposed {
            true => (heads.permute((0, 2, 3, 1))?, dh, m), // [b, h, dh, m]
            false => (heads.permute((0, 2, 1, 3))?, m, dh), // [b, h, m, dh]
        };
        let eye = self.eye(t.dtype(), t.device())?;
        let d = blocks.unsqueeze(3)?.broadcast_mul(&eye)?; // [b, h, rows, h, cols]
        ledger::op("block diagonal", &[t], &[&d]);
        d.reshape((b, h * rows, h * cols))
    }

    /// The diagonal blocks of `d: [b, h·dh, h·m]` (or `[b, h·m, h·dh]` with `transposed`
    /// off) back as `[b, m, h·dh]` (the gradient of [`Heads::block_diagonal`]'s input).
    fn diagonal_of(&self, d: &Tensor, m: usize, transposed: bool) -> Result<Tensor> {
        let (b, h, dh) = (self.b, self.h, self.dh);
        let (rows, cols) = if transposed { (dh, m) } else { (m, dh) };
        let eye = self.eye(d.dtype(), d.device())?;
        let blocks = d
            .reshape((b, h, rows, h, cols))?
            .broadcast_mul(&eye)?
            .sum(3)?; // [b, h, rows, cols]
        ledger::op("diagonal blocks", &[d], &[&blocks]);
        let per_key = match transposed {
            true => blocks.permute((0, 3, 1, 2))?, // [b, m, h, dh]
            false => blocks.permute((0, 2, 1, 3))?,
        };
        ledger::contiguous(&per_key)?.reshape((b, m, h * dh))
    }
}

/// `a · b` in `dtype`: stored as the bf16 product returns it where that is bf16 and the
/// products run on bf16 operands, else the product's f32 cast to `dtype`.
fn product_in(a: &Tensor, b: &Tensor, dtype: DType) -> Result<Tensor> {
    if dtype == DType::BF16 && stores_low(&[a, b]) {
        return matmul_low(a, b);
    }
    ledger::cast(&matmul(a, b)?, dtype)
}

/// An operand in the products' precision where they take bf16 (rounded once, for all the
/// products that read it), else as it is.
fn low(t: &Tensor) -> Result<Tensor> {
    match stores_low(&[t]) {
        true => ledger::cast(t, DType::BF16),
        false => Ok(t.clone()),
    }
}

/// The weights `softmax(scale · q K̂)` per head: `[b, n, h·m]` (f32).
fn weights(q: &Tensor, kd: &Tensor, hs: Heads, m: usize, scale: f64) -> Result<Tensor> {
    let (b, n) = (hs.b, q.dim(1)?);
    let logits = (matmul(q, kd)? * scale)?;
    let rows = ledger::contiguous(&logits)?.reshape((b, n * hs.h, m))?;
    let a = softmax_no_grad(&rows)?;
    ledger::op("softmax", &[&rows], &[&a]);
    a.reshape((b, n, hs.h * m))
}

impl TensorNode for FewKeysNode {
    fn name(&self) -> &'static str {
        "osrt-few-keys-node"
    }

    fn what(&self) -> &'static str {
        "attention node"
    }

    fn out(&self) -> &Handover {
        &self.out
    }

    /// With `A` the weights and `G` the output's gradient (both `[b, n, h··]`, heads side
    /// by side): `dV̂ = Aᵀ G`, `dA = G V̂ᵀ`, `dL = scale · A ⊙ (dA − Σ A ⊙ dA)` per head,
    /// `dQ = dL K̂ᵀ`, `dK̂ = Qᵀ dL`; `dK`, `dV` are `dK̂`'s and `dV̂`'s diagonal blocks.
    fn backward(&self, operands: &[&Tensor], grad: &Tensor) -> Result<Vec<Option<Tensor>>> {
        let &[q, k, v] = operands else {
            candle_core::bail!("attention node: {} operands", operands.len())
        };
        crate::profile::nested(|| {
            let hs = self.heads;
            let (b, n, m) = (hs.b, q.dim(1)?, k.dim(1)?);
            let q = low(&q.detach())?;
            let kd = low(&hs.block_diagonal(&f32_of(k)?, true)?)?;
            let vd = low(&hs.block_diagonal(&f32_of(v)?, false)?)?;
            let a = match self.weights.take() {
                Some(a) => a,
                None => weights(&q, &kd, hs, m, self.scale)?,
            };
            let g = low(&grad.detach())?;
            let a_low = low(&a)?;
            let dv = hs.diagonal_of(&matmul(&a_low.t()?, &g)?, m, false)?;
            drop(a_low);
            let da = ledger::contiguous(&matmul(&g, &vd.t()?)?)?;
            drop(g);
            let rows = |t: &Tensor| t.reshape((b, n * hs.h, m));
            ledger::op("softmax backward", &[&a, &da], &[&da]);
            let dl = softmax_grad_scaled(&rows(&a)?, rows(&da)?, self.scale)?;
            drop(a);
            let dl = low(&dl.reshape((b, n, hs.h * m))?)?;
            let dq = product_in(&dl, &kd.t()?, self.dtypes[0])?;
            let dk = hs.diagonal_of(&matmul(&q.t()?, &dl)?, m, true)?;
            Ok(vec![
                Some(dq),
                Some(ledger::cast(&dk, self.dtypes[1])?),
                Some(ledger::cast(&dv, self.dtypes[2])?),
            ])
        })
    }
}

/// [`crate::attention`]'s core over few keys (`heads · m ≤` [`FEW_KEYS`]) as one node that
/// keeps only the attention weights: `q: [b, n, h·dh]`, `k, v: [b, m, h·dh]` → `[b, n,
/// h·dh]` in `q`'s type (shapes checked by the caller).
pub(crate) fn attention(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    heads: usize,
    scale: f64,
) -> Result<Tensor> {
    let (b, _, inner) = q.dims3()?;
    let m = k.dim(1)?;
    let hs = Heads {
        b,
        h: heads,
        dh: inner / heads,
    };
    let kd = low(&hs.block_diagonal(&f32_of(k)?, true)?)?;
    let a = weights(&low(&q.detach())?, &kd, hs, m, scale)?;
    drop(kd);
    let vd = low(&hs.block_diagonal(&f32_of(v)?, false)?)?;
    let out = product_in(&low(&a)?, &vd, q.dtype())?;
    let keep = q.track_op() || k.track_op() || v.track_op();
    let node = FewKeysNode {
        out: Handover::new(out)?,
        weights: Kept::new(keep.then_some(a)),
        heads: hs,
        scale,
        dtypes: [q.dtype(), k.dtype(), v.dtype()],
    };
    q.apply_op3(k, v, Node::new(node))
}

#[cfg(test)]
mod tests;
