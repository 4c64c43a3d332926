//! The core of multi-head attention, `softmax(scale · Q Kᵀ) V` per head, as one graph
//! node built from tensor ops, for devices without a hand-written attention kernel (a
//! GPU: the products are cuBLAS's, the softmax `cuda.rs`'s).
//!
//! Why: composed, the graph keeps the logits, the scaled logits and the weights, each
//! `[b·h, n, m]`, for the backward pass (and more with bf16 copies), which is most of the
//! memory of an encoder over five views. This node computes the forward pass on detached
//! tensors, keeps only the weights (as PyTorch's eager attention does), and its backward
//! pass is the textbook one in tensor ops. The result is handed to the graph through a
//! node on `(q, k, v)` whose forward returns a copy of it (the size of the output, not of
//! the weights).

use crate::handover::Handover;
use crate::*;
use candle_core::{CpuStorage, CustomOp3, Layout, Result, Shape, Tensor};

/// The finished forward pass, handed over once to [`AttentionNode`]'s forward.
struct AttentionNode {
    out: Handover,
    /// Attention weights `[b·h, n, m]`, kept for the backward pass when it can follow.
    weights: Kept<Tensor>,
    scale: f64,
}

impl CustomOp3 for AttentionNode {
    fn name(&self) -> &'static str {
        "osrt-attention-node"
    }

    fn cpu_fwd(
        &self,
        _: &CpuStorage,
        _: &Layout,
        _: &CpuStorage,
        _: &Layout,
        _: &CpuStorage,
        _: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        self.out.cpu("attention node")
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        _: &candle_core::CudaStorage,
        _: &Layout,
        _: &candle_core::CudaStorage,
        _: &Layout,
        _: &candle_core::CudaStorage,
        _: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        self.out.cuda("attention node")
    }

    /// With `A` the weights and `G` the output's gradient: `dV = Aᵀ G`, `dA = G Vᵀ`,
    /// `dL = scale · A ⊙ (dA − Σ A ⊙ dA)`, `dQ = dL K`, `dK = dLᵀ Q`.
    fn bwd(
        &self,
        q: &Tensor,
        k: &Tensor,
        v: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        // The products below are this node's backward pass, not ops of the step's own
        // (a profile recording the step must not count them apart).
        crate::profile::nested(|| {
            let (q, k, v) = (q.detach(), k.detach(), v.detach());
            let a = match self.weights.take() {
                Some(a) => a,
                None => scores(&q, &k, self.scale)?,
            };
            let g = grad.detach().contiguous()?;
            let dv = matmul(&a.t()?, &g)?;
            let da = matmul(&g, &v.t()?)?.contiguous()?;
            let dl = (softmax::softmax_grad(&a, &da)? * self.scale)?;
            let dq = matmul(&dl, &k)?;
            let dk = matmul(&dl.t()?, &q)?;
            Ok((Some(dq), Some(dk), Some(dv)))
        })
    }
}

/// `softmax(scale · q kᵀ)` over the last dimension: `[bh, n, dh]`, `[bh, m, dh]` → `[bh, n, m]`.
fn scores(q: &Tensor, k: &Tensor, scale: f64) -> Result<Tensor> {
    // The scale goes on the smaller operand: `q` has n·dh values, the logits n·m.
    let (dh, m) = (q.dim(2)?, k.dim(1)?);
    let logits = if dh <= m {
        matmul(&(q * scale)?, &k.t()?)?
    } else {
        (matmul(q, &k.t()?)? * scale)?
    };
    softmax::softmax_no_grad(&logits.contiguous()?)
}

/// [`crate::attention`]'s core on heads already split: `q: [bh, n, dh]`, `k, v: [bh, m,
/// dh]` → `[bh, n, dh]`, as one node that keeps only the attention weights.
pub(crate) fn attention_heads(q: &Tensor, k: &Tensor, v: &Tensor, scale: f64) -> Result<Tensor> {
    let (qd, kd, vd) = (q.detach(), k.detach(), v.detach());
    let a = scores(&qd, &kd, scale)?;
    let out = matmul(&a, &vd)?.contiguous()?;
    let keep = q.track_op() || k.track_op() || v.track_op();
    let node = AttentionNode {
        out: Handover::new(out)?,
        weights: Kept::new(keep.then_some(a)),
        scale,
    };
    q.apply_op3(k, v, node)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::*;

    /// The node against candle's composed ops, and against finite differences.
    #[test]
    fn the_attention_node_matches_the_composed_ops_and_finite_differences() {
        let composed = |t: &[Tensor], s: f64| -> Result<Tensor> {
            let logits = (t[0].matmul(&t[1].t()?)? * s)?;
            candle_nn::ops::softmax(&logits, 2)?.matmul(&t[2])
        };
        for (n, m, dh) in [(5, 7, 4), (9, 3, 6)] {
            let args = [
                randn(&[2, n, dh], 1.0, 71),
                randn(&[2, m, dh], 1.0, 72),
                randn(&[2, m, dh], 1.0, 73),
            ];
            let [(y1, g1), (y2, g2)] = [true, false].map(|node| {
                let f = |t: &[Tensor]| {
                    if node {
                        attention_heads(&t[0], &t[1], &t[2], 0.4)
                    } else {
                        composed(t, 0.4)
                    }
                };
                both(&args, f)[0].clone()
            });
            assert!(max_diff(&y1, &y2) < 1e-5);
            for (a, b) in g1.iter().zip(&g2) {
                assert!(max_diff(a, b) < 1e-5 * max_abs(b).max(1.0));
            }
            finite_difference_check(&args, |t| attention_heads(&t[0], &t[1], &t[2], 0.4));
        }
    }

    #[test]
    fn extreme_logits_give_finite_weights_and_gradients() {
        let q = (randn(&[1, 4, 8], 1.0, 81) * 1e15).unwrap();
        let k = (randn(&[1, 6, 8], 1.0, 82) * 1e15).unwrap();
        let v = randn(&[1, 6, 8], 1.0, 83);
        let [(y, grads), _] = both(&[q, k, v], |t| attention_heads(&t[0], &t[1], &t[2], 0.35));
        for t in std::iter::once(&y).chain(&grads) {
            let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            assert!(v.iter().all(|x| x.is_finite()), "{v:?}");
        }
    }
}
