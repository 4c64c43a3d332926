//! The choice of attention: the fused CPU node where it applies, on the device graph the
//! attention node built from tensor ops, else candle's composed ops
//! ([`attention_composed`]).

use super::pointwise::softmax;
use super::{usable, usable_with_cuda};
use crate::cpu::attention::{self, Dims};
use crate::graph::attention_node::{self, Heads};
use crate::graph::few_keys;
use crate::graph::matmul::{matmul, stores_low};
use crate::{device_graph, profile};
use candle_core::{D, Result, Tensor};

/// Multi-head scaled dot-product attention, `softmax(scale · Q Kᵀ) V` per head, as one
/// graph node where the fused ops apply (else [`attention_composed`]).
///
/// # Shapes
/// `q: [b, n, heads·dh]`, `k, v: [b, m, heads·dh]` → `[b, n, heads·dh]`
pub fn attention(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize, scale: f64) -> Result<Tensor> {
    profile::op("attention", &[q, k, v], move |t| {
        attention_here(&t[0], &t[1], &t[2], heads, scale)
    })
}

fn attention_here(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize, scale: f64) -> Result<Tensor> {
    let (b, n, inner) = q.dims3()?;
    let (bk, m, ik) = k.dims3()?;
    if bk != b || ik != inner || k.dims() != v.dims() || heads == 0 || inner % heads != 0 {
        candle_core::bail!(
            "attention: q {:?}, k {:?}, v {:?} with {heads} heads",
            q.dims(),
            k.dims(),
            v.dims()
        );
    }
    if !(usable(&[q, k, v]) && n > 0 && m > 0) {
        return attention_composed(q, k, v, heads, scale);
    }
    attention::attention(
        q,
        k,
        v,
        Dims {
            b,
            n,
            m,
            h: heads,
            dh: inner / heads,
            scale: scale as f32,
            precision: crate::precision(),
        },
    )
}

/// The same attention from candle ops: split heads, `Q Kᵀ · scale`, softmax, `· V`,
/// merge heads.
pub fn attention_composed(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    heads: usize,
    scale: f64,
) -> Result<Tensor> {
    profile::op("attention", &[q, k, v], move |t| {
        attention_composed_here(&t[0], &t[1], &t[2], heads, scale)
    })
}

fn attention_composed_here(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    heads: usize,
    scale: f64,
) -> Result<Tensor> {
    let (b, n, inner) = q.dims3()?;
    let m = k.dim(1)?;
    let takes = usable_with_cuda(&[q, k, v]) || stores_low(&[q, k, v]);
    if takes && device_graph(q) && n > 0 && m > 0 {
        // A GPU: one node that keeps only the weights (`graph::attention_node`), over
        // few keys with the query side where it lies (`graph::few_keys`).
        if heads > 1 && heads * m <= few_keys::FEW_KEYS {
            return few_keys::attention(q, k, v, heads, scale);
        }
        return attention_node::attention(q, k, v, heads, scale);
    }
    let hs = Heads {
        b,
        h: heads,
        dh: inner / heads,
    };
    let (q, k, v) = (hs.split(q)?, hs.split(k)?, hs.split(v)?);
    let logits = (matmul(&q, &k.t()?)? * scale)?; // [b·h, n, m]
    let attn = softmax(&logits, D::Minus1)?;
    hs.merge(&matmul(&attn, &v)?) // [b·h, n, dh] → [b, n, h·dh]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cpu::attention::{FEW_BATCH, QUERY_ROWS_PER_TASK};
    use crate::testing::{
        assert_matches_composed, both, finite_difference_check, max_abs, max_diff, randn,
    };
    use crate::with_fused;
    use candle_core::{Device, Var};

    /// `[q, k, v]` for `b` batch elements, `n` queries, `m` keys of width `inner`.
    fn args(b: usize, n: usize, m: usize, inner: usize, seed: u64) -> Vec<Tensor> {
        vec![
            randn(&[b, n, inner], 1.0, seed),
            randn(&[b, m, inner], 1.0, seed + 1),
            randn(&[b, m, inner], 1.0, seed + 2),
        ]
    }

    fn run(t: &[Tensor], heads: usize) -> Result<Tensor> {
        let dh = t[0].dim(2)? / heads;
        attention(&t[0], &t[1], &t[2], heads, 1.0 / (dh as f64).sqrt())
    }

    fn values(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1().unwrap()
    }

    #[test]
    fn attention_matches_the_composed_version_and_finite_differences() {
        // Self-attention-like (n = m), the decoder's cross-attention (many queries, few
        // keys), one head and several, one batch element and several.
        for (b, n, m, inner, heads) in [(3, 9, 9, 16, 4), (2, 70, 7, 32, 4), (1, 5, 3, 8, 1)] {
            let a = args(b, n, m, inner, 10 + n as u64);
            assert_matches_composed(&a, |t| run(t, heads), 2e-5);
        }
        finite_difference_check(&args(2, 4, 3, 6, 20), |t| run(t, 2));
        finite_difference_check(&args(1, 3, 5, 4, 21), |t| run(t, 1));
    }

    /// Large logits (a saturated softmax) and constant rows (uniform weights): the
    /// composed version's values, finite gradients.
    /// With few batch elements the forward pass splits the query rows into blocks (here
    /// three, the last one short): the values of the one-task-per-element path (the same
    /// elements inside a batch of `FEW_BATCH`) to float tolerance (gemm may take another
    /// kernel for fewer rows), forward and backward (the weights kept for the backward
    /// pass reassembled from the blocks), and the composed version's values.
    #[test]
    fn query_row_blocks_give_the_bits_of_whole_elements() {
        let n = 2 * QUERY_ROWS_PER_TASK + 37;
        let few = args(2, n, 5, 8, 60);
        let tiled: Vec<Tensor> = few
            .iter()
            .map(|t| Tensor::cat(&[t; FEW_BATCH / 2], 0).unwrap())
            .collect();
        let [(y_few, g_few), _] = both(&few, |t| run(t, 2));
        let [(y_all, g_all), _] = both(&tiled, |t| run(t, 2));
        let first2 = |t: &Tensor| t.narrow(0, 0, 2).unwrap();
        assert!(max_diff(&y_few, &first2(&y_all)) <= 1e-6, "forward");
        for (a, b) in g_few.iter().zip(&g_all) {
            // Each batch element's gradient is its own (nothing is shared across them).
            assert!(max_diff(a, &first2(b)) <= 1e-5, "gradient");
        }
        assert_matches_composed(&few, |t| run(t, 2), 1e-5);
    }

    #[test]
    fn attention_is_finite_and_matches_on_extreme_inputs() {
        let mut big = args(2, 4, 5, 8, 30);
        big[0] = (&big[0] * 1e3).unwrap();
        big[1] = (&big[1] * 1e2).unwrap();
        let mut constant = args(2, 4, 5, 8, 31);
        constant[0] = Tensor::ones((2, 4, 8), candle_core::DType::F32, &Device::Cpu).unwrap();
        constant[1] = Tensor::full(3.0f32, (2, 5, 8), &Device::Cpu).unwrap();
        for a in [big, constant] {
            let [(yf, gf), (yc, gc)] = both(&a, |t| run(t, 2));
            let rel = |x: &Tensor, y: &Tensor| max_diff(x, y) / (1.0 + max_abs(y));
            assert!(rel(&yf, &yc) <= 1e-5, "forward differs");
            for (i, (x, y)) in gf.iter().zip(&gc).enumerate() {
                assert!(values(x).iter().all(|v| v.is_finite()), "gradient {i}");
                assert!(rel(x, y) <= 1e-5, "gradient {i} differs: {}", rel(x, y));
            }
        }
    }

    /// Inputs that are data get no gradient; a second backward through the same graph
    /// (whose weights the first one took) recomputes them and agrees.
    #[test]
    fn data_inputs_get_no_gradient_and_a_second_backward_recomputes() {
        let a = args(2, 6, 4, 8, 40);
        let (kv, vv) = (
            Var::from_tensor(&a[1]).unwrap(),
            Var::from_tensor(&a[2]).unwrap(),
        );
        let ts = [a[0].clone(), kv.as_tensor().clone(), vv.as_tensor().clone()];
        let loss = with_fused(true, || {
            run(&ts, 2).unwrap().sqr().unwrap().sum_all().unwrap()
        });
        let (first, second) = (loss.backward().unwrap(), loss.backward().unwrap());
        assert!(first.get(&a[0]).is_none(), "a data input got a gradient");
        for v in [&kv, &vv] {
            let (g1, g2) = (
                first.get(v.as_tensor()).unwrap(),
                second.get(v.as_tensor()).unwrap(),
            );
            assert_eq!(values(g1), values(g2));
        }
        let no_grad = with_fused(true, || run(&a, 2).unwrap());
        let with_grad = with_fused(true, || run(&ts, 2).unwrap());
        assert_eq!(values(&no_grad), values(&with_grad));
    }

    #[test]
    fn mismatched_shapes_are_an_error() {
        let a = args(2, 3, 4, 8, 50);
        let short = randn(&[2, 4, 6], 1.0, 51);
        with_fused(true, || {
            assert!(attention(&a[0], &short, &a[2], 2, 1.0).is_err());
            assert!(attention(&a[0], &a[1], &a[2], 3, 1.0).is_err());
        });
    }
}
