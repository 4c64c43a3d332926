//! Tests of the whole-MLP ops: the one node against the layer-by-layer ops and candle's
//! composed ops, finite differences, extreme inputs, and the MLP of two inputs side by side.

use super::*;
use crate::cpu::mlp::FORWARDS;
use crate::testing::{
    assert_matches_composed, both, finite_difference_check, max_abs, max_diff, randn,
};
use crate::with_fused;
use candle_core::{Device, Var};

const ACTS: [MlpAct; 3] = [MlpAct::Relu, MlpAct::LeakyRelu(0.01), MlpAct::Gelu];

/// `[x, W1, (b1), W2, (b2), …]` for widths `dims` over `n` rows.
fn args(n: usize, dims: &[usize], bias: bool, seed: u64) -> Vec<Tensor> {
    let mut out = vec![randn(&[n, dims[0]], 1.0, seed)];
    for (i, w) in dims.windows(2).enumerate() {
        let s = seed + 10 * (i as u64 + 1);
        out.push(randn(&[w[1], w[0]], 1.0 / (w[0] as f32).sqrt(), s));
        if bias {
            out.push(randn(&[w[1]], 0.5, s + 1));
        }
    }
    out
}

/// The MLP of `args` (see [`args`]) through `f`.
fn run(
    t: &[Tensor],
    bias: bool,
    act: MlpAct,
    f: fn(&Tensor, &[MlpLayer], MlpAct) -> Result<Tensor>,
) -> Result<Tensor> {
    let step = if bias { 2 } else { 1 };
    let layers: Vec<_> = t[1..].chunks(step).map(|c| (&c[0], c.get(1))).collect();
    f(&t[0], &layers, act)
}

fn values(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1().unwrap()
}

/// The one-node MLP and the per-layer fused ops are the same arithmetic: the same bits
/// forward and backward, for every activation, with and without biases, over enough
/// rows that the row-parallel kernels split the work.
#[test]
fn the_one_node_mlp_gives_the_per_layer_ops_bits() {
    for act in ACTS {
        for bias in [true, false] {
            let a = args(700, &[11, 32, 17, 5], bias, 1);
            let before = FORWARDS.with(|c| c.get());
            let [(y1, g1), (y2, g2)] = [mlp, mlp_layer_by_layer].map(|f| {
                let [(y, g), _] = both(&a, |t| run(t, bias, act, f));
                (y, g)
            });
            // The one-node op ran (once in `both`'s fused half), not a fallback.
            assert_eq!(FORWARDS.with(|c| c.get()), before + 1);
            assert_eq!(values(&y1), values(&y2), "{act:?} bias {bias}: forward");
            for (i, (a, b)) in g1.iter().zip(&g2).enumerate() {
                assert_eq!(values(a), values(b), "{act:?} bias {bias}: gradient {i}");
            }
        }
    }
}

#[test]
fn the_mlp_matches_the_composed_version_and_finite_differences() {
    for act in ACTS {
        let a = args(300, &[7, 24, 24, 4], true, 2);
        assert_matches_composed(&a, |t| run(t, true, act, mlp), 2e-5);
        let a = args(40, &[5, 8, 3], false, 3);
        assert_matches_composed(&a, |t| run(t, false, act, mlp), 2e-5);
    }
    // ReLU's kink is where finite differences straddle; the smooth and leaky ones are
    // checked (with these seeds no pre-activation lies within a step of the kink).
    for act in [MlpAct::Gelu, MlpAct::LeakyRelu(0.01)] {
        finite_difference_check(&args(6, &[3, 5, 4, 2], true, 4), |t| run(t, true, act, mlp));
    }
}

/// Huge inputs and a constant row: the composed ops' values, finite gradients.
#[test]
fn the_mlp_is_finite_and_matches_on_extreme_inputs() {
    for act in ACTS {
        let mut a = args(2, &[3, 6, 2], true, 5);
        a[0] = Tensor::new(&[[1e18f32, -1e18, 3.0], [2.0, 2.0, 2.0]], &Device::Cpu).unwrap();
        let [(yf, gf), (yc, gc)] = both(&a, |t| run(t, true, act, mlp));
        let rel = |x: &Tensor, y: &Tensor| max_diff(x, y) / (1.0 + max_abs(y));
        assert!(rel(&yf, &yc) <= 1e-6, "{act:?}: forward differs");
        for (i, (x, y)) in gf.iter().zip(&gc).enumerate() {
            assert!(
                values(x).iter().all(|v| v.is_finite()),
                "{act:?}: gradient {i}"
            );
            assert!(rel(x, y) <= 1e-6, "{act:?}: gradient {i} differs");
        }
    }
}

/// A data input gets no gradient (and costs no `dx` matmul); a second backward through
/// the same graph (whose saved activations the first one took) recomputes them and
/// gives the same gradients; without any gradient-carrying input nothing is saved.
#[test]
fn data_inputs_get_no_gradient_and_a_second_backward_recomputes() {
    let a = args(50, &[4, 9, 3], true, 6);
    let vars: Vec<Var> = a[1..]
        .iter()
        .map(|t| Var::from_tensor(t).unwrap())
        .collect();
    let mut ts = vec![a[0].clone()];
    ts.extend(vars.iter().map(|v| v.as_tensor().clone()));
    let loss = with_fused(true, || {
        run(&ts, true, MlpAct::Gelu, mlp)
            .unwrap()
            .sqr()
            .unwrap()
            .sum_all()
            .unwrap()
    });
    let first = loss.backward().unwrap();
    let second = loss.backward().unwrap();
    assert!(first.get(&a[0]).is_none(), "a data input got a gradient");
    for v in &vars {
        let (g1, g2) = (
            first.get(v.as_tensor()).unwrap(),
            second.get(v.as_tensor()).unwrap(),
        );
        assert_eq!(values(g1), values(g2));
    }
    let no_grad = with_fused(true, || run(&a, true, MlpAct::Gelu, mlp).unwrap());
    let with_grad = with_fused(true, || run(&ts, true, MlpAct::Gelu, mlp).unwrap());
    assert_eq!(values(&no_grad), values(&with_grad));
}

#[test]
fn mismatched_widths_are_an_error() {
    let x = randn(&[3, 4], 1.0, 7);
    let (w1, w2) = (randn(&[5, 4], 1.0, 8), randn(&[2, 6], 1.0, 9));
    let err = with_fused(true, || mlp(&x, &[(&w1, None), (&w2, None)], MlpAct::Relu));
    assert!(err.is_err());
}

/// `[a, b, W₁, b₁, …]`: the `args` MLP with its input split into widths `wa` and
/// the rest, leading dims `[2, n]`.
fn cat_args(n: usize, wa: usize, dims: &[usize], seed: u64) -> Vec<Tensor> {
    let mut a = args(2 * n, dims, true, seed);
    let x = a.remove(0);
    let x = x.reshape((2, n, dims[0])).unwrap();
    let (left, right) = (
        x.narrow(2, 0, wa).unwrap().contiguous().unwrap(),
        x.narrow(2, wa, dims[0] - wa).unwrap().contiguous().unwrap(),
    );
    [vec![left, right], a].concat()
}

fn run_cat(t: &[Tensor], act: MlpAct) -> Result<Tensor> {
    let layers: Vec<_> = t[2..].chunks(2).map(|c| (&c[0], c.get(1))).collect();
    mlp_cat(&t[0], &t[1], &layers, act)
}

/// Two inputs read side by side give the MLP of their concatenation, forward and
/// backward (each input its own gradient, the first layer's weight its columns), to
/// float tolerance: only the first layer's sums are split in two. Also against
/// candle's composed ops and finite differences, with either input a data input.
#[test]
fn mlp_cat_is_the_mlp_of_the_concatenation() {
    for act in ACTS {
        let a = cat_args(150, 5, &[12, 16, 3], 11);
        let [(y1, g1), _] = both(&a, |t| run_cat(t, act));
        let [(y2, g2), _] = both(&a, |t| {
            let layers: Vec<_> = t[2..].chunks(2).map(|c| (&c[0], c.get(1))).collect();
            mlp(&Tensor::cat(&[&t[0], &t[1]], D::Minus1)?, &layers, act)
        });
        let tol = |b: &Tensor| 1e-5 * (1.0 + max_abs(b));
        assert!(max_diff(&y1, &y2) <= tol(&y2), "{act:?}: forward");
        for (i, (a, b)) in g1.iter().zip(&g2).enumerate() {
            assert!(max_diff(a, b) <= tol(b), "{act:?}: gradient {i}");
        }
        assert_matches_composed(&a, |t| run_cat(t, act), 2e-5);
    }
    finite_difference_check(&cat_args(4, 2, &[5, 6, 2], 12), |t| {
        run_cat(t, MlpAct::Gelu)
    });
    // Data inputs get no gradient; the other input and the parameters do.
    let a = cat_args(20, 3, &[7, 8, 2], 13);
    let vars: Vec<Var> = a[1..]
        .iter()
        .map(|t| Var::from_tensor(t).unwrap())
        .collect();
    let mut ts = vec![a[0].clone()];
    ts.extend(vars.iter().map(|v| v.as_tensor().clone()));
    let y = with_fused(true, || run_cat(&ts, MlpAct::Relu)).unwrap();
    let g = y.sqr().unwrap().sum_all().unwrap().backward().unwrap();
    assert!(g.get(&ts[0]).is_none());
    assert!(ts[1..].iter().all(|t| g.get(t).is_some()));
    // Widths that do not add up are an error, not a panic.
    let bad = with_fused(true, || {
        mlp_cat(&a[0], &a[0], &[(&a[2], Some(&a[3]))], MlpAct::Relu)
    });
    assert!(bad.is_err());
}

/// Huge inputs stay finite and agree with the composed version.
#[test]
fn mlp_cat_is_finite_on_extreme_inputs() {
    let mut a = cat_args(10, 4, &[9, 6, 2], 14);
    a[0] = (&a[0] * 1e15).unwrap();
    let [(y, g), (yc, _)] = both(&a, |t| run_cat(t, MlpAct::LeakyRelu(0.01)));
    assert!(max_diff(&y, &yc) <= 1e-5 * (1.0 + max_abs(&yc)));
    for t in std::iter::once(&y).chain(&g) {
        assert!(max_abs(t).is_finite());
    }
}
