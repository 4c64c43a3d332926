//! Tests of the transformer block node: against the separate ops and candle's composed
//! ops, finite differences, inputs with a storage offset, extreme rows and the fall-back.

use super::*;
use crate::testing::{
    assert_matches_composed, both, finite_difference_check, max_abs, max_diff, randn,
};
use crate::{MlpAct, with_fused};
use candle_core::{D, Var};

const HEADS: usize = 2;

/// `[x, ctx (cross only), γ₁, β₁, W_q, W_k, W_v, W_o, b_o, γ₂, β₂, W₀, b₀, W₁, b₁]`:
/// `b` elements of `n` rows of width `d`, a context of `m` rows of width `dc`,
/// attention width `inner`, MLP hidden width `hid`.
fn args(cross: bool, (b, n, m): (usize, usize, usize), scale: f32, seed: u64) -> Vec<Tensor> {
    let (d, dc, inner, hid) = (6, 5, 8, 10);
    let dc = if cross { dc } else { d };
    let mut a = vec![randn(&[b, n, d], scale, seed)];
    if cross {
        a.push(randn(&[b, m, dc], 1.0, seed + 1));
    }
    let shapes: [&[usize]; 13] = [
        &[d],
        &[d],
        &[inner, d],
        &[inner, dc],
        &[inner, dc],
        &[d, inner],
        &[d],
        &[d],
        &[d],
        &[hid, d],
        &[hid],
        &[d, hid],
        &[d],
    ];
    for (i, s) in shapes.iter().enumerate() {
        a.push(randn(s, 0.5, seed + 10 + i as u64));
    }
    a
}

/// The tensors of `args` as block parameters.
fn params(t: &[Tensor]) -> BlockParams<'_> {
    BlockParams {
        norm_attn: (&t[0], &t[1]),
        q: &t[2],
        k: &t[3],
        v: &t[4],
        out: (&t[5], &t[6]),
        norm_mlp: (&t[7], &t[8]),
        mlp: vec![(&t[9], Some(&t[10])), (&t[11], Some(&t[12]))],
        act: MlpAct::Gelu,
        heads: HEADS,
        eps: 1e-5,
    }
}

/// The block from the separate ops (fused or composed, as the thread's switch says),
/// as `nn::Block::forward_composed` builds it.
fn separate(x: &Tensor, ctx: Option<&Tensor>, p: &BlockParams) -> Result<Tensor> {
    let ln = |x: &Tensor, (g, b): (&Tensor, &Tensor)| crate::layer_norm(x, g, b, p.eps);
    let h = ln(x, p.norm_attn)?;
    let c = ctx.unwrap_or(&h);
    let lin = |x: &Tensor, w: &Tensor| crate::linear(x, w, None);
    let dh = p.q.dim(0)? / p.heads;
    let o = crate::attention(
        &lin(&h, p.q)?,
        &lin(c, p.k)?,
        &lin(c, p.v)?,
        p.heads,
        1.0 / (dh as f64).sqrt(),
    )?;
    let x = (x + crate::linear(&o, p.out.0, Some(p.out.1))?)?;
    let m = crate::mlp(&ln(&x, p.norm_mlp)?, &p.mlp, p.act)?;
    x + m
}

/// The fused block where it applies, else the separate ops.
fn run(cross: bool) -> impl Fn(&[Tensor]) -> Result<Tensor> {
    move |t: &[Tensor]| {
        let (x, ctx, rest) = match cross {
            true => (&t[0], Some(&t[1]), &t[2..]),
            false => (&t[0], None, &t[1..]),
        };
        let p = params(rest);
        match block(x, ctx, &p)? {
            Some(y) => Ok(y),
            None => separate(x, ctx, &p),
        }
    }
}

/// Value and gradients of `Σ f(args) · u` with the fused ops on, and the number of
/// activation nodes in the graph.
fn value_and_grads(
    args: &[Tensor],
    f: impl Fn(&[Tensor]) -> Result<Tensor>,
) -> (Vec<f32>, Vec<Vec<f32>>, usize) {
    with_fused(true, || {
        let vars: Vec<Var> = args.iter().map(|a| Var::from_tensor(a).unwrap()).collect();
        let ts: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();
        let y = f(&ts).unwrap();
        let u = randn(y.dims(), 1.0, 77);
        let grads = (&y * &u).unwrap().sum_all().unwrap().backward().unwrap();
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let g = ts.iter().map(|t| flat(grads.get(t).unwrap())).collect();
        // Graph nodes of activations, `[b, n, ·]`: the ones whose gradient
        // accumulation candle pays for.
        let big = y
            .sorted_nodes()
            .iter()
            .filter(|n| n.rank() == 3 && n.dims()[..2] == y.dims()[..2])
            .count();
        (flat(&y), g, big)
    })
}

/// One node gives the separate fused ops' forward bits, and their gradients for input,
/// context and every parameter to float tolerance (only the order in which a tensor's
/// gradient terms are summed may differ), self- and cross-attention.
#[test]
fn block_matches_the_separate_ops() {
    for cross in [false, true] {
        let a = args(cross, (3, 7, 4), 1.0, 1);
        let (y1, g1, nodes1) = value_and_grads(&a, run(cross));
        let (y2, g2, nodes2) = value_and_grads(&a, |t| {
            let (x, ctx, rest) = match cross {
                true => (&t[0], Some(&t[1]), &t[2..]),
                false => (&t[0], None, &t[1..]),
            };
            separate(x, ctx, &params(rest))
        });
        assert_eq!(y1, y2, "forward bits (cross {cross})");
        for (i, (a, b)) in g1.iter().zip(&g2).enumerate() {
            let scale = 1.0 + b.iter().fold(0f32, |m, v| m.max(v.abs()));
            let diff = a.iter().zip(b).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
            assert!(
                diff <= 1e-5 * scale,
                "gradient {i} differs by {diff} (cross {cross})"
            );
        }
        // Activation-sized nodes: input and output only, against every intermediate.
        assert_eq!(nodes1, 2);
        assert!(
            nodes2 >= 9,
            "{nodes2} activation-sized nodes in the separate ops"
        );
    }
}

/// Input and context that start inside a larger buffer (a contiguous view with an
/// offset) give the bits of fresh copies, forward and backward.
#[test]
fn inputs_with_a_storage_offset_give_the_bits_of_copies() {
    for cross in [false, true] {
        let a = args(cross, (2, 5, 3), 1.0, 6);
        let n_inputs = if cross { 2 } else { 1 };
        let offset: Vec<Tensor> = a
            .iter()
            .enumerate()
            .map(|(i, t)| match i < n_inputs {
                // Rows 1.. of a tensor with one extra leading row.
                true => Tensor::cat(&[&t.narrow(0, 0, 1).unwrap(), t], 0)
                    .unwrap()
                    .narrow(0, 1, t.dim(0).unwrap())
                    .unwrap(),
                false => t.clone(),
            })
            .collect();
        assert!(offset[0].storage_and_layout().1.start_offset() > 0);
        let f = |ts: &[Tensor]| {
            let vars: Vec<Var> = ts.iter().map(|t| Var::from_tensor(t).unwrap()).collect();
            // Var::from_tensor copies; keep the offset views for the inputs.
            let mut inputs: Vec<Tensor> = ts[..n_inputs].to_vec();
            inputs.extend(vars[n_inputs..].iter().map(|v| v.as_tensor().clone()));
            let y = with_fused(true, || run(cross)(&inputs)).unwrap();
            let g = (&y * &randn(y.dims(), 1.0, 9)).unwrap().sum_all().unwrap();
            let g = g.backward().unwrap();
            let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let grads: Vec<Vec<f32>> = vars[n_inputs..]
                .iter()
                .map(|v| flat(g.get(v.as_tensor()).unwrap()))
                .collect();
            (flat(&y), grads)
        };
        assert_eq!(f(&offset), f(&a), "cross {cross}");
    }
}

/// Against candle's composed ops (softmax, matmuls, broadcast adds) and finite
/// differences in f64.
#[test]
fn block_matches_the_composed_version_and_finite_differences() {
    for cross in [false, true] {
        assert_matches_composed(&args(cross, (2, 5, 3), 1.0, 2), run(cross), 1e-4);
        finite_difference_check(&args(cross, (1, 3, 2), 1.0, 3), run(cross));
    }
}

/// In bf16 against the f32 block and f64 finite differences (`bf16_twin_check`).
#[test]
fn block_in_bf16_tracks_the_f32_block() {
    for cross in [false, true] {
        for scale in [1.0, 1e-18, 1e17] {
            let args = args(cross, (2, 5, 3), scale, 4);
            let what = format!("block (cross {cross}) at {scale:e}");
            crate::testing::bf16_twin_check(&what, &args, run(cross), 1e-2, scale == 1.0);
        }
    }
}

/// Huge inputs and constant rows (LayerNorm's zero variance) stay finite and agree with
/// the composed version.
#[test]
fn block_is_finite_on_extreme_and_constant_rows() {
    for cross in [false, true] {
        let mut a = args(cross, (2, 4, 3), 1e15, 4);
        let [(y, g), (yc, _)] = both(&a, run(cross));
        let rel = max_diff(&y, &yc) / (1.0 + max_abs(&yc));
        assert!(rel <= 1e-5, "forward differs by {rel} (relative)");
        for t in std::iter::once(&y).chain(&g) {
            assert!(max_abs(t).is_finite());
        }
        // Constant rows: every row of the input the same value.
        a[0] = (a[0].zeros_like().unwrap() + 3.0).unwrap();
        let [(y, g), _] = both(&a, run(cross));
        for t in std::iter::once(&y).chain(&g) {
            assert!(max_abs(t).is_finite());
        }
        assert!(y.dim(D::Minus1).unwrap() == 6);
    }
}

/// Parameters that do not fit are refused with `None` (the caller composes), not a
/// panic: here a bias-free MLP.
#[test]
fn a_block_that_does_not_fit_falls_back() {
    let a = args(false, (1, 3, 3), 1.0, 5);
    let mut p = params(&a[1..]);
    p.mlp[0].1 = None;
    assert!(
        with_fused(true, || block(&a[0], None, &p))
            .unwrap()
            .is_none()
    );
}
