//! The choice of the row-wise ops: the activations ([`MlpAct`]'s node included),
//! softmax, LayerNorm, the bias add and bias with activation each run as the fused node
//! where it applies (the ops with CUDA kernels also on a GPU), else as candle's composed
//! ops.

use super::{usable, usable_with_cuda};
use crate::cpu::{self, MlpAct};
use crate::{ledger, profile};
use candle_core::{D, Result, Tensor};

/// erf-based GELU, elementwise.
pub fn gelu(x: &Tensor) -> Result<Tensor> {
    let y = profile::op("gelu", &[x], |t| gelu_here(&t[0]))?;
    pointwise("gelu", &[x], y)
}

fn gelu_here(x: &Tensor) -> Result<Tensor> {
    if usable(&[x]) {
        return cpu::activation::gelu(x);
    }
    x.gelu_erf()
}

/// `max(x, 0)`, elementwise (gradient 1 at 0, as candle's `relu`).
pub fn relu(x: &Tensor) -> Result<Tensor> {
    let y = profile::op("relu", &[x], |t| relu_here(&t[0]))?;
    pointwise("relu", &[x], y)
}

fn relu_here(x: &Tensor) -> Result<Tensor> {
    if usable(&[x]) {
        return cpu::activation::leaky_relu(x, 0.0);
    }
    x.relu()
}

/// `x` where `x ≥ 0`, `slope · x` below (gradient 1 at 0); composed:
/// `maximum(x, slope · x)` for slopes in (0, 1).
pub fn leaky_relu(x: &Tensor, slope: f32) -> Result<Tensor> {
    let y = profile::op("leaky_relu", &[x], move |t| leaky_relu_here(&t[0], slope))?;
    pointwise("leaky_relu", &[x], y)
}

fn leaky_relu_here(x: &Tensor, slope: f32) -> Result<Tensor> {
    if usable(&[x]) {
        return cpu::activation::leaky_relu(x, slope);
    }
    x.maximum(&(x * slope as f64)?)
}

impl MlpAct {
    /// The same activation as its own node (the layer-by-layer path).
    pub(crate) fn apply(self, x: &Tensor) -> Result<Tensor> {
        match self {
            MlpAct::Relu => relu(x),
            MlpAct::LeakyRelu(s) => leaky_relu(x, s),
            MlpAct::Gelu => gelu(x),
        }
    }
}

/// Softmax over dimension `dim` (any; other than the last it goes through a transpose).
pub fn softmax<Dim: candle_core::shape::Dim>(x: &Tensor, dim: Dim) -> Result<Tensor> {
    let dim = dim.to_index(x.shape(), "softmax")?;
    let y = profile::op("softmax", &[x], move |t| softmax_here(&t[0], dim))?;
    pointwise("softmax", &[x], y)
}

fn softmax_here(x: &Tensor, dim: usize) -> Result<Tensor> {
    if !usable_with_cuda(&[x]) {
        return candle_nn::ops::softmax(x, dim);
    }
    let last = x.rank() - 1;
    if dim == last {
        cpu::softmax::softmax_last_dim(x)
    } else {
        cpu::softmax::softmax_last_dim(&x.transpose(dim, last)?)?.transpose(dim, last)
    }
}

/// LayerNorm over the last dimension: `x: [.., d]`, `weight`, `bias: [d]` → `[.., d]`.
pub fn layer_norm(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Tensor> {
    let y = profile::op("layer_norm", &[x, weight, bias], move |t| {
        layer_norm_here(&t[0], &t[1], &t[2], eps)
    })?;
    pointwise("layer_norm", &[x, weight, bias], y)
}

fn layer_norm_here(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Tensor> {
    if usable_with_cuda(&[x, weight, bias]) {
        return cpu::layer_norm::layer_norm(x, weight, bias, eps as f32);
    }
    let mean = x.mean_keepdim(D::Minus1)?;
    let centred = x.broadcast_sub(&mean)?;
    let var = centred.sqr()?.mean_keepdim(D::Minus1)?;
    let normed = centred.broadcast_div(&(var + eps)?.sqrt()?)?;
    normed.broadcast_mul(weight)?.broadcast_add(bias)
}

/// `x: [.., d] + bias: [d]`.
pub fn bias_add(x: &Tensor, bias: &Tensor) -> Result<Tensor> {
    let y = profile::op("bias_add", &[x, bias], |t| bias_add_here(&t[0], &t[1]))?;
    pointwise("bias_add", &[x, bias], y)
}

fn bias_add_here(x: &Tensor, bias: &Tensor) -> Result<Tensor> {
    if usable(&[x, bias]) && x.dim(D::Minus1)? == bias.elem_count() && bias.rank() == 1 {
        return cpu::linear::bias_add(x, bias);
    }
    x.broadcast_add(bias)
}

/// `act(x + b)` for `x: [.., d]`, `b: [d]`, `act` none (a bias add) or an MLP activation.
/// One node where the one-node ops apply (f32 on the CPU or a CUDA device); the composed
/// ops otherwise.
pub fn bias_act(x: &Tensor, b: &Tensor, act: Option<MlpAct>) -> Result<Tensor> {
    let y = profile::op("bias_act", &[x, b], move |t| {
        bias_act_here(&t[0], &t[1], act)
    })?;
    pointwise("bias_act", &[x, b], y)
}

fn bias_act_here(x: &Tensor, b: &Tensor, act: Option<MlpAct>) -> Result<Tensor> {
    if usable_with_cuda(&[x, b])
        && b.rank() == 1
        && x.dim(candle_core::D::Minus1)? == b.elem_count()
    {
        return cpu::bias_act::bias_act(x, b, act);
    }
    let z = x.broadcast_add(b)?;
    match act {
        None => Ok(z),
        Some(a) => a.apply(&z),
    }
}

/// Enters a row-wise op of `inputs` giving `y` in the ledger under its kind: its forward
/// pass, and the backward pass of its one-node version where an input carries a gradient
/// (the inputs and `y`'s gradient read, the tracked inputs' gradients written).
fn pointwise(kind: &'static str, inputs: &[&Tensor], y: Tensor) -> Result<Tensor> {
    if !ledger::on() {
        return Ok(y);
    }
    ledger::within(kind, || {
        ledger::op(kind, inputs, &[&y]);
        let tracked: Vec<&Tensor> = inputs.iter().copied().filter(|t| t.track_op()).collect();
        if !tracked.is_empty() {
            let read: u64 = inputs.iter().map(|t| ledger::size(t)).sum::<u64>() + ledger::size(&y);
            let written = tracked.iter().map(|t| ledger::size(t)).sum();
            let what = format!("{kind} backward");
            ledger::in_phase(ledger::Phase::Backward, || {
                ledger::moved(ledger::Moved::Op, &what, read, written)
            });
        }
    });
    Ok(y)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{assert_matches_composed, both, finite_difference_check, max_diff, randn};
    use crate::with_fused;
    use candle_core::Device;

    #[test]
    fn gelu_matches_the_composed_version_and_finite_differences() {
        let x = randn(&[5, 300], 3.0, 11);
        assert_matches_composed(&[x], |t| gelu(&t[0]), 1e-5);
        finite_difference_check(&[randn(&[40], 2.0, 12)], |t| gelu(&t[0]));
        // Extremes: GELU(x) → x for large x, → 0 for very negative x; gradients 1 and 0.
        let x = Tensor::new(&[-1e30f32, -60.0, 0.0, 60.0, 1e30], &Device::Cpu).unwrap();
        let [(y, g), _] = both(&[x], |t| gelu(&t[0]));
        let y: Vec<f32> = y.to_vec1().unwrap();
        assert_eq!(y, vec![-0.0, -0.0, 0.0, 60.0, 1e30]);
        let w: Vec<f32> = randn(&[5], 1.0, 99).to_vec1().unwrap();
        let g: Vec<f32> = g[0].to_vec1().unwrap();
        let want = [0.0, 0.0, 0.5 * w[2], w[3], w[4]];
        for (g, w) in g.iter().zip(want) {
            assert!((g - w).abs() <= 1e-6 * (1.0 + w.abs()), "{g} vs {w}");
        }
        assert!((crate::fastmath::erf(0.5) as f64 - 0.520_499_877_813_046_5).abs() < 4e-7);
    }
    #[test]
    fn relu_and_leaky_relu_match_the_composed_versions_and_finite_differences() {
        // Values kept ≥ 0.05 away from the kink, where finite differences straddle it.
        let away = |t: Tensor| {
            let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            let v: Vec<f32> = v.iter().map(|x| x + 0.05f32.copysign(*x)).collect();
            Tensor::from_vec(v, t.shape(), &Device::Cpu).unwrap()
        };
        let x = [away(randn(&[7, 33], 2.0, 51))];
        assert_matches_composed(&x, |t| relu(&t[0]), 0.0);
        assert_matches_composed(&x, |t| leaky_relu(&t[0], 0.01), 1e-7);
        let small = [away(randn(&[3, 8], 1.0, 52))];
        finite_difference_check(&small, |t| relu(&t[0]));
        finite_difference_check(&small, |t| leaky_relu(&t[0], 0.01));
        // Extremes: huge magnitudes and infinities; NaN passes through (it must reach the
        // non-finite checks rather than become 0).
        let x = Tensor::new(
            &[-1e30f32, 1e30, f32::NEG_INFINITY, f32::INFINITY, f32::NAN],
            &Device::Cpu,
        )
        .unwrap();
        let r: Vec<f32> = relu(&x).unwrap().to_vec1().unwrap();
        assert_eq!(&r[..4], &[0.0, 1e30, 0.0, f32::INFINITY]);
        assert!(r[4].is_nan());
        let l: Vec<f32> = leaky_relu(&x, 0.01).unwrap().to_vec1().unwrap();
        assert_eq!(&l[..4], &[-1e28, 1e30, f32::NEG_INFINITY, f32::INFINITY]);
        assert!(l[4].is_nan());
    }

    #[test]
    fn softmax_matches_the_composed_version_and_finite_differences() {
        let x = randn(&[3, 5, 40], 2.0, 41);
        for dim in [2, 1] {
            assert_matches_composed(std::slice::from_ref(&x), |t| softmax(&t[0], dim), 1e-5);
            finite_difference_check(&[randn(&[2, 3, 6], 1.5, 42)], |t| softmax(&t[0], dim));
        }
        // Extremes: huge logits pick one entry, a constant row is uniform, nothing overflows.
        let x = Tensor::new(
            &[
                [1e30f32, -1e30, 0.0, 5.0],
                [7.0, 7.0, 7.0, 7.0],
                [-1e30, -1e30, -1e30, -2e30],
            ],
            &Device::Cpu,
        )
        .unwrap();
        let [(y, g), _] = both(std::slice::from_ref(&x), |t| softmax(&t[0], 1));
        let y: Vec<Vec<f32>> = y.to_vec2().unwrap();
        assert_eq!(y[0], vec![1.0, 0.0, 0.0, 0.0]);
        assert_eq!(y[1], vec![0.25; 4]);
        assert_eq!(y[2], vec![1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0, 0.0]);
        let g: Vec<f32> = g[0].flatten_all().unwrap().to_vec1().unwrap();
        assert!(g.iter().all(|v| v.is_finite()), "{g:?}");
        assert_matches_composed(&[x], |t| softmax(&t[0], 1), 1e-6);
    }

    fn ln(ts: &[Tensor]) -> Result<Tensor> {
        layer_norm(&ts[0], &ts[1], &ts[2], 1e-5)
    }

    #[test]
    fn layer_norm_matches_the_composed_version_and_finite_differences() {
        let args = [
            randn(&[3, 70, 16], 1.0, 1),
            randn(&[16], 1.0, 2),
            randn(&[16], 1.0, 3),
        ];
        assert_matches_composed(&args, ln, 2e-5);
        let small = [
            randn(&[2, 3, 8], 1.0, 4),
            randn(&[8], 1.0, 5),
            randn(&[8], 1.0, 6),
        ];
        finite_difference_check(&small, ln);
    }

    #[test]
    fn layer_norm_is_finite_on_extreme_and_constant_rows() {
        // Large magnitudes, a constant row (zero variance) and tiny values.
        let mut v = vec![1e6f32, -3e6, 2e6, 5e5];
        v.extend([7.0f32; 4]);
        v.extend([1e-20f32, -1e-20, 0.0, 2e-20]);
        let x = Tensor::from_vec(v, (3, 4), &Device::Cpu).unwrap();
        let args = [x, randn(&[4], 1.0, 7), randn(&[4], 1.0, 8)];
        let [(y, grads), _] = both(&args, ln);
        for t in std::iter::once(&y).chain(&grads) {
            let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            assert!(v.iter().all(|x| x.is_finite()), "{v:?}");
        }
        // The constant row normalises to exactly the bias.
        let row: Vec<f32> = y.get(1).unwrap().to_vec1().unwrap();
        let bias: Vec<f32> = args[2].to_vec1().unwrap();
        assert_eq!(row, bias);
        assert_matches_composed(&args, ln, 1e-3);
    }
    #[test]
    fn non_contiguous_inputs_take_the_same_values() {
        let x = randn(&[6, 8], 1.0, 31).t().unwrap(); // [8, 6], strided
        let g = randn(&[6], 1.0, 32);
        let b = randn(&[6], 1.0, 33);
        let a = with_fused(true, || layer_norm(&x, &g, &b, 1e-5)).unwrap();
        let c = with_fused(false, || layer_norm(&x, &g, &b, 1e-5)).unwrap();
        assert!(max_diff(&a, &c) < 1e-5);
    }

    #[test]
    fn bias_add_matches_the_composed_version_and_finite_differences() {
        let args = [randn(&[4, 9, 33], 1.0, 21), randn(&[33], 1.0, 22)];
        assert_matches_composed(&args, |t| bias_add(&t[0], &t[1]), 1e-4);
        finite_difference_check(&[randn(&[3, 5], 1.0, 23), randn(&[5], 1.0, 24)], |t| {
            bias_add(&t[0], &t[1])
        });
        let big = [
            Tensor::new(&[[3e38f32, -3e38], [1.0, 2.0]], &Device::Cpu).unwrap(),
            randn(&[2], 1.0, 25),
        ];
        assert_matches_composed(&big, |t| bias_add(&t[0], &t[1]), 0.0);
    }

    const ACTS: [Option<MlpAct>; 4] = [
        None,
        Some(MlpAct::Relu),
        Some(MlpAct::LeakyRelu(0.01)),
        Some(MlpAct::Gelu),
    ];

    #[test]
    fn bias_act_matches_the_composed_ops_and_finite_differences() {
        for act in ACTS {
            let args = [randn(&[3, 7, 24], 1.0, 61), randn(&[24], 1.0, 62)];
            assert_matches_composed(&args, |t| bias_act(&t[0], &t[1], act), 1e-5);
            let small = [randn(&[2, 3, 5], 1.0, 63), randn(&[5], 1.0, 64)];
            finite_difference_check(&small, |t| bias_act(&t[0], &t[1], act));
        }
    }

    /// The in-place forward and backward ops give the node's bits, over sizes that end

    #[test]
    fn bias_act_is_finite_on_extreme_inputs() {
        let x = Tensor::new(
            &[[1e30f32, -1e30, 0.0, 3e38], [-3e38, 1e-30, -1e-30, 7.0]],
            &Device::Cpu,
        )
        .unwrap();
        let b = Tensor::new(&[0.5f32, -0.5, 0.0, 1.0], &Device::Cpu).unwrap();
        for act in ACTS {
            let [(y, grads), _] = both(&[x.clone(), b.clone()], |t| bias_act(&t[0], &t[1], act));
            for t in std::iter::once(&y).chain(&grads) {
                let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
                assert!(v.iter().all(|x| x.is_finite()), "{act:?}: {v:?}");
            }
        }
    }
}
