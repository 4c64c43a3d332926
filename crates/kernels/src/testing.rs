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

/// Value and gradients of `Σ f(args) · w` (w fixed random) with the thread's switches.
fn value_and_grads(
    args: &[Tensor],
    f: &impl Fn(&[Tensor]) -> Result<Tensor>,
) -> (Tensor, Vec<Tensor>) {
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
}

/// Value and gradients of `Σ f(args) · w` (w fixed random), fused and composed.
pub(crate) fn both(
    args: &[Tensor],
    f: impl Fn(&[Tensor]) -> Result<Tensor>,
) -> [(Tensor, Vec<Tensor>); 2] {
    [true, false].map(|on| with_fused(on, || value_and_grads(args, &f)))
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

/// Central finite differences of `Σ f(args) · w` in f64 (`w` the checks' fixed weights,
/// of the output's `dims`; `f` takes the composed path there: the same function) with
/// respect to argument `a`, at about 12 of its elements: `(element, difference)`.
fn sampled_differences(
    args: &[Tensor],
    f: &impl Fn(&[Tensor]) -> Result<Tensor>,
    dims: &[usize],
    a: usize,
) -> Vec<(usize, f64)> {
    let f64_ = candle_core::DType::F64;
    let w64 = randn(dims, 1.0, 99).to_dtype(f64_).unwrap();
    let args64: Vec<Tensor> = args.iter().map(|a| a.to_dtype(f64_).unwrap()).collect();
    let base: Vec<f64> = args64[a].flatten_all().unwrap().to_vec1().unwrap();
    let h = 1e-5;
    (0..base.len())
        .step_by((base.len() / 12).max(1))
        .map(|i| {
            let eval = |delta: f64| -> f64 {
                let mut v = base.clone();
                v[i] += delta;
                let mut xs = args64.clone();
                xs[a] = Tensor::from_vec(v, args64[a].shape(), &Device::Cpu).unwrap();
                let y = with_fused(false, || f(&xs)).unwrap();
                (y * &w64)
                    .unwrap()
                    .sum_all()
                    .unwrap()
                    .to_scalar::<f64>()
                    .unwrap()
            };
            (i, (eval(h) - eval(-h)) / (2.0 * h))
        })
        .collect()
}

/// Central finite differences of `Σ f(args) · w`, computed in f64 (where `f` takes the
/// composed path: the same function), against the fused backward in f32.
pub(crate) fn finite_difference_check(args: &[Tensor], f: impl Fn(&[Tensor]) -> Result<Tensor>) {
    let [(y, grads), _] = both(args, &f);
    for (a, grad) in grads.iter().enumerate() {
        let g: Vec<f32> = grad.flatten_all().unwrap().to_vec1().unwrap();
        for (i, num) in sampled_differences(args, &f, y.dims(), a) {
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

/// `‖a − b‖ / ‖b‖` over flattened values (`‖a − b‖` where `b` is all zeros).
pub(crate) fn rel_l2(a: &Tensor, b: &Tensor) -> f64 {
    let (d, n) = (l2(&(a - b).unwrap()), l2(b));
    if n == 0.0 { d } else { d / n }
}

fn l2(t: &Tensor) -> f64 {
    let v: Vec<f64> = t
        .to_dtype(candle_core::DType::F64)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

/// The fused ops in bf16 against their f32 twins, for `Σ f(args) · w`: the value within
/// `tol` relative L2 of the f32 one, all gradients finite. At unit scale (`unit`) each
/// gradient within `4·tol` relative L2 of its f32 twin, the values' bits differ where the
/// CPU has bf16 products (the bf16 products ran), and each gradient within `4·tol` of f64
/// central finite differences of the same function (the composed path in f64, sampled
/// elements). At extreme scales a gradient may be small by cancellation (a tiny input's
/// LayerNorm rows are nearly its bias, so attention over them is nearly uniform): each is
/// within `4·tol` of the largest f32 gradient's norm, and no finite difference is taken
/// (a step that moves the tiny input moves the output below f64's resolution).
pub(crate) fn bf16_twin_check(
    what: &str,
    args: &[Tensor],
    f: impl Fn(&[Tensor]) -> Result<Tensor>,
    tol: f64,
    unit: bool,
) {
    use crate::{Precision, with_precision};
    let fused = |p: Precision| with_precision(p, || with_fused(true, || value_and_grads(args, &f)));
    let ((y32, g32), (y16, g16)) = (fused(Precision::F32), fused(Precision::Bf16));
    let finite = |t: &Tensor| f32_bits(t).iter().all(|&b| f32::from_bits(b).is_finite());
    assert!(finite(&y16), "{what}: bf16 values not finite");
    let e = rel_l2(&y16, &y32);
    assert!(
        e <= tol,
        "{what}: bf16 values {e} from f32's (tolerance {tol})"
    );
    if unit && crate::cpu_bf16_products().is_some() {
        assert_ne!(
            f32_bits(&y16),
            f32_bits(&y32),
            "{what}: the bf16 products did not run"
        );
    }
    let largest = g32.iter().map(l2).fold(0f64, f64::max);
    for (i, (a, b)) in g16.iter().zip(&g32).enumerate() {
        assert!(finite(a), "{what}: bf16 gradient {i} not finite");
        let e = match unit {
            true => rel_l2(a, b),
            false => l2(&(a - b).unwrap()) / largest.max(f64::MIN_POSITIVE),
        };
        assert!(e <= 4.0 * tol, "{what}: bf16 gradient {i}: {e} from f32's");
    }
    if !unit {
        return;
    }
    // Finite differences of the f64 function, sampled as in `finite_difference_check`.
    for (a, grad) in g16.iter().enumerate() {
        let g: Vec<f32> = grad.flatten_all().unwrap().to_vec1().unwrap();
        let (got, num): (Vec<f64>, Vec<f64>) = sampled_differences(args, &f, y32.dims(), a)
            .into_iter()
            .map(|(i, num)| (g[i] as f64, num))
            .unzip();
        let t = |v: Vec<f64>| Tensor::new(v, &Device::Cpu).unwrap();
        let e = rel_l2(&t(got), &t(num));
        assert!(
            e <= 4.0 * tol,
            "{what}: bf16 gradient {a}: {e} from finite differences"
        );
    }
}
