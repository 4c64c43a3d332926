//! The core of multi-head attention, `softmax(scale · Q Kᵀ) V` per head, as one graph
//! node built from tensor ops, for devices without a hand-written attention kernel (a
//! GPU: the products are cuBLAS's, the softmax `crate::cuda`'s).
//!
//! Why: composed, the graph keeps the logits, the scaled logits and the weights, each
//! `[b·h, n, m]`, for the backward pass (and more with bf16 copies), which is most of the
//! memory of an encoder over five views. This node computes the forward pass on detached
//! tensors, keeps only the weights (as PyTorch's eager attention does), and its backward
//! pass is the textbook one in tensor ops. The result is handed to the graph through a
//! node on `(q, k, v)` whose forward returns a copy of it (the size of the output, not of
//! the weights).
//!
//! The node takes `q`, `k`, `v` and returns its output with the heads side by side in the
//! last dimension (`[b, len, h·dh]`, the projections' layout) and splits and merges the
//! heads on detached tensors: split in the graph, each head-major copy (`[b·h, len, dh]`)
//! of `q`, `k`, `v` and of the output would be a node's input, kept beside the tensor it
//! was copied from until the backward pass (the `paper` decoder's queries at 8,192 rays:
//! two extra `[b, 8192, 1536]` tensors per attention layer, 23 % of its activations).
//!
//! `q`, `k`, `v` may be stored in bf16 (projections stored as the bf16 product returns
//! them, [`crate::linear_low`]): the node computes in f32 from them, as it would from
//! their exact f32 values, returns its output in `q`'s type (in bf16 for the output
//! projection's bf16 product, which rounds it the same way) and each gradient in its
//! operand's type.

use super::handover::Handover;
use super::matmul::{matmul, matmul_low, stores_low};
use super::node::{Node, TensorNode};
use crate::cpu::softmax::{softmax_grad_scaled, softmax_no_grad};
use crate::kept::Kept;
use crate::ledger;
use candle_core::{DType, Result, Tensor};

/// The finished forward pass, handed over once to [`AttentionNode`]'s forward.
struct AttentionNode {
    out: Handover,
    /// Attention weights `[b·h, n, m]`, kept for the backward pass when it can follow.
    weights: Kept<Tensor>,
    heads: Heads,
    scale: f64,
    /// The types of `q` and `k` (their gradients' types).
    dtypes: [DType; 2],
}

/// `t` detached, a bf16 tensor widened to f32 (other types as they are).
pub(crate) fn f32_of(t: &Tensor) -> Result<Tensor> {
    match t.dtype() {
        DType::BF16 => ledger::cast(&t.detach(), DType::F32),
        _ => Ok(t.detach()),
    }
}

/// How `[b, len, h·dh]` splits into heads.
#[derive(Clone, Copy)]
pub(crate) struct Heads {
    pub(crate) b: usize,
    pub(crate) h: usize,
    pub(crate) dh: usize,
}

impl Heads {
    /// `[b, len, h·dh]` → `[b·h, len, dh]` (a copy).
    pub(crate) fn split(&self, t: &Tensor) -> Result<Tensor> {
        let len = t.dim(1)?;
        let s = t.reshape((self.b, len, self.h, self.dh))?.transpose(1, 2)?;
        if self.h > 1 {
            ledger::cast_of(s.elem_count(), s.dtype(), s.dtype());
        }
        s.reshape((self.b * self.h, len, self.dh))
    }

    /// `[b·h, len, dh]` → `[b, len, h·dh]` (a copy).
    pub(crate) fn merge(&self, t: &Tensor) -> Result<Tensor> {
        let len = t.dim(1)?;
        let m = t.reshape((self.b, self.h, len, self.dh))?.transpose(1, 2)?;
        if self.h > 1 {
            ledger::cast_of(m.elem_count(), m.dtype(), m.dtype());
        }
        m.reshape((self.b, len, self.h * self.dh))
    }

    /// [`Heads::split`] of `t` detached, as a product's operand: a bf16 `t` stays bf16
    /// where the products take bf16 operands (they round an f32 operand to bf16, which
    /// gives a widened bf16 value back exactly), else it is widened to f32 after the split
    /// (the copy made in the narrower type).
    fn split_operand(&self, t: &Tensor) -> Result<Tensor> {
        let s = self.split(&t.detach())?;
        match s.dtype() == DType::BF16 && stores_low(&[&s]) {
            true => Ok(s),
            false => f32_of(&s),
        }
    }

    /// `a · b` (`[b·h, len, dh]`) merged into `[b, len, h·dh]` in `dtype`: where that is bf16
    /// and the products run on bf16 operands, the bf16 product as it comes out (the bits
    /// of its f32 result rounded back), with no f32 copy of it.
    fn merged_product(&self, a: &Tensor, b: &Tensor, dtype: DType) -> Result<Tensor> {
        if dtype == DType::BF16 && stores_low(&[a, b]) {
            return self.merge(&matmul_low(a, b)?);
        }
        self.merge_to(matmul(a, b)?, dtype)
    }

    /// [`Heads::merge`] of `t` in `dtype`: narrowed first (the values of narrowing after
    /// the merge), so that `t` goes before the copy is made.
    fn merge_to(&self, t: Tensor, dtype: DType) -> Result<Tensor> {
        let low = ledger::cast(&t, dtype)?;
        drop(t);
        self.merge(&low)
    }
}

impl TensorNode for AttentionNode {
    fn name(&self) -> &'static str {
        "osrt-attention-node"
    }

    fn what(&self) -> &'static str {
        "attention node"
    }

    fn out(&self) -> &Handover {
        &self.out
    }

    /// With `A` the weights and `G` the output's gradient: `dV = Aᵀ G`, `dA = G Vᵀ`,
    /// `dL = scale · A ⊙ (dA − Σ A ⊙ dA)`, `dQ = dL K`, `dK = dLᵀ Q`.
    fn backward(&self, operands: &[&Tensor], grad: &Tensor) -> Result<Vec<Option<Tensor>>> {
        let &[q, k, v] = operands else {
            candle_core::bail!("attention node: {} operands", operands.len())
        };
        // The products below are this node's backward pass, not ops of the step's own
        // (a profile recording the step must not count them apart).
        crate::profile::nested(|| {
            let hs = self.heads;
            let a = match self.weights.take() {
                Some(a) => a,
                None => scores(&hs.split_operand(q)?, &hs.split_operand(k)?, self.scale)?,
            };
            // Where the products take bf16 operands, the weights and the logits' gradient
            // are each rounded once and read transposed in place (no copy per product).
            let low = |t: &Tensor| match stores_low(&[t]) {
                true => ledger::cast(t, DType::BF16),
                false => Ok(t.clone()),
            };
            let g = hs.split_operand(grad)?;
            let dv = hs.merged_product(&low(&a)?.t()?, &g, v.dtype())?;
            let da = ledger::contiguous(&matmul(&g, &hs.split_operand(v)?.t()?)?)?;
            drop(g);
            // The logits' gradient written over the weights' (the product's own tensor).
            ledger::op("softmax backward", &[&a, &da], &[&da]);
            let dl = low(&softmax_grad_scaled(&a, da, self.scale)?)?;
            drop(a);
            // k and q split one at a time, each where its product reads it: with many
            // queries (the decoder's rays) q and its gradient are the largest tensors here.
            let dq = hs.merged_product(&dl, &hs.split_operand(k)?, self.dtypes[0])?;
            let dk = hs.merged_product(&dl.t()?, &hs.split_operand(q)?, self.dtypes[1])?;
            Ok(vec![Some(dq), Some(dk), Some(dv)])
        })
    }
}

/// `softmax(scale · q kᵀ)` over the last dimension: `[bh, n, dh]`, `[bh, m, dh]` → `[bh, n, m]`.
fn scores(q: &Tensor, k: &Tensor, scale: f64) -> Result<Tensor> {
    // The scale goes on the smaller operand: `q` has n·dh values, the logits n·m.
    let (dh, m) = (q.dim(2)?, k.dim(1)?);
    let logits = if dh <= m {
        // Scaled in f32, as an f32 `q` is, before the product rounds it.
        let q = f32_of(q)?;
        let scaled = (&q * scale)?;
        ledger::op("scale", &[&q], &[&scaled]);
        matmul(&scaled, &k.t()?)?
    } else {
        let l = matmul(q, &k.t()?)?;
        let scaled = (&l * scale)?;
        ledger::op("scale", &[&l], &[&scaled]);
        scaled
    };
    let logits = ledger::contiguous(&logits)?;
    let a = softmax_no_grad(&logits)?;
    ledger::op("softmax", &[&logits], &[&a]);
    Ok(a)
}

/// [`crate::attention`]'s core as one node that keeps only the attention weights: `q: [b,
/// n, h·dh]`, `k, v: [b, m, h·dh]` → `[b, n, h·dh]` (`heads` = h; shapes checked by the
/// caller).
pub(crate) fn attention(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    heads: usize,
    scale: f64,
) -> Result<Tensor> {
    let (b, _, inner) = q.dims3()?;
    let hs = Heads {
        b,
        h: heads,
        dh: inner / heads,
    };
    let a = scores(&hs.split_operand(q)?, &hs.split_operand(k)?, scale)?;
    let out = hs.merged_product(&a, &hs.split_operand(v)?, q.dtype())?;
    let keep = q.track_op() || k.track_op() || v.track_op();
    let node = AttentionNode {
        out: Handover::new(out)?,
        weights: Kept::new(keep.then_some(a)),
        heads: hs,
        scale,
        dtypes: [q.dtype(), k.dtype()],
    };
    q.apply_op3(k, v, Node::new(node))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{both, f32_bits, finite_difference_check, max_abs, max_diff, randn};
    use crate::{Kernels, Precision, with_kernels, with_precision};
    use candle_core::Var;

    /// `[b, len, h·dh]` → per head `softmax(s · q kᵀ) v` → `[b, n, h·dh]` from candle's ops.
    fn composed(t: &[Tensor], heads: usize, s: f64) -> Result<Tensor> {
        let (b, _, inner) = t[0].dims3()?;
        let hs = Heads {
            b,
            h: heads,
            dh: inner / heads,
        };
        let (q, k, v) = (hs.split(&t[0])?, hs.split(&t[1])?, hs.split(&t[2])?);
        let logits = (q.matmul(&k.t()?)? * s)?;
        hs.merge(&candle_nn::ops::softmax(&logits, 2)?.matmul(&v)?)
    }

    /// The node (heads split and merged inside it) against candle's composed ops, and
    /// against finite differences.
    #[test]
    fn the_attention_node_matches_the_composed_ops_and_finite_differences() {
        for (n, m, heads, dh) in [(5, 7, 1, 4), (9, 3, 3, 2), (4, 6, 2, 3)] {
            let args = [
                randn(&[2, n, heads * dh], 1.0, 71),
                randn(&[2, m, heads * dh], 1.0, 72),
                randn(&[2, m, heads * dh], 1.0, 73),
            ];
            let node = |t: &[Tensor]| attention(&t[0], &t[1], &t[2], heads, 0.4);
            let [(y1, g1), _] = both(&args, node);
            let [(y2, g2), _] = both(&args, |t| composed(t, heads, 0.4));
            assert_eq!(y1.dims(), &[2, n, heads * dh]);
            assert!(max_diff(&y1, &y2) < 1e-5);
            for (a, b) in g1.iter().zip(&g2) {
                assert_eq!(a.dims(), b.dims());
                assert!(max_diff(a, b) < 1e-5 * max_abs(b).max(1.0));
            }
            finite_difference_check(&args, node);
        }
    }

    /// On the device graph with bf16 products, `q`, `k`, `v` stored in bf16 (as the bf16
    /// projections return them) give the values and gradients of the same values stored
    /// in f32, to the bit (each in its operand's type), with the scale on `q` (`dh ≤ m`)
    /// and on the logits (`dh > m`, the decoder's rays over few slots).
    #[test]
    fn bf16_operands_give_their_f32_values_bits() {
        let run = |dtype: DType, n: usize, m: usize, heads: usize, dh: usize| {
            let vars: Vec<Var> = [(n, 91u64), (m, 92), (m, 93)]
                .iter()
                .map(|&(len, seed)| {
                    let t = randn(&[2, len, heads * dh], 1.0, seed);
                    // Values a bf16 tensor holds, in either type.
                    let t = t.to_dtype(DType::BF16).unwrap().to_dtype(dtype).unwrap();
                    Var::from_tensor(&t).unwrap()
                })
                .collect();
            with_kernels(Kernels::Device, || {
                with_precision(Precision::Bf16, || {
                    let (q, k, v) = (
                        vars[0].as_tensor(),
                        vars[1].as_tensor(),
                        vars[2].as_tensor(),
                    );
                    let y = attention(q, k, v, heads, 0.3).unwrap();
                    assert_eq!(y.dtype(), dtype);
                    let w = randn(y.dims(), 1.0, 94).to_dtype(dtype).unwrap();
                    let g = (&y * &w).unwrap().sum_all().unwrap().backward().unwrap();
                    let mut out = vec![f32_bits(&y)];
                    for var in &vars {
                        let d = g.get(var.as_tensor()).unwrap();
                        assert_eq!(d.dtype(), dtype);
                        out.push(f32_bits(d));
                    }
                    out
                })
            })
        };
        for (n, m, heads, dh) in [(5, 7, 2, 3), (40, 3, 2, 8)] {
            let low = run(DType::BF16, n, m, heads, dh);
            let high = run(DType::F32, n, m, heads, dh);
            for (k, (a, b)) in low.iter().zip(&high).enumerate() {
                assert_eq!(a, b, "output/gradient {k}, n {n} m {m} dh {dh}");
            }
        }
    }

    #[test]
    fn extreme_logits_give_finite_weights_and_gradients() {
        let q = (randn(&[1, 4, 8], 1.0, 81) * 1e15).unwrap();
        let k = (randn(&[1, 6, 8], 1.0, 82) * 1e15).unwrap();
        let v = randn(&[1, 6, 8], 1.0, 83);
        let [(y, grads), _] = both(&[q, k, v], |t| attention(&t[0], &t[1], &t[2], 2, 0.35));
        for t in std::iter::once(&y).chain(&grads) {
            let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            assert!(v.iter().all(|x| x.is_finite()), "{v:?}");
        }
    }
}
