use crate::*;
use candle_core::{CpuStorage, CustomOp1, CustomOp2, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// 1/√2
const FRAC_1_SQRT_2: f32 = std::f32::consts::FRAC_1_SQRT_2;
/// 1/√(2π)
const INV_SQRT_2PI: f32 = 0.398_942_3;

// In f32 with the vectorising `fastmath` kernels (was f64 libm: ~9 % of a train step).
#[inline(always)]
fn gelu_f(x: f32) -> f32 {
    0.5 * x * (1.0 + fastmath::erf(x * FRAC_1_SQRT_2))
}

#[inline(always)]
fn gelu_grad_f(x: f32) -> f32 {
    let cdf = 0.5 * (1.0 + fastmath::erf(x * FRAC_1_SQRT_2));
    cdf + x * INV_SQRT_2PI * fastmath::exp(-0.5 * x * x)
}

/// Elements per parallel task of the elementwise ops.
const ELEMENTS_PER_TASK: usize = 8192;

/// `out = kernel(x)`, chunk by chunk in parallel (`kernel` is one of the slice kernels).
pub(crate) fn par_elementwise(x: &[f32], kernel: impl Fn(&mut [f32], &[f32]) + Sync) -> Vec<f32> {
    const E: usize = ELEMENTS_PER_TASK;
    buffer::par_filled(x.len(), E, |i, o| kernel(o, &x[i * E..][..o.len()]))
}

/// `dx = kernel(x, dy)`, chunk by chunk in parallel: an elementwise op's backward.
pub(crate) fn par_elementwise_grad(
    x: &[f32],
    dy: &[f32],
    kernel: impl Fn(&mut [f32], &[f32], &[f32]) + Sync,
) -> Vec<f32> {
    const E: usize = ELEMENTS_PER_TASK;
    buffer::par_filled(x.len(), E, |i, o| {
        let at = i * E..i * E + o.len();
        kernel(o, &x[at.clone()], &dy[at])
    })
}

/// `kernel` in [`par_elementwise`]'s chunks where the input or the output is not f32:
/// each chunk's input made by `load` (from the chunk's first index), its output handed
/// to `store`.
pub(crate) fn par_elementwise_with<T: Send>(
    out: &mut [T],
    load: impl Fn(usize, &mut [f32]) + Sync,
    kernel: impl Fn(&mut [f32], &[f32]) + Sync,
    store: impl Fn(&[f32], &mut [T]) + Sync,
) {
    out.par_chunks_mut(ELEMENTS_PER_TASK)
        .enumerate()
        .for_each(|(i, o)| {
            let mut x = vec![0f32; o.len()];
            load(i * ELEMENTS_PER_TASK, &mut x);
            let mut y = vec![0f32; o.len()];
            kernel(&mut y, &x);
            store(&y, o);
        });
}

/// `kernel(x, dy)` in [`par_elementwise_grad`]'s chunks where the operands are not f32:
/// each chunk's `x` and `dy` made by `load` (from the chunk's first index), the result
/// written into `out`.
pub(crate) fn par_elementwise_grad_with(
    out: &mut [f32],
    load: impl Fn(usize, &mut [f32], &mut [f32]) + Sync,
    kernel: impl Fn(&mut [f32], &[f32], &[f32]) + Sync,
) {
    out.par_chunks_mut(ELEMENTS_PER_TASK)
        .enumerate()
        .for_each(|(i, o)| {
            let (mut x, mut dy) = (vec![0f32; o.len()], vec![0f32; o.len()]);
            load(i * ELEMENTS_PER_TASK, &mut x, &mut dy);
            kernel(o, &x, &dy);
        });
}

/// [`par_elementwise`] written over `x`, in the same chunks (each copied once, so that
/// the kernel reads and writes distinct slices): the same bits, no second buffer.
pub(crate) fn par_elementwise_in_place(x: &mut [f32], kernel: impl Fn(&mut [f32], &[f32]) + Sync) {
    x.par_chunks_mut(ELEMENTS_PER_TASK).for_each(|o| {
        let x = o.to_vec();
        kernel(o, &x)
    });
}

/// [`par_elementwise_grad`] written over `x`, in the same chunks.
pub(crate) fn par_elementwise_grad_in_place(
    x: &mut [f32],
    dy: &[f32],
    kernel: impl Fn(&mut [f32], &[f32], &[f32]) + Sync,
) {
    x.par_chunks_mut(ELEMENTS_PER_TASK)
        .zip(dy.par_chunks(ELEMENTS_PER_TASK))
        .for_each(|(o, dy)| {
            let x = o.to_vec();
            kernel(o, &x, dy)
        });
}

fastmath::kernel! {
    /// `out[i] = GELU(x[i])`.
    pub fn gelu_slice(out: &mut [f32], x: &[f32]) {
        for (o, &x) in out.iter_mut().zip(x) {
            *o = gelu_f(x);
        }
    }
}

fastmath::kernel! {
    /// `out[i] = dy[i] · GELU'(x[i])`.
    pub fn gelu_grad_slice(out: &mut [f32], x: &[f32], dy: &[f32]) {
        for ((o, &x), &dy) in out.iter_mut().zip(x).zip(dy) {
            *o = dy * gelu_grad_f(x);
        }
    }
}

struct GeluOp;

impl CustomOp1 for GeluOp {
    fn name(&self) -> &'static str {
        "osrt-gelu-erf"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s, l, "gelu")?;
        let out = par_elementwise(x, gelu_slice);
        Ok((CpuStorage::F32(out), l.shape().clone()))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(x.apply_op2_no_bwd(&grad.contiguous()?, &GeluBwd)?))
    }
}

/// `dx = dy · GELU'(x)`.
struct GeluBwd;

impl CustomOp2 for GeluBwd {
    fn name(&self) -> &'static str {
        "osrt-gelu-erf-bwd"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1, "gelu backward x")?;
        let dy = f32_slice(s2, l2, "gelu backward gradient")?;
        let out = par_elementwise_grad(x, dy, gelu_grad_slice);
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }
}

/// erf-based GELU, elementwise.
pub fn gelu(x: &Tensor) -> Result<Tensor> {
    crate::profile::op("gelu", &[x], |t| gelu_here(&t[0]))
}

fn gelu_here(x: &Tensor) -> Result<Tensor> {
    if usable(&[x]) {
        return x.contiguous()?.apply_op1(GeluOp);
    }
    x.gelu_erf()
}

// ---------------------------------------------------------------- ReLU / leaky ReLU

fastmath::kernel! {
    /// `out[i] = x[i]` where `x[i] ≥ 0` (and NaN), `slope · x[i]` below 0 (0 for
    /// slope 0, also at −∞).
    pub fn leaky_relu_slice(out: &mut [f32], x: &[f32], slope: f32) {
        for (o, &x) in out.iter_mut().zip(x) {
            let neg = if slope == 0.0 { 0.0 } else { slope * x };
            *o = if x < 0.0 { neg } else { x };
        }
    }
}

fastmath::kernel! {
    /// `out[i] = dy[i] · (slope if x[i] < 0 else 1)`.
    pub fn leaky_relu_grad_slice(out: &mut [f32], x: &[f32], dy: &[f32], slope: f32) {
        for ((o, &x), &dy) in out.iter_mut().zip(x).zip(dy) {
            *o = if x < 0.0 { dy * slope } else { dy };
        }
    }
}

/// ReLU (slope 0) or leaky ReLU as one node each way; candle's leaky ReLU is
/// `maximum(x, s·x)`, whose backward takes two masks, a division and an add.
struct LeakyReluOp {
    slope: f32,
}

impl CustomOp1 for LeakyReluOp {
    fn name(&self) -> &'static str {
        "osrt-leaky-relu"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s, l, "leaky relu")?;
        let out = par_elementwise(x, |o, x| leaky_relu_slice(o, x, self.slope));
        Ok((CpuStorage::F32(out), l.shape().clone()))
    }

    fn bwd(&self, x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let bwd = LeakyReluBwd { slope: self.slope };
        Ok(Some(x.apply_op2_no_bwd(&grad.contiguous()?, &bwd)?))
    }
}

struct LeakyReluBwd {
    slope: f32,
}

impl CustomOp2 for LeakyReluBwd {
    fn name(&self) -> &'static str {
        "osrt-leaky-relu-bwd"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1, "leaky relu backward x")?;
        let dy = f32_slice(s2, l2, "leaky relu backward gradient")?;
        let out = par_elementwise_grad(x, dy, |o, x, dy| {
            leaky_relu_grad_slice(o, x, dy, self.slope)
        });
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }
}

/// `max(x, 0)`, elementwise (gradient 1 at 0, as candle's `relu`).
pub fn relu(x: &Tensor) -> Result<Tensor> {
    crate::profile::op("relu", &[x], |t| relu_here(&t[0]))
}

fn relu_here(x: &Tensor) -> Result<Tensor> {
    if usable(&[x]) {
        return x.contiguous()?.apply_op1(LeakyReluOp { slope: 0.0 });
    }
    x.relu()
}

/// `x` where `x ≥ 0`, `slope · x` below (gradient 1 at 0); composed:
/// `maximum(x, slope · x)` for slopes in (0, 1).
pub fn leaky_relu(x: &Tensor, slope: f32) -> Result<Tensor> {
    crate::profile::op("leaky_relu", &[x], move |t| leaky_relu_here(&t[0], slope))
}

fn leaky_relu_here(x: &Tensor, slope: f32) -> Result<Tensor> {
    if usable(&[x]) {
        return x.contiguous()?.apply_op1(LeakyReluOp { slope });
    }
    x.maximum(&(x * slope as f64)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::*;
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
}
