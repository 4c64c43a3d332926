//! The kernels under the model, and the one switch between them and candle's composed
//! ops. Fused CPU ops with hand-written backward passes (LayerNorm, softmax, erf-GELU,
//! ReLU, the bias add and the whole of a linear layer, a convolution, a whole MLP, the
//! core of multi-head attention, a whole transformer block) compute the same functions
//! as candle's composed ops (`candle_nn::ops::softmax`, `Tensor::gelu_erf`,
//! `broadcast_add`, …), with one graph node per op and row-wise kernels where candle's
//! backward pass is slow (a broadcast's gradient is a `sum_keepdim` over leading dims,
//! and every graph node costs a zero tensor and an add in gradient accumulation). Each
//! op's tests check values and gradients against the composed version, against f64
//! finite differences, and on extreme inputs.
//!
//! The crate in rooms:
//!
//! - `cpu`: the CPU kernels (rows, products through `gemm`, `fastmath`) and one node per
//!   op that runs them;
//! - `graph`: the nodes above single ops (the product every node is built from; the
//!   device graph's attention, convolution and MLP nodes built from tensor ops; a whole
//!   transformer block and the Slot Mixer's mixing block as fused CPU nodes) and the
//!   backward pass in segments (`cut`);
//! - `cuda`: the CUDA kernels' source and launch geometry, their launcher (a `cuda`
//!   build) and, in the tests, an emulator that runs them on the host;
//! - `dispatch`: the public ops, each choosing between those and candle's ops;
//! - `profile`, `ledger`, `device_check` and `testing`: the per-op profile, the ledger of
//!   a step's products, casts and copies, the check of a device's ops against the CPU's,
//!   and the tests' helpers.
//!
//! This file is the hub: the thread's switches, [`Kernels`] (applied per thread with
//! [`with_kernels`]) and [`Precision`] ([`with_precision`]), and the public API. The
//! fused kernels need f32 on the CPU; anything else takes the composed path whatever the
//! switch says, except the ops with CUDA kernels too (LayerNorm, softmax, bias with
//! activation), which on a GPU are the one-node ops, beside the nodes built from tensor
//! ops; the rest of a GPU's graph is candle's.

mod cpu;
pub mod cuda;
pub mod device_check;
mod dispatch;
mod graph;
mod kept;
pub mod ledger;
pub mod profile;
#[cfg(test)]
mod testing;

pub use cpu::mlp::MlpLayer;
pub use cpu::{MlpAct, f32_slice, fastmath};
pub use dispatch::attention::{attention, attention_composed};
pub use dispatch::block::block;
pub use dispatch::conv::{conv2d_nhwc, conv2d_relu_nhwc};
pub use dispatch::linear::{linear, linear_low};
pub use dispatch::mix::slot_mix;
pub use dispatch::mlp::{mlp, mlp_cat, mlp_layer_by_layer};
pub use dispatch::pointwise::{bias_act, bias_add, gelu, layer_norm, leaky_relu, relu, softmax};
pub use graph::block::BlockParams;
pub use graph::cut;
pub use graph::cut::{Cuts, cut, recompute, with_cuts};
pub use graph::matmul::{matmul, matmul_low};

use candle_core::Tensor;
use std::cell::Cell;

thread_local! {
    static KERNELS: Cell<Kernels> = const { Cell::new(Kernels::Fused) };
    static PRECISION: Cell<Precision> = const { Cell::new(Precision::F32) };
}

/// The number format of the matrix products (linear layers, convolutions, attention):
/// `bf16` rounds both operands to bfloat16 and sums the products in f32 (cuBLAS on a GPU,
/// AMX tiles or AVX512-BF16 in the fused CPU kernels: [`cpu_bf16_products`]), as
/// PyTorch's autocast does; LayerNorm, softmax, the loss, gradients' sums over the batch
/// and the optimiser stay in f32. On a CPU without bf16 products the fused kernels' products
/// stay f32.
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

/// The unit that runs the fused CPU kernels' bf16 products in this process ("AMX tiles",
/// "AVX512-BF16 dot products"), chosen once at run time from what the CPU has and the OS
/// allows (narrowed by the `OSRT_CPU_BF16` environment variable: `amx`, `avx512-bf16`,
/// `off`); `None` where there is none, and the products in bf16 graphs stay f32 there.
pub fn cpu_bf16_products() -> Option<&'static str> {
    #[cfg(target_arch = "x86_64")]
    return cpu::bf16::unit().map(|u| match u {
        cpu::bf16::Unit::Amx => "AMX tiles",
        cpu::bf16::Unit::Avx512Bf16 => "AVX512-BF16 dot products",
    });
    #[cfg(not(target_arch = "x86_64"))]
    None
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
    let (l, at) = (ledger::current(), ledger::context());
    device.with_context(|| {
        with_kernels(k, || {
            with_precision(p, || {
                profile::recording(r, || ledger::recording(l, || ledger::in_context(at, f)))
            })
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

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
}
