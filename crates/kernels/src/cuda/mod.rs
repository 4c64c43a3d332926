//! osrt's CUDA kernels: their source (`device_kernels.cu`) with the geometry each is
//! launched with (`device_kernels`); in a `cuda` build, their compilation and launcher
//! (`launch`) and the one-node ops' launches (`rows`: LayerNorm, softmax, column sums;
//! `elementwise`: bias with activation, im2col, col2im); and, in the CPU build's tests,
//! an emulator that runs the same source on the host (`emulated`).
//!
//! The launches are CUDA versions of the one-node ops whose composed form costs the most
//! memory on a GPU: LayerNorm (candle's composition keeps five full-size intermediates
//! for the backward pass; this op keeps its input), softmax (four; this op keeps its
//! output) and a bias with its activation (`cpu::bias_act`: up to three; this op none),
//! forward and backward, and the column sums their gradients need; and the unfolding
//! (im2col) and its adjoint (col2im) of the convolution node. The kernels are compiled
//! once per process with NVRTC, so a build needs no GPU. They compute what the CPU ops
//! compute, in f32, with reductions in a fixed order (a warp per row, shuffles in a fixed
//! pattern; column sums over fixed chunks of rows, the chunks added in order): the same
//! bits for the same input on the same GPU.

pub mod device_kernels;
#[cfg(feature = "cuda")]
mod elementwise;
#[cfg(test)]
mod emulated;
#[cfg(feature = "cuda")]
mod launch;
#[cfg(feature = "cuda")]
mod rows;

#[cfg(feature = "cuda")]
pub use elementwise::{
    bias_act_bwd, bias_act_bwd_in_place, bias_act_bwd_low, bias_act_fwd, bias_act_fwd_in_place,
    bias_act_low, col2im, im2col,
};
#[cfg(feature = "cuda")]
pub use launch::compile;
#[cfg(feature = "cuda")]
pub use rows::{
    column_sum, layer_norm_bwd, layer_norm_fwd, softmax_bwd, softmax_bwd_scaled_in_place,
    softmax_fwd,
};
