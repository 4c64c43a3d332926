//! Compiling osrt's CUDA kernels with NVRTC and launching them: the kernels' PTX (compiled
//! once per process, so a build needs no GPU), the [`launch!`] helper every launch goes
//! through, device views of the operands and the launch geometries of
//! `device_kernels` in cudarc's form.

// Launching a kernel is an unsafe call of cudarc: [`launch!`] expands to it, inside the
// caller's `unsafe` block, which says why the call is sound.
#![allow(unsafe_code)]

use super::device_kernels::{self as geometry, Launch, SOURCE};
use candle_core::backend::BackendStorage;
use candle_core::cuda_backend::CudaDevice;
use candle_core::cuda_backend::cudarc::driver::{CudaView, CudaViewMut, LaunchConfig};
use candle_core::{CudaStorage, Layout, Result};
use std::sync::OnceLock;

/// Module name under which the device caches the loaded kernels.
pub(super) const MODULE: &str = "osrt_kernels_rows";

/// The kernels' PTX, compiled by NVRTC on first use.
pub(super) fn ptx() -> Result<&'static str> {
    static PTX: OnceLock<std::result::Result<String, String>> = OnceLock::new();
    PTX.get_or_init(|| {
        candle_core::cuda_backend::cudarc::nvrtc::compile_ptx(SOURCE)
            .map(|p| p.to_src())
            .map_err(|e| e.to_string())
    })
    .as_deref()
    .map_err(|e| candle_core::Error::Msg(format!("compiling osrt's CUDA kernels: {e}")))
}

/// Compiles the kernels (no GPU needed): for a test that they build.
pub fn compile() -> Result<usize> {
    Ok(ptx()?.len())
}

/// `launch!(dev, name, cfg; args…)` launches kernel `name` (loaded once per device) on
/// `dev` over the geometry `cfg` with `args`, in the kernel's parameter order. It expands
/// to cudarc's `unsafe` launch: the caller wraps it in an `unsafe` block that says why the
/// arguments match the kernel's signature and each buffer holds what the kernel reads and
/// writes over `cfg`.
macro_rules! launch {
    ($dev:expr, $name:expr, $cfg:expr; $($arg:expr),+ $(,)?) => {{
        let f = $dev.get_or_load_custom_func(
            $name,
            $crate::cuda::launch::MODULE,
            $crate::cuda::launch::ptx()?,
        )?;
        let mut l = f.builder();
        $(candle_core::cuda_backend::cudarc::driver::PushKernelArg::arg(&mut l, $arg);)+
        candle_core::cuda_backend::WrapErr::w(l.launch($cfg))
    }};
}
pub(super) use launch;

/// A contiguous f32 input as a device view.
pub(super) fn input<'a>(s: &'a CudaStorage, l: &Layout, what: &str) -> Result<CudaView<'a, f32>> {
    let Some((a, b)) = l.contiguous_offsets() else {
        candle_core::bail!("{what}: the CUDA kernel needs a contiguous input")
    };
    Ok(s.as_cuda_slice::<f32>()?.slice(a..b))
}

/// `(rows, d)` of a `[.., d]` layout, as the kernels' `int`s; an empty tensor is no rows
/// (the kernels then write nothing, as the CPU ops return empty tensors).
pub(super) fn rows_cols(l: &Layout, d: usize, what: &str) -> Result<(i32, i32)> {
    let n = l.shape().elem_count();
    if n == 0 {
        return match i32::try_from(d) {
            Ok(d) => Ok((0, d)),
            Err(_) => candle_core::bail!("{what}: rows of {d} are too wide for one launch"),
        };
    }
    if d == 0 || !n.is_multiple_of(d) {
        candle_core::bail!("{what}: {n} elements are not rows of {d}")
    }
    match (i32::try_from(n / d), i32::try_from(d)) {
        (Ok(r), Ok(d)) => Ok((r, d)),
        _ => candle_core::bail!("{what}: {n} elements are too many for one launch"),
    }
}

/// cudarc's form of a launch geometry.
pub(super) fn config(l: Launch) -> LaunchConfig {
    LaunchConfig {
        grid_dim: l.grid,
        block_dim: l.block,
        shared_mem_bytes: 0,
    }
}

pub(super) fn row_launch(rows: i32) -> LaunchConfig {
    config(geometry::rows(rows))
}

pub(super) fn column_launch(width: i32, chunks: usize) -> LaunchConfig {
    config(geometry::columns(width, chunks))
}

pub(super) fn device(s: &CudaStorage) -> &CudaDevice {
    s.device()
}

pub(super) fn elementwise_launch(n: usize) -> LaunchConfig {
    config(geometry::elementwise(n))
}

/// The contiguous f32 elements of `s` under `l`, writable: the buffer an in-place kernel
/// overwrites.
pub(super) fn output<'a>(
    s: &'a mut CudaStorage,
    l: &Layout,
    what: &str,
) -> Result<CudaViewMut<'a, f32>> {
    let Some((a, b)) = l.contiguous_offsets() else {
        candle_core::bail!("{what}: the CUDA kernel needs a contiguous tensor")
    };
    Ok(s.as_cuda_slice_mut::<f32>()?.slice_mut(a..b))
}
