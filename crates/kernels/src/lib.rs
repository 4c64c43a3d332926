//! The kernels under the model: fused CPU ops with hand-written backward passes: LayerNorm, softmax, erf-GELU, ReLU,
//! the bias add and the whole of a linear layer, a convolution, a whole MLP (`mlp.rs`),
//! the core of multi-head attention (`attention.rs`) and a whole transformer block
//! (`block.rs`); their matrix products go through `gemm.rs`.
//!
//! Why: candle 0.11 composes these from elementwise and broadcast ops, and its backward
//! pass is slow exactly there (a broadcast's gradient is a `sum_keepdim` over leading
//! dims, done as a scalar div/mod loop; every graph node also costs a zero tensor and an
//! add in gradient accumulation). One node per op with a row-wise kernel removes both.
//! Each op computes the same function as the composed version (candle's ops:
//! `candle_nn::ops::softmax`, `Tensor::gelu_erf`, `broadcast_add`, …); each op's tests,
//! beside it, check values and gradients against those and against f64 finite
//! differences, and extreme inputs.
//!
//! One switch chooses between the fused and the composed ops: [`Kernels`], a job-config
//! value applied per thread with [`with_kernels`]. The kernels need f32 on the CPU;
//! anything else takes the composed path whatever the switch says, except LayerNorm and
//! softmax, which have CUDA kernels too (`cuda.rs`, in a `cuda` build): on a GPU they
//! are the only one-node ops, and the rest of the graph is candle's.

mod activation;
mod attention;
mod attention_node;
mod bias_act;
mod block;
mod buffer;
mod conv;
mod conv_node;
#[cfg(feature = "cuda")]
pub mod cuda;
pub mod cut;
pub mod device_check;
pub mod device_kernels;
#[cfg(test)]
mod emulated;
pub mod fastmath;
mod gemm;
mod handover;
mod layer_norm;
mod linear;
mod links;
mod matmul_node;
mod mix;
mod mlp;
mod mlp_node;
pub mod profile;
mod softmax;
#[cfg(test)]
mod testing;

pub use activation::{gelu, leaky_relu, relu};
pub use attention::{attention, attention_composed};
pub use bias_act::bias_act;
pub use block::{BlockParams, block};
pub use conv::{conv2d_nhwc, conv2d_relu_nhwc};
pub use cut::{Cuts, cut, recompute, with_cuts};
pub use layer_norm::layer_norm;
pub use linear::{bias_add, linear, linear_low};
pub use mix::slot_mix;
pub use mlp::{MlpAct, MlpLayer, mlp, mlp_cat, mlp_layer_by_layer};
pub use softmax::softmax;

// Row kernels the one-node ops share.
use activation::{
    gelu_grad_slice, gelu_slice, leaky_relu_grad_slice, leaky_relu_slice, par_elementwise,
    par_elementwise_grad, par_elementwise_grad_in_place, par_elementwise_grad_with,
    par_elementwise_in_place, par_elementwise_with,
};
use layer_norm::{LayerNormBwd, LayerNormOp};
use linear::{ColumnSum, add_bias_rows, matmul_xwt, rows_layout, weight_grad, with_last_dim};
use softmax::{softmax_row, softmax_row_grad};

use candle_core::{CpuStorage, Layout, Result, Tensor};
use std::cell::Cell;
use std::sync::Mutex;

thread_local! {
    static KERNELS: Cell<Kernels> = const { Cell::new(Kernels::Fused) };
    static PRECISION: Cell<Precision> = const { Cell::new(Precision::F32) };
}

/// The number format of the matrix products (linear layers, convolutions, attention) on
/// the composed path: `bf16` rounds both operands to bfloat16 and the product comes back
/// as f32 (cuBLAS accumulates in f32), as PyTorch's autocast does; LayerNorm, softmax,
/// the loss, gradients' sums over the batch and the optimiser stay in f32. The fused CPU
/// kernels are f32 only.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    #[default]
    F32,
    Bf16,
}

impl std::fmt::Display for Precision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::F32 => "f32",
            Self::Bf16 => "bf16",
        })
    }
}

impl std::str::FromStr for Precision {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "f32" => Ok(Self::F32),
            "bf16" => Ok(Self::Bf16),
            other => Err(format!("unknown precision `{other}`: expected f32 or bf16")),
        }
    }
}

/// The matrix products' precision of graphs built on this thread.
pub fn precision() -> Precision {
    PRECISION.with(|p| p.get())
}

/// Runs `f` with the matrix products in `p` on this thread.
pub fn with_precision<T>(p: Precision, f: impl FnOnce() -> T) -> T {
    let prev = PRECISION.with(|c| c.replace(p));
    let out = f();
    PRECISION.with(|c| c.set(prev));
    out
}

/// `a · b` (candle's batched matmul) in this thread's [`precision`]; with the fused ops
/// on, as one node that keeps no bf16 copies and whose gradients hold no graph
/// (`matmul_node.rs`).
pub fn matmul(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    profile::op("matmul", &[a, b], |t| {
        let f32s = t.iter().all(|t| t.dtype() == candle_core::DType::F32);
        if enabled() && (f32s || stores_low(&[&t[0], &t[1]])) {
            let bf16 = precision() == Precision::Bf16;
            return matmul_node::matmul_node(&t[0], &t[1], bf16);
        }
        in_precision(&[&t[0], &t[1]], |t| t[0].matmul(&t[1]))
    })
}

/// [`matmul`], the product stored as the bf16 product returns it where the products run
/// in bf16 on the device graph (else as [`matmul`]): for a product whose one reader is
/// another bf16 product or an op that reads it in f32, where storing it in f32 would
/// only double the bytes the graph keeps (autocast stores a product in bf16 too). The
/// values and gradients are [`matmul`]'s (`matmul_node.rs`).
pub fn matmul_low(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    profile::op("matmul", &[a, b], |t| {
        if stores_low(&[&t[0], &t[1]]) {
            return matmul_node::matmul_node_low(&t[0], &t[1]);
        }
        matmul(&t[0], &t[1])
    })
}

/// Whether products of `ts` run on bf16 operands with the device graph's nodes, which
/// also take (and may store) bf16 tensors ([`matmul_low`]).
pub(crate) fn stores_low(ts: &[&Tensor]) -> bool {
    use candle_core::DType;
    enabled()
        && precision() == Precision::Bf16
        && ts.iter().all(|t| {
            matches!(t.dtype(), DType::F32 | DType::BF16)
                && t.rank() >= 1
                && device_graph(t)
                && (t.device().is_cpu() || (cfg!(feature = "cuda") && t.device().is_cuda()))
        })
}

/// Runs a product-like op on its f32 operands rounded to bf16 when the thread's precision
/// asks for it (the result back in f32; the casts carry the gradient back to f32).
pub(crate) fn in_precision(
    ts: &[&Tensor],
    op: impl FnOnce(&[Tensor]) -> Result<Tensor>,
) -> Result<Tensor> {
    use candle_core::DType;
    let cast = precision() == Precision::Bf16 && ts.iter().all(|t| t.dtype() == DType::F32);
    if !cast {
        let owned: Vec<Tensor> = ts.iter().map(|t| (*t).clone()).collect();
        return op(&owned);
    }
    let low = ts
        .iter()
        .map(|t| t.to_dtype(DType::BF16))
        .collect::<Result<Vec<_>>>()?;
    op(&low)?.to_dtype(DType::F32)
}

/// Which ops graphs are built from: `fused` (this crate's one-node kernels where they
/// apply; the default), `composed` (candle's own ops only) or `device` (the graph a GPU
/// builds with `fused`, on any device). The three compute the same functions; fused is
/// the fast path on CPUs, composed the reference. On a GPU, fused means the ops with CUDA
/// kernels (LayerNorm, softmax, bias with activation) and the nodes built from tensor ops
/// (attention, convolution, MLP, bf16 products) as one node each, candle's ops elsewhere;
/// `device` builds that same graph on the CPU, where its memory can be counted and its
/// training compared with the fused CPU ops'.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Kernels {
    #[default]
    Fused,
    Composed,
    Device,
}

impl std::fmt::Display for Kernels {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Fused => "fused",
            Self::Composed => "composed",
            Self::Device => "device",
        })
    }
}

impl std::str::FromStr for Kernels {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "fused" => Ok(Self::Fused),
            "composed" => Ok(Self::Composed),
            "device" => Ok(Self::Device),
            other => Err(format!(
                "unknown kernels `{other}`: expected fused, composed or device"
            )),
        }
    }
}

/// The kernels graphs built on this thread use.
pub fn kernels() -> Kernels {
    KERNELS.with(|k| k.get())
}

/// Whether graphs built on this thread use one-node ops (`fused` or `device`).
pub fn enabled() -> bool {
    kernels() != Kernels::Composed
}

/// Whether `t`'s ops take the device graph's nodes: on a GPU, or anywhere with
/// [`Kernels::Device`].
pub(crate) fn device_graph(t: &Tensor) -> bool {
    !t.device().is_cpu() || kernels() == Kernels::Device
}

/// Runs `f` with graphs on this thread built from `k`.
pub fn with_kernels<T>(k: Kernels, f: impl FnOnce() -> T) -> T {
    let prev = KERNELS.with(|c| c.replace(k));
    let out = f();
    KERNELS.with(|c| c.set(prev));
    out
}

/// [`with_kernels`] with the fused ops on or off (comparisons, tests).
pub fn with_fused<T>(on: bool, f: impl FnOnce() -> T) -> T {
    with_kernels(
        if on {
            Kernels::Fused
        } else {
            Kernels::Composed
        },
        f,
    )
}

/// Runs `f` on candle's CPU thread pool (`Device::with_context`), with this thread's
/// fused-ops setting carried along (it is thread-local). Every parallel section inside —
/// gemm, candle's elementwise maps, the fused ops — then runs on the pool's own threads;
/// called from outside a pool, each of the thousands of sections in a step is handed
/// across threads and waited for (the step took 1.04–1.12× as long at 1 thread in
/// interleaved runs: docs/performance.md).
pub fn on_device_pool<T: Send>(device: &candle_core::Device, f: impl FnOnce() -> T + Send) -> T {
    let (k, p, r) = (kernels(), precision(), profile::current());
    device.with_context(|| with_kernels(k, || with_precision(p, || profile::recording(r, f))))
}

/// What a one-node op's forward pass keeps for its backward pass: put there only when a
/// gradient can follow, and taken (not cloned) by the backward pass, so a second backward
/// through the same graph finds it empty and recomputes it.
struct Kept<T>(Mutex<Option<T>>);

impl<T> Kept<T> {
    fn new(v: Option<T>) -> Self {
        Self(Mutex::new(v))
    }

    fn put(&self, v: T) {
        *self.0.lock().unwrap_or_else(|e| e.into_inner()) = Some(v);
    }

    fn take(&self) -> Option<T> {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).take()
    }
}

/// Rows per parallel task: small tensors stay on one thread.
const ROWS_PER_TASK: usize = 64;

/// The contiguous f32 values behind a CPU tensor's storage and layout (kernels of other crates
/// read their operands through it).
pub fn f32_slice<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> Result<&'a [f32]> {
    let CpuStorage::F32(v) = s else {
        candle_core::bail!("{what}: fused ops take f32");
    };
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&v[a..b]),
        None => candle_core::bail!("{what}: fused ops take contiguous tensors"),
    }
}

/// [`f32_slice`], writable: the elements an in-place op overwrites.
pub(crate) fn f32_slice_mut<'a>(
    s: &'a mut CpuStorage,
    l: &Layout,
    what: &str,
) -> Result<&'a mut [f32]> {
    let CpuStorage::F32(v) = s else {
        candle_core::bail!("{what}: in-place ops take f32");
    };
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&mut v[a..b]),
        None => candle_core::bail!("{what}: in-place ops take contiguous tensors"),
    }
}

/// The CPU storage behind a tensor (the fused ops run on the CPU only).
fn cpu_storage(s: &candle_core::Storage) -> Result<&CpuStorage> {
    match s {
        candle_core::Storage::Cpu(s) => Ok(s),
        _ => candle_core::bail!("fused ops run on the CPU"),
    }
}

fn usable(ts: &[&Tensor]) -> bool {
    kernels() == Kernels::Fused
        && ts
            .iter()
            .all(|t| t.dtype() == candle_core::DType::F32 && t.device().is_cpu() && t.rank() >= 1)
}

/// [`usable`] for the ops that have CUDA kernels too (`cuda.rs`: LayerNorm, softmax,
/// bias with activation): f32 on the CPU or, in a `cuda` build, on a CUDA device.
fn usable_with_cuda(ts: &[&Tensor]) -> bool {
    enabled() && usable_with_cuda_any(ts)
}

/// [`usable_with_cuda`] whatever the fused-ops switch says (for the hand-written backward
/// passes of one-node ops, which run whichever way the graph was built).
fn usable_with_cuda_any(ts: &[&Tensor]) -> bool {
    ts.iter().all(|t| {
        t.dtype() == candle_core::DType::F32
            && t.rank() >= 1
            && (t.device().is_cpu() || (cfg!(feature = "cuda") && t.device().is_cuda()))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::*;
    use candle_core::{Device, Var};

    #[test]
    fn bf16_products_track_f32_and_keep_f32_gradients() {
        let rel = |a: &Tensor, b: &Tensor| -> f32 {
            let d = (a - b).unwrap().sqr().unwrap().sum_all().unwrap();
            let n = b.sqr().unwrap().sum_all().unwrap();
            let (d, n) = (d.to_scalar::<f32>().unwrap(), n.to_scalar::<f32>().unwrap());
            // Inputs of 1e17 saturate the softmax: both gradients are exactly 0 there.
            if n == 0.0 { d.sqrt() } else { (d / n).sqrt() }
        };
        for scale in [1.0f32, 1e-18, 1e17] {
            let x = randn(&[2, 9, 24], scale, 1);
            let w = Var::from_tensor(&randn(&[16, 24], 0.2, 2)).unwrap();
            let b = Var::from_tensor(&randn(&[16], 0.2, 3)).unwrap();
            let k = randn(&[2, 5, 16], 1.0, 4);
            let run = |p: Precision| {
                with_fused(false, || {
                    with_precision(p, || {
                        let h = linear(&x, w.as_tensor(), Some(b.as_tensor())).unwrap();
                        let a = attention_composed(&h, &k, &k, 2, 0.25).unwrap();
                        let g = a.sqr().unwrap().sum_all().unwrap().backward().unwrap();
                        (h, g.get(w.as_tensor()).unwrap().clone())
                    })
                })
            };
            let (h32, g32) = run(Precision::F32);
            let (h16, g16) = run(Precision::Bf16);
            assert_eq!(g16.dtype(), candle_core::DType::F32);
            assert!(rel(&h16, &h32) < 1e-2, "scale {scale}: {}", rel(&h16, &h32));
            assert!(rel(&g16, &g32) < 5e-2, "scale {scale}: {}", rel(&g16, &g32));
            let finite = g16.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            assert!(finite.iter().all(|v| v.is_finite()), "scale {scale}");
        }
        let seen = with_precision(Precision::Bf16, || on_device_pool(&Device::Cpu, precision));
        assert_eq!(seen, Precision::Bf16);
        assert_eq!(precision(), Precision::F32, "restored after the closure");
    }

    /// `on_device_pool` runs its closure on a pool thread, where the thread-local switch
    /// would otherwise fall back to the default: the caller's setting must come along
    /// (else the fused-vs-composed comparisons would compare the fused ops with themselves).
    #[test]
    fn the_device_pool_keeps_the_callers_fused_setting() {
        for on in [false, true] {
            let seen = with_fused(on, || {
                on_device_pool(&Device::Cpu, || (enabled(), std::thread::current().id()))
            });
            assert_eq!(seen.0, on);
            assert_ne!(seen.1, std::thread::current().id(), "ran on a pool thread");
        }
    }

    /// On the device graph in bf16, attention with its projections stored in bf16
    /// (`linear_low`), and a mixed slot stored in bf16 (`matmul_low`) read by an MLP of a
    /// concatenation, give the bits (values and every gradient) of the same graph stored in
    /// f32, and store half the bytes; elsewhere the `_low` ops are the plain ones.
    #[test]
    fn products_stored_in_bf16_change_no_bits() {
        let x = Var::from_tensor(&randn(&[2, 5, 6], 1.0, 1)).unwrap();
        let ctx = Var::from_tensor(&randn(&[2, 3, 4], 1.0, 2)).unwrap();
        let w: Vec<Var> = [[8, 6], [8, 4], [8, 4], [6, 8], [8, 6], [4, 10], [3, 4]]
            .iter()
            .enumerate()
            .map(|(i, s)| Var::from_tensor(&randn(s, 0.4, 10 + i as u64)).unwrap())
            .collect();
        let b: Vec<Var> = [6, 4, 3]
            .iter()
            .enumerate()
            .map(|(i, &n)| Var::from_tensor(&randn(&[n], 0.2, 20 + i as u64)).unwrap())
            .collect();
        let run = |k: Kernels, p: Precision, stored_low: bool| {
            with_kernels(k, || {
                with_precision(p, || {
                    let proj = |t: &Tensor, w: &Var| match stored_low {
                        true => linear_low(t, w.as_tensor()),
                        false => linear(t, w.as_tensor(), None),
                    };
                    let (xt, ct) = (x.as_tensor(), ctx.as_tensor());
                    let (q, kk, v) = (
                        proj(xt, &w[0]).unwrap(),
                        proj(ct, &w[1]).unwrap(),
                        proj(ct, &w[2]).unwrap(),
                    );
                    let o = attention(&q, &kk, &v, 2, 0.5).unwrap();
                    let h = linear(&o, w[3].as_tensor(), Some(b[0].as_tensor())).unwrap();
                    let logits = linear(&h, w[4].as_tensor(), None).unwrap();
                    let wts = softmax(&logits.narrow(2, 0, 3).unwrap(), 2).unwrap();
                    let slots = ct.to_dtype(candle_core::DType::F32).unwrap();
                    let mixed = match stored_low {
                        true => matmul_low(&wts, &slots).unwrap(),
                        false => matmul(&wts, &slots).unwrap(),
                    };
                    let layers: Vec<MlpLayer> = vec![
                        (w[5].as_tensor(), Some(b[1].as_tensor())),
                        (w[6].as_tensor(), Some(b[2].as_tensor())),
                    ];
                    let y = mlp_cat(&mixed, &h, &layers, MlpAct::Relu).unwrap();
                    let low = [&q, &kk, &v, &o, &mixed]
                        .iter()
                        .filter(|t| t.dtype() == candle_core::DType::BF16)
                        .count();
                    let g = (&y * randn(y.dims(), 1.0, 30))
                        .unwrap()
                        .sum_all()
                        .unwrap()
                        .backward()
                        .unwrap();
                    let mut out = vec![y.flatten_all().unwrap().to_vec1::<f32>().unwrap()];
                    for v in [&x, &ctx].into_iter().chain(&w).chain(&b) {
                        out.push(
                            g.get(v.as_tensor())
                                .unwrap()
                                .flatten_all()
                                .unwrap()
                                .to_vec1()
                                .unwrap(),
                        );
                    }
                    (out, low)
                })
            })
        };
        let bits = |v: Vec<Vec<f32>>| -> Vec<Vec<u32>> {
            v.iter()
                .map(|x| x.iter().map(|f| f.to_bits()).collect())
                .collect()
        };
        for k in [Kernels::Device, Kernels::Composed, Kernels::Fused] {
            for p in [Precision::F32, Precision::Bf16] {
                if k == Kernels::Fused && p == Precision::Bf16 {
                    continue;
                }
                let (low, n_low) = run(k, p, true);
                let (plain, n_plain) = run(k, p, false);
                assert_eq!(bits(low), bits(plain), "{k} {p}");
                let stored = k == Kernels::Device && p == Precision::Bf16;
                assert_eq!((n_low, n_plain), (if stored { 5 } else { 0 }, 0), "{k} {p}");
            }
        }
    }
}
