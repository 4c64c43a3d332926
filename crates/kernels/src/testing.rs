//! Helpers of the kernels' tests: seeded inputs, fused-vs-composed comparisons, f64
//! finite differences, a second backward pass.

use crate::with_fused;
use candle_core::{Device, Result, Tensor, Var};
use rand::{Rng, SeedableRng};

pub(crate) fn randn(shape: &[usize], scale: f32, seed: u64) -> Tensor {
    let n: usize = shape.iter().product();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    // Box–Muller, pairwise: the model's initialiser draws the same way.
    let mut v = Vec::with_capacity(n + 1);
    while v.len() < n {
        let u1: f64 = rng.random::<f64>().max(1e-300);
        let u2: f64 = rng.random::<f64>();
        let (r, t) = ((-2.0 * u1.ln()).sqrt(), std::f64::consts::TAU * u2);
        v.extend([(r * t.cos()) as f32 * scale, (r * t.sin()) as f32 * scale]);
    }
    v.truncate(n);
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}

/// The bits of `t`'s values widened to f32 (any float type), flattened.
pub(crate) fn f32_bits(t: &Tensor) -> Vec<u32> {
    let v: Vec<f32> = t
        .to_dtype(candle_core::DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    v.iter().map(|x| x.to_bits()).collect()
}

pub(crate) fn max_abs(a: &Tensor) -> f32 {
    a.abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar()
        .unwrap()
}

pub(crate) fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
    (a - b)
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

/// Value and gradients of `Σ f(args) · w` (w fixed random), fused and composed.
pub(crate) fn both(
    args: &[Tensor],
    f: impl Fn(&[Tensor]) -> Result<Tensor>,
) -> [(Tensor, Vec<Tensor>); 2] {
    [true, false].map(|on| {
        with_fused(on, || {
            let vars: Vec<Var> = args.iter().map(|a| Var::from_tensor(a).unwrap()).collect();
            let ts: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();
            let y = f(&ts).unwrap();
            let w = randn(y.dims(), 1.0, 99);
            let loss = (&y * &w).unwrap().sum_all().unwrap();
            let g = loss.backward().unwrap();
            let grads = vars
                .iter()
                .map(|v| g.get(v.as_tensor()).unwrap().clone())
                .collect();
            (y, grads)
        })
    })
}

pub(crate) fn assert_matches_composed(
    args: &[Tensor],
    f: impl Fn(&[Tensor]) -> Result<Tensor>,
    tol: f32,
) {
    let [(yf, gf), (yc, gc)] = both(args, f);
    assert!(
        max_diff(&yf, &yc) <= tol,
        "forward differs by {}",
        max_diff(&yf, &yc)
    );
    for (i, (a, b)) in gf.iter().zip(&gc).enumerate() {
        let d = max_diff(a, b);
        assert!(d <= tol, "gradient {i} differs by {d}");
        assert!(
            a.flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
                .iter()
                .all(|v| v.is_finite())
        );
    }
}

/// Central finite differences of `Σ f(args) · w`, computed in f64 (where `f` takes the
/// composed path: the same function), against the fused backward in f32.
pub(crate) fn finite_difference_check(args: &[Tensor], f: impl Fn(&[Tensor]) -> Result<Tensor>) {
    let [(y, grads), _] = both(args, &f);
    let f64_ = candle_core::DType::F64;
    let w64 = randn(y.dims(), 1.0, 99).to_dtype(f64_).unwrap();
    let args64: Vec<Tensor> = args.iter().map(|a| a.to_dtype(f64_).unwrap()).collect();
    let h = 1e-5;
    for (a, grad) in grads.iter().enumerate() {
        let base: Vec<f64> = args64[a].flatten_all().unwrap().to_vec1().unwrap();
        let g: Vec<f32> = grad.flatten_all().unwrap().to_vec1().unwrap();
        for i in (0..base.len()).step_by((base.len() / 12).max(1)) {
            let eval = |delta: f64| -> f64 {
                let mut v = base.clone();
                v[i] += delta;
                let mut xs = args64.clone();
                xs[a] = Tensor::from_vec(v, args64[a].shape(), &Device::Cpu).unwrap();
                (f(&xs).unwrap() * &w64)
                    .unwrap()
                    .sum_all()
                    .unwrap()
                    .to_scalar::<f64>()
                    .unwrap()
            };
            let num = (eval(h) - eval(-h)) / (2.0 * h);
            let err = (num - g[i] as f64).abs();
            assert!(
                err <= 1e-3 * (1.0 + num.abs()),
                "arg {a} element {i}: finite difference {num}, backward {}",
                g[i]
            );
        }
    }
}

/// A second backward pass through the same graph of `Σ f(args)²` (built with the fused
/// ops, every argument a variable) gives the first one's gradients: a node whose first
/// backward pass took what it kept recomputes it.
pub(crate) fn assert_second_backward_agrees(
    args: &[Tensor],
    f: impl Fn(&[Tensor]) -> Result<Tensor>,
) {
    let vars: Vec<Var> = args.iter().map(|a| Var::from_tensor(a).unwrap()).collect();
    let ts: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();
    let loss = with_fused(true, || f(&ts))
        .unwrap()
        .sqr()
        .unwrap()
        .sum_all()
        .unwrap();
    let (g1, g2) = (loss.backward().unwrap(), loss.backward().unwrap());
    for (i, v) in vars.iter().enumerate() {
        let flat = |g: &candle_core::backprop::GradStore| -> Vec<f32> {
            let t = g.get(v.as_tensor()).unwrap();
            t.flatten_all().unwrap().to_vec1().unwrap()
        };
        assert_eq!(flat(&g1), flat(&g2), "argument {i}");
    }
}
