//! The activations' CPU kernels: erf-GELU, ReLU and leaky ReLU over slices (vectorised
//! through `fastmath`), the parallel elementwise loops that run them, the MLP activation
//! [`MlpAct`] over buffers, and the one-node GELU and (leaky) ReLU with their backward
//! passes.

use super::{buffer, f32_slice, fastmath};
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

/// erf-based GELU as one node (f32 on the CPU).
pub(crate) fn gelu(x: &Tensor) -> Result<Tensor> {
    x.contiguous()?.apply_op1(GeluOp)
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

/// Leaky ReLU (ReLU at slope 0) as one node (f32 on the CPU).
pub(crate) fn leaky_relu(x: &Tensor, slope: f32) -> Result<Tensor> {
    x.contiguous()?.apply_op1(LeakyReluOp { slope })
}

// ---------------------------------------------------------------- the MLP activation

/// The activation between layers (its node, `MlpAct::apply`, is chosen in
/// `crate::dispatch::pointwise`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MlpAct {
    Relu,
    /// Leaky ReLU with this negative slope.
    LeakyRelu(f32),
    /// erf-based GELU.
    Gelu,
}

impl MlpAct {
    pub(crate) fn forward(self, z: &[f32]) -> Vec<f32> {
        match self {
            MlpAct::Relu => par_elementwise(z, |o, x| leaky_relu_slice(o, x, 0.0)),
            MlpAct::LeakyRelu(s) => par_elementwise(z, |o, x| leaky_relu_slice(o, x, s)),
            MlpAct::Gelu => par_elementwise(z, gelu_slice),
        }
    }

    /// `dy · act'(z)`.
    pub(crate) fn backward(self, z: &[f32], dy: &[f32]) -> Vec<f32> {
        match self {
            MlpAct::Relu => {
                par_elementwise_grad(z, dy, |o, x, d| leaky_relu_grad_slice(o, x, d, 0.0))
            }
            MlpAct::LeakyRelu(s) => {
                par_elementwise_grad(z, dy, |o, x, d| leaky_relu_grad_slice(o, x, d, s))
            }
            MlpAct::Gelu => par_elementwise_grad(z, dy, gelu_grad_slice),
        }
    }

    /// [`MlpAct::forward`] in `par_elementwise_with`'s chunks: `load` makes each chunk's
    /// input, `store` takes its output.
    pub(crate) fn forward_with<T: Send>(
        act: Option<Self>,
        out: &mut [T],
        load: impl Fn(usize, &mut [f32]) + Sync,
        store: impl Fn(&[f32], &mut [T]) + Sync,
    ) {
        match act {
            None => par_elementwise_with(out, load, |o, x| o.copy_from_slice(x), store),
            Some(MlpAct::Relu) => {
                par_elementwise_with(out, load, |o, x| leaky_relu_slice(o, x, 0.0), store)
            }
            Some(MlpAct::LeakyRelu(s)) => {
                par_elementwise_with(out, load, |o, x| leaky_relu_slice(o, x, s), store)
            }
            Some(MlpAct::Gelu) => par_elementwise_with(out, load, gelu_slice, store),
        }
    }

    /// [`MlpAct::forward`] written over `z`.
    pub(crate) fn forward_in_place(self, z: &mut [f32]) {
        match self {
            MlpAct::Relu => par_elementwise_in_place(z, |o, x| leaky_relu_slice(o, x, 0.0)),
            MlpAct::LeakyRelu(s) => par_elementwise_in_place(z, |o, x| leaky_relu_slice(o, x, s)),
            MlpAct::Gelu => par_elementwise_in_place(z, gelu_slice),
        }
    }

    /// [`MlpAct::backward`] written over `z`.
    pub(crate) fn backward_in_place(self, z: &mut [f32], dy: &[f32]) {
        match self {
            MlpAct::Relu => {
                par_elementwise_grad_in_place(z, dy, |o, x, d| leaky_relu_grad_slice(o, x, d, 0.0))
            }
            MlpAct::LeakyRelu(s) => {
                par_elementwise_grad_in_place(z, dy, |o, x, d| leaky_relu_grad_slice(o, x, d, s))
            }
            MlpAct::Gelu => par_elementwise_grad_in_place(z, dy, gelu_grad_slice),
        }
    }

    /// [`MlpAct::backward`] in `par_elementwise_grad_with`'s chunks: `load` makes each
    /// chunk's `z` and `dy`.
    pub(crate) fn backward_with(
        self,
        out: &mut [f32],
        load: impl Fn(usize, &mut [f32], &mut [f32]) + Sync,
    ) {
        match self {
            MlpAct::Relu => {
                par_elementwise_grad_with(out, load, |o, x, d| leaky_relu_grad_slice(o, x, d, 0.0))
            }
            MlpAct::LeakyRelu(s) => {
                par_elementwise_grad_with(out, load, |o, x, d| leaky_relu_grad_slice(o, x, d, s))
            }
            MlpAct::Gelu => par_elementwise_grad_with(out, load, gelu_grad_slice),
        }
    }
}
