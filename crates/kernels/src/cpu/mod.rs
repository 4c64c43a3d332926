//! The fused CPU ops: row kernels, the matrix products (`gemm`), vectorised math
//! (`fastmath`) and parallel output buffers (`buffer`), and one candle node per op that
//! runs them forward and backward: the activations with [`MlpAct`], softmax, LayerNorm,
//! the bias add and the linear layer, bias with activation, a whole MLP, the convolution
//! and the core of attention. The nodes of the ops that have CUDA kernels too (LayerNorm,
//! softmax, bias with activation, column sums, im2col and col2im) launch them from their
//! `cuda_fwd` (`crate::cuda`). Which op runs where is chosen in `crate::dispatch`.
//!
//! Below: how the nodes read their operands' storage.

pub(crate) mod activation;
pub(crate) mod attention;
#[cfg(target_arch = "x86_64")]
pub(crate) mod bf16;
pub(crate) mod bias_act;
pub(crate) mod buffer;
pub(crate) mod conv;
pub mod fastmath;
pub(crate) mod gemm;
pub(crate) mod layer_norm;
pub(crate) mod linear;
pub(crate) mod matrix;
pub(crate) mod mlp;
pub(crate) mod softmax;

pub use activation::MlpAct;

use candle_core::{CpuStorage, Layout, Result, Shape, Tensor};

/// Rows per parallel task: small tensors stay on one thread.
pub(crate) const ROWS_PER_TASK: usize = 64;

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
pub(crate) fn cpu_storage(s: &candle_core::Storage) -> Result<&CpuStorage> {
    match s {
        candle_core::Storage::Cpu(s) => Ok(s),
        _ => candle_core::bail!("fused ops run on the CPU"),
    }
}

/// Whether the nodes with CUDA kernels too (LayerNorm, softmax, bias with activation) take
/// `ts`: f32 on the CPU or, in a `cuda` build, on a CUDA device, whatever the kernels
/// switch says (for the hand-written backward passes of one-node ops, which run whichever
/// way the graph was built).
pub(crate) fn usable_with_cuda_any(ts: &[&Tensor]) -> bool {
    ts.iter().all(|t| {
        t.dtype() == candle_core::DType::F32
            && t.rank() >= 1
            && (t.device().is_cpu() || (cfg!(feature = "cuda") && t.device().is_cuda()))
    })
}

/// A contiguous `[.., k]` layout as the 2-D `[rows, k]` the matmul kernels take: the
/// same memory with the leading dims flattened. The ops take N-D inputs themselves
/// because a `reshape` around them would be two more graph nodes, each costing a zero
/// tensor and an add of the whole activation in candle's backward pass.
pub(crate) fn rows_layout(l: &Layout) -> Result<Layout> {
    let Some(&k) = l.dims().last() else {
        candle_core::bail!("a scalar where rows of values were expected")
    };
    if !l.is_contiguous() {
        candle_core::bail!("fused ops take contiguous tensors");
    }
    let rows = l.shape().elem_count().checked_div(k).unwrap_or(0);
    Ok(Layout::contiguous_with_offset((rows, k), l.start_offset()))
}

/// `l`'s shape with its last dim replaced by `last`.
pub(crate) fn with_last_dim(l: &Layout, last: usize) -> Shape {
    let mut dims = l.dims().to_vec();
    if let Some(d) = dims.last_mut() {
        *d = last;
    }
    Shape::from(dims)
}
