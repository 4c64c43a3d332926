//! CUDA versions of the one-node ops whose composed form costs the most memory on a GPU:
//! LayerNorm (candle's composition keeps five full-size intermediates for the backward
//! pass; this op keeps its input), softmax (four; this op keeps its output) and a bias
//! with its activation (`bias_act.rs`: up to three; this op none), forward and backward,
//! and the column sums their gradients need; and the unfolding (im2col) and its adjoint
//! (col2im) of the convolution node. The kernels (`device_kernels.cu`, launched with the
//! geometry of `device_kernels.rs`) are compiled once per process with NVRTC, so a build
//! needs no GPU; the CPU build runs the same source on the host in its tests
//! (`emulated.rs`). They compute what the CPU ops compute, in f32, with reductions in a fixed
//! order (a warp per row, shuffles in a fixed pattern; column sums over fixed chunks of
//! rows, the chunks added in order): the same bits for the same input on the same GPU.

// Launching a kernel and allocating memory it fills are unsafe calls of cudarc; each is
// preceded by the checks that make it sound (contiguous inputs, sizes, argument order).
#![allow(unsafe_code)]

use candle_core::backend::BackendStorage;
use candle_core::cuda_backend::cudarc::driver::{CudaView, LaunchConfig, PushKernelArg};
use candle_core::cuda_backend::{CudaDevice, WrapErr};
use candle_core::{CudaStorage, Layout, Result, Shape};
use std::sync::OnceLock;

use crate::device_kernels::{self as geometry, Launch, PARAM_CHUNK, SOURCE};

/// Module name under which the device caches the loaded kernels.
const MODULE: &str = "osrt_kernels_rows";

/// The kernels' PTX, compiled by NVRTC on first use.
fn ptx() -> Result<&'static str> {
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

/// A contiguous f32 input as a device view.
fn input<'a>(s: &'a CudaStorage, l: &Layout, what: &str) -> Result<CudaView<'a, f32>> {
    let Some((a, b)) = l.contiguous_offsets() else {
        candle_core::bail!("{what}: the CUDA kernel needs a contiguous input")
    };
    Ok(s.as_cuda_slice::<f32>()?.slice(a..b))
}

/// `(rows, d)` of a `[.., d]` layout, as the kernels' `int`s; an empty tensor is no rows
/// (the kernels then write nothing, as the CPU ops return empty tensors).
fn rows_cols(l: &Layout, d: usize, what: &str) -> Result<(i32, i32)> {
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
fn config(l: Launch) -> LaunchConfig {
    LaunchConfig {
        grid_dim: l.grid,
        block_dim: l.block,
        shared_mem_bytes: 0,
    }
}

fn row_launch(rows: i32) -> LaunchConfig {
    config(geometry::rows(rows))
}

fn column_launch(width: i32, chunks: usize) -> LaunchConfig {
    config(geometry::columns(width, chunks))
}

fn device(s: &CudaStorage) -> &CudaDevice {
    s.device()
}

/// LayerNorm forward: `x: [.., d]`, `g`, `b: [d]` → `[.., d]`.
#[allow(clippy::too_many_arguments)]
pub fn layer_norm_fwd(
    x: &CudaStorage,
    lx: &Layout,
    g: &CudaStorage,
    lg: &Layout,
    b: &CudaStorage,
    lb: &Layout,
    eps: f32,
) -> Result<(CudaStorage, Shape)> {
    let dev = device(x);
    let d = lg.shape().elem_count();
    let (rows, dd) = rows_cols(lx, d, "layer_norm")?;
    if lb.shape().elem_count() != d {
        candle_core::bail!("layer_norm: a bias of {:?} for a weight of {d}", lb.shape())
    }
    let (xv, gv, bv) = (
        input(x, lx, "layer_norm x")?,
        input(g, lg, "layer_norm weight")?,
        input(b, lb, "layer_norm bias")?,
    );
    // SAFETY: every element is written by the kernel below.
    let mut y = unsafe { dev.alloc::<f32>(lx.shape().elem_count().max(1))? };
    {
        let f = dev.get_or_load_custom_func("osrt_layer_norm_fwd", MODULE, ptx()?)?;
        let mut l = f.builder();
        l.arg(&xv)
            .arg(&gv)
            .arg(&bv)
            .arg(&mut y)
            .arg(&rows)
            .arg(&dd)
            .arg(&eps);
        // SAFETY: the arguments match the kernel's signature; sizes were checked above.
        unsafe { l.launch(row_launch(rows)) }.w()?;
    }
    Ok((
        CudaStorage::wrap_cuda_slice(y, dev.clone()),
        lx.shape().clone(),
    ))
}

/// LayerNorm backward, packed as the CPU op packs it: `[rows + 2, d]` = dx rows, dγ, dβ.
#[allow(clippy::too_many_arguments)]
pub fn layer_norm_bwd(
    x: &CudaStorage,
    lx: &Layout,
    g: &CudaStorage,
    lg: &Layout,
    dy: &CudaStorage,
    ldy: &Layout,
    eps: f32,
) -> Result<(CudaStorage, Shape)> {
    let dev = device(x);
    let d = lg.shape().elem_count();
    let (rows, dd) = rows_cols(lx, d, "layer_norm backward")?;
    if ldy.shape().elem_count() != lx.shape().elem_count() {
        candle_core::bail!(
            "layer_norm backward: gradient {:?} for input {:?}",
            ldy.shape(),
            lx.shape()
        )
    }
    let (xv, gv, dyv) = (
        input(x, lx, "layer_norm backward x")?,
        input(g, lg, "layer_norm backward weight")?,
        input(dy, ldy, "layer_norm backward gradient")?,
    );
    let n = rows as usize * d;
    let chunks = geometry::chunks(rows as usize);
    // SAFETY: the kernels below write every element of each buffer.
    let (mut out, mut stats, mut partial) = unsafe {
        (
            dev.alloc::<f32>(n + 2 * d)?,
            dev.alloc::<f32>((2 * rows as usize).max(1))?,
            dev.alloc::<f32>(chunks * 2 * d)?,
        )
    };
    let (chunk, nchunks, width) = (PARAM_CHUNK as i32, chunks as i32, 2 * dd);
    {
        let mut dx = out.slice_mut(0..n);
        let f = dev.get_or_load_custom_func("osrt_layer_norm_bwd", MODULE, ptx()?)?;
        let mut l = f.builder();
        l.arg(&xv).arg(&gv).arg(&dyv).arg(&mut dx).arg(&mut stats);
        l.arg(&rows).arg(&dd).arg(&eps);
        // SAFETY: the arguments match the kernel's signature; sizes were checked above.
        unsafe { l.launch(row_launch(rows)) }.w()?;
    }
    {
        let f = dev.get_or_load_custom_func("osrt_layer_norm_bwd_params", MODULE, ptx()?)?;
        let mut l = f.builder();
        l.arg(&xv).arg(&dyv).arg(&stats).arg(&mut partial);
        l.arg(&rows).arg(&dd).arg(&chunk);
        // SAFETY: as above; `partial` holds 2·d floats per chunk.
        unsafe { l.launch(column_launch(dd, chunks)) }.w()?;
    }
    {
        let mut dgb = out.slice_mut(n..n + 2 * d);
        let f = dev.get_or_load_custom_func("osrt_sum_chunks", MODULE, ptx()?)?;
        let mut l = f.builder();
        l.arg(&partial).arg(&mut dgb).arg(&nchunks).arg(&width);
        // SAFETY: as above; the last 2·d floats of `out` take the sums.
        unsafe { l.launch(column_launch(width, 1)) }.w()?;
    }
    Ok((
        CudaStorage::wrap_cuda_slice(out, dev.clone()),
        Shape::from((rows as usize + 2, d)),
    ))
}

/// Softmax over the last dimension.
pub fn softmax_fwd(x: &CudaStorage, lx: &Layout) -> Result<(CudaStorage, Shape)> {
    let dev = device(x);
    let d = lx.dims().last().copied().unwrap_or(1);
    let (rows, dd) = rows_cols(lx, d, "softmax")?;
    let xv = input(x, lx, "softmax")?;
    // SAFETY: every element is written by the kernel below.
    let mut y = unsafe { dev.alloc::<f32>(lx.shape().elem_count().max(1))? };
    {
        let f = dev.get_or_load_custom_func("osrt_softmax_fwd", MODULE, ptx()?)?;
        let mut l = f.builder();
        l.arg(&xv).arg(&mut y).arg(&rows).arg(&dd);
        // SAFETY: the arguments match the kernel's signature; sizes were checked above.
        unsafe { l.launch(row_launch(rows)) }.w()?;
    }
    Ok((
        CudaStorage::wrap_cuda_slice(y, dev.clone()),
        lx.shape().clone(),
    ))
}

/// Softmax backward from its output: `dx = y ⊙ (dy − Σ y ⊙ dy)` per row.
pub fn softmax_bwd(
    y: &CudaStorage,
    ly: &Layout,
    dy: &CudaStorage,
    ldy: &Layout,
) -> Result<(CudaStorage, Shape)> {
    let dev = device(y);
    let d = ly.dims().last().copied().unwrap_or(1);
    let (rows, dd) = rows_cols(ly, d, "softmax backward")?;
    if ldy.shape() != ly.shape() {
        candle_core::bail!(
            "softmax backward: gradient {:?} for output {:?}",
            ldy.shape(),
            ly.shape()
        )
    }
    let (yv, dyv) = (
        input(y, ly, "softmax backward output")?,
        input(dy, ldy, "softmax backward gradient")?,
    );
    // SAFETY: every element is written by the kernel below.
    let mut dx = unsafe { dev.alloc::<f32>(ly.shape().elem_count().max(1))? };
    {
        let f = dev.get_or_load_custom_func("osrt_softmax_bwd", MODULE, ptx()?)?;
        let mut l = f.builder();
        l.arg(&yv).arg(&dyv).arg(&mut dx).arg(&rows).arg(&dd);
        // SAFETY: the arguments match the kernel's signature; sizes were checked above.
        unsafe { l.launch(row_launch(rows)) }.w()?;
    }
    Ok((
        CudaStorage::wrap_cuda_slice(dx, dev.clone()),
        ly.shape().clone(),
    ))
}

/// [`softmax_bwd`] times `scale` (candle's affine), written over `dy` (a buffer its
/// caller owns).
pub fn softmax_bwd_scaled_in_place(
    y: &CudaStorage,
    ly: &Layout,
    dy: &mut CudaStorage,
    ldy: &Layout,
    scale: f32,
) -> Result<()> {
    let dev = device(y).clone();
    let d = ly.dims().last().copied().unwrap_or(1);
    let (rows, dd) = rows_cols(ly, d, "softmax backward in place")?;
    if ldy.shape() != ly.shape() {
        candle_core::bail!(
            "softmax backward in place: gradient {:?} for output {:?}",
            ldy.shape(),
            ly.shape()
        )
    }
    let yv = input(y, ly, "softmax backward in place output")?;
    let mut dyv = output(dy, ldy, "softmax backward in place gradient")?;
    let f = dev.get_or_load_custom_func("osrt_softmax_bwd_scaled_inplace", MODULE, ptx()?)?;
    let mut l = f.builder();
    l.arg(&yv).arg(&mut dyv).arg(&rows).arg(&dd).arg(&scale);
    // SAFETY: the arguments match the kernel's signature; sizes were checked above.
    unsafe { l.launch(row_launch(rows)) }.w()?;
    Ok(())
}

fn elementwise_launch(n: usize) -> LaunchConfig {
    config(geometry::elementwise(n))
}

/// `act(x + b)` for `x: [.., d]`, `b: [d]`; `act` as `bias_act::act_code` spells it.
pub fn bias_act_fwd(
    x: &CudaStorage,
    lx: &Layout,
    b: &CudaStorage,
    lb: &Layout,
    (kind, slope): (i32, f32),
) -> Result<(CudaStorage, Shape)> {
    let dev = device(x);
    let d = lb.shape().elem_count();
    let (_, cols) = rows_cols(lx, d, "bias+activation")?;
    let n = lx.shape().elem_count();
    let (xv, bv) = (
        input(x, lx, "bias+activation x")?,
        input(b, lb, "bias+activation bias")?,
    );
    let n64 = n as i64;
    // SAFETY: every element is written by the kernel below.
    let mut y = unsafe { dev.alloc::<f32>(n.max(1))? };
    {
        let f = dev.get_or_load_custom_func("osrt_bias_act_fwd", MODULE, ptx()?)?;
        let mut l = f.builder();
        l.arg(&xv)
            .arg(&bv)
            .arg(&mut y)
            .arg(&n64)
            .arg(&cols)
            .arg(&kind)
            .arg(&slope);
        // SAFETY: the arguments match the kernel's signature; sizes were checked above.
        unsafe { l.launch(elementwise_launch(n)) }.w()?;
    }
    Ok((
        CudaStorage::wrap_cuda_slice(y, dev.clone()),
        lx.shape().clone(),
    ))
}

/// The contiguous f32 elements of `s` under `l`, writable: the buffer an in-place kernel
/// overwrites.
fn output<'a>(
    s: &'a mut CudaStorage,
    l: &Layout,
    what: &str,
) -> Result<candle_core::cuda_backend::cudarc::driver::CudaViewMut<'a, f32>> {
    let Some((a, b)) = l.contiguous_offsets() else {
        candle_core::bail!("{what}: the CUDA kernel needs a contiguous tensor")
    };
    Ok(s.as_cuda_slice_mut::<f32>()?.slice_mut(a..b))
}

/// `bf16(act(z + b))` for a bf16 `z: [.., d]` and an f32 `b: [d]`, in bf16.
pub fn bias_act_low(
    z: &CudaStorage,
    lz: &Layout,
    b: &CudaStorage,
    lb: &Layout,
    (kind, slope): (i32, f32),
) -> Result<(CudaStorage, Shape)> {
    let dev = device(b).clone();
    let d = lb.shape().elem_count();
    let (_, cols) = rows_cols(lz, d, "bias+activation to bf16")?;
    let n = lz.shape().elem_count();
    let Some((a, e)) = lz.contiguous_offsets() else {
        candle_core::bail!("bias+activation to bf16: the CUDA kernel needs a contiguous input")
    };
    let zv = z.as_cuda_slice::<half::bf16>()?.slice(a..e);
    let bv = input(b, lb, "bias+activation to bf16 bias")?;
    let n64 = n as i64;
    // SAFETY: every element is written by the kernel below.
    let mut y = unsafe { dev.alloc::<half::bf16>(n.max(1))? };
    {
        let f = dev.get_or_load_custom_func("osrt_bias_act_low", MODULE, ptx()?)?;
        let mut l = f.builder();
        l.arg(&zv)
            .arg(&bv)
            .arg(&mut y)
            .arg(&n64)
            .arg(&cols)
            .arg(&kind)
            .arg(&slope);
        // SAFETY: the arguments match the kernel's signature; sizes were checked above.
        unsafe { l.launch(elementwise_launch(n)) }.w()?;
    }
    Ok((CudaStorage::wrap_cuda_slice(y, dev), lz.shape().clone()))
}

/// [`bias_act_fwd`] written over `x` (a buffer its caller owns).
pub fn bias_act_fwd_in_place(
    x: &mut CudaStorage,
    lx: &Layout,
    b: &CudaStorage,
    lb: &Layout,
    (kind, slope): (i32, f32),
) -> Result<()> {
    let dev = device(b).clone();
    let d = lb.shape().elem_count();
    let (_, cols) = rows_cols(lx, d, "bias+activation in place")?;
    let n = lx.shape().elem_count();
    let bv = input(b, lb, "bias+activation in place bias")?;
    let mut xv = output(x, lx, "bias+activation in place x")?;
    let n64 = n as i64;
    let f = dev.get_or_load_custom_func("osrt_bias_act_fwd_inplace", MODULE, ptx()?)?;
    let mut l = f.builder();
    l.arg(&mut xv)
        .arg(&bv)
        .arg(&n64)
        .arg(&cols)
        .arg(&kind)
        .arg(&slope);
    // SAFETY: the arguments match the kernel's signature; sizes were checked above.
    unsafe { l.launch(elementwise_launch(n)) }.w()?;
    Ok(())
}

/// [`bias_act_bwd`] written over `x` (a buffer its caller owns).
#[allow(clippy::too_many_arguments)]
pub fn bias_act_bwd_in_place(
    x: &mut CudaStorage,
    lx: &Layout,
    b: &CudaStorage,
    lb: &Layout,
    dy: &CudaStorage,
    ldy: &Layout,
    (kind, slope): (i32, f32),
) -> Result<()> {
    let dev = device(b).clone();
    let d = lb.shape().elem_count();
    let (_, cols) = rows_cols(lx, d, "bias+activation backward in place")?;
    let n = lx.shape().elem_count();
    if ldy.shape().elem_count() != n {
        candle_core::bail!(
            "bias+activation backward in place: gradient {:?} for {:?}",
            ldy.shape(),
            lx.shape()
        )
    }
    let (bv, dyv) = (
        input(b, lb, "bias+activation backward in place bias")?,
        input(dy, ldy, "bias+activation backward in place gradient")?,
    );
    let mut xv = output(x, lx, "bias+activation backward in place x")?;
    let n64 = n as i64;
    let f = dev.get_or_load_custom_func("osrt_bias_act_bwd_inplace", MODULE, ptx()?)?;
    let mut l = f.builder();
    l.arg(&mut xv).arg(&bv).arg(&dyv);
    l.arg(&n64).arg(&cols).arg(&kind).arg(&slope);
    // SAFETY: the arguments match the kernel's signature; sizes were checked above.
    unsafe { l.launch(elementwise_launch(n)) }.w()?;
    Ok(())
}

/// `f32(dy) · act'(f32(z) + b)` for a bf16 `z: [.., d]`, an f32 `b: [d]` and a bf16 `dy`, in
/// f32.
#[allow(clippy::too_many_arguments)]
pub fn bias_act_bwd_low(
    z: &CudaStorage,
    lz: &Layout,
    b: &CudaStorage,
    lb: &Layout,
    dy: &CudaStorage,
    ldy: &Layout,
    (kind, slope): (i32, f32),
) -> Result<(CudaStorage, Shape)> {
    let dev = device(b).clone();
    let d = lb.shape().elem_count();
    let (_, cols) = rows_cols(lz, d, "bias+activation backward from bf16")?;
    let n = lz.shape().elem_count();
    let (Some((a, e)), Some((c, f))) = (lz.contiguous_offsets(), ldy.contiguous_offsets()) else {
        candle_core::bail!(
            "bias+activation backward from bf16: the CUDA kernel needs contiguous operands"
        )
    };
    if f - c != n {
        candle_core::bail!(
            "bias+activation backward from bf16: gradient {:?} for {:?}",
            ldy.shape(),
            lz.shape()
        )
    }
    let zv = z.as_cuda_slice::<half::bf16>()?.slice(a..e);
    let dyv = dy.as_cuda_slice::<half::bf16>()?.slice(c..f);
    let bv = input(b, lb, "bias+activation backward from bf16 bias")?;
    let n64 = n as i64;
    // SAFETY: every element is written by the kernel below.
    let mut dz = unsafe { dev.alloc::<f32>(n.max(1))? };
    {
        let func = dev.get_or_load_custom_func("osrt_bias_act_bwd_low", MODULE, ptx()?)?;
        let mut l = func.builder();
        l.arg(&zv).arg(&bv).arg(&dyv).arg(&mut dz);
        l.arg(&n64).arg(&cols).arg(&kind).arg(&slope);
        // SAFETY: the arguments match the kernel's signature; sizes were checked above.
        unsafe { l.launch(elementwise_launch(n)) }.w()?;
    }
    Ok((CudaStorage::wrap_cuda_slice(dz, dev), lz.shape().clone()))
}

/// `dy · act'(x + b)`.
#[allow(clippy::too_many_arguments)]
pub fn bias_act_bwd(
    x: &CudaStorage,
    lx: &Layout,
    b: &CudaStorage,
    lb: &Layout,
    dy: &CudaStorage,
    ldy: &Layout,
    (kind, slope): (i32, f32),
) -> Result<(CudaStorage, Shape)> {
    let dev = device(x);
    let d = lb.shape().elem_count();
    let (_, cols) = rows_cols(lx, d, "bias+activation backward")?;
    let n = lx.shape().elem_count();
    if ldy.shape().elem_count() != n {
        candle_core::bail!(
            "bias+activation backward: gradient {:?} for {:?}",
            ldy.shape(),
            lx.shape()
        )
    }
    let (xv, bv, dyv) = (
        input(x, lx, "bias+activation backward x")?,
        input(b, lb, "bias+activation backward bias")?,
        input(dy, ldy, "bias+activation backward gradient")?,
    );
    let n64 = n as i64;
    // SAFETY: every element is written by the kernel below.
    let mut dz = unsafe { dev.alloc::<f32>(n.max(1))? };
    {
        let f = dev.get_or_load_custom_func("osrt_bias_act_bwd", MODULE, ptx()?)?;
        let mut l = f.builder();
        l.arg(&xv).arg(&bv).arg(&dyv).arg(&mut dz);
        l.arg(&n64).arg(&cols).arg(&kind).arg(&slope);
        // SAFETY: the arguments match the kernel's signature; sizes were checked above.
        unsafe { l.launch(elementwise_launch(n)) }.w()?;
    }
    Ok((
        CudaStorage::wrap_cuda_slice(dz, dev.clone()),
        lx.shape().clone(),
    ))
}

/// Sums over the rows of a `[rows, d]` buffer → `[d]`: per fixed chunk of rows, then the
/// chunks in order.
pub fn column_sum(a: &CudaStorage, la: &Layout, d: usize) -> Result<(CudaStorage, Shape)> {
    let dev = device(a);
    let (rows, cols) = rows_cols(la, d, "column sum")?;
    let av = input(a, la, "column sum")?;
    let chunks = geometry::chunks(rows as usize);
    let (chunk, nchunks) = (PARAM_CHUNK as i32, chunks as i32);
    // SAFETY: the kernels below write every element of each buffer.
    let (mut partial, mut out) = unsafe { (dev.alloc::<f32>(chunks * d)?, dev.alloc::<f32>(d)?) };
    {
        let f = dev.get_or_load_custom_func("osrt_column_partials", MODULE, ptx()?)?;
        let mut l = f.builder();
        l.arg(&av)
            .arg(&mut partial)
            .arg(&rows)
            .arg(&cols)
            .arg(&chunk);
        // SAFETY: the arguments match the kernel's signature; `partial` holds d per chunk.
        unsafe { l.launch(column_launch(cols, chunks)) }.w()?;
    }
    {
        let f = dev.get_or_load_custom_func("osrt_sum_chunks", MODULE, ptx()?)?;
        let mut l = f.builder();
        l.arg(&partial).arg(&mut out).arg(&nchunks).arg(&cols);
        // SAFETY: as above.
        unsafe { l.launch(column_launch(cols, 1)) }.w()?;
    }
    Ok((
        CudaStorage::wrap_cuda_slice(out, dev.clone()),
        Shape::from(d),
    ))
}

/// An unfolding's sizes as the kernels' `int`s: `[h, w, c, k, stride, pad, ho, wo]`.
fn fold_ints(dims: [usize; 9], what: &str) -> Result<[i32; 8]> {
    let [_, h, w, c, k, stride, pad, ho, wo] = dims;
    let mut out = [0i32; 8];
    for (o, v) in out.iter_mut().zip([h, w, c, k, stride.max(1), pad, ho, wo]) {
        *o = i32::try_from(v)
            .map_err(|_| candle_core::Error::Msg(format!("{what}: size {v} too large")))?;
    }
    Ok(out)
}

/// The offsets of a contiguous input of `expected` values in its storage.
fn fold_input(l: &Layout, expected: usize, what: &str) -> Result<(usize, usize)> {
    if l.shape().elem_count() != expected {
        candle_core::bail!(
            "{what}: {} values where the geometry needs {expected}",
            l.shape().elem_count()
        )
    }
    match l.contiguous_offsets() {
        Some(o) => Ok(o),
        None => candle_core::bail!("{what}: the CUDA kernel needs a contiguous input"),
    }
}

/// Runs unfolding kernel `name` (arguments: input, output, total, then `ints`) over
/// `total` outputs; `$input` and `$out` are device buffers of the kernel's types.
macro_rules! launch_fold {
    ($dev:expr, $name:expr, $input:expr, $out:expr, $total:expr, $ints:expr) => {{
        let f = $dev.get_or_load_custom_func($name, MODULE, ptx()?)?;
        let mut l = f.builder();
        let total: usize = $total;
        let total64 = total as i64;
        let ints: [i32; 8] = $ints;
        l.arg($input).arg($out).arg(&total64);
        for v in &ints {
            l.arg(v);
        }
        // SAFETY: the kernels take (input, output, total, h, w, c, k, stride, pad, ho,
        // wo); the input holds every value they read (its size was checked against the
        // geometry) and the output `total` values.
        unsafe { l.launch(elementwise_launch(total)) }.w()?;
    }};
}

/// Im2col (`conv.rs`): NHWC `x: [n, h, w, c]` in f32 or bf16 → `[n·ho·wo, c·k·k]` in its
/// type; `dims` = `[n, h, w, c, k, stride, pad, ho, wo]`.
pub fn im2col(x: &CudaStorage, l: &Layout, dims: [usize; 9]) -> Result<(CudaStorage, Shape)> {
    let [n, h, w, c, k, _, _, ho, wo] = dims;
    let (a, b) = fold_input(l, n * h * w * c, "im2col")?;
    let ints = fold_ints(dims, "im2col")?;
    let dev = device(x).clone();
    let total = n * ho * wo * c * k * k;
    let out = match x.dtype() {
        candle_core::DType::F32 => {
            let v = x.as_cuda_slice::<f32>()?.slice(a..b);
            // SAFETY: every element is written by the kernel.
            let mut cols = unsafe { dev.alloc::<f32>(total.max(1))? };
            launch_fold!(dev, "osrt_im2col_f32", &v, &mut cols, total, ints);
            CudaStorage::wrap_cuda_slice(cols, dev)
        }
        candle_core::DType::BF16 => {
            // Copied as their 16 bits.
            let v = x.as_cuda_slice::<half::bf16>()?.slice(a..b);
            // SAFETY: as above.
            let mut cols = unsafe { dev.alloc::<half::bf16>(total.max(1))? };
            launch_fold!(dev, "osrt_im2col_bf16", &v, &mut cols, total, ints);
            CudaStorage::wrap_cuda_slice(cols, dev)
        }
        other => candle_core::bail!("im2col: input of {other:?}, expected f32 or bf16"),
    };
    Ok((out, Shape::from((n * ho * wo, c * k * k))))
}

/// Col2im (`conv.rs`): `cols: [n·ho·wo, c·k·k]` in f32 or bf16 → `[n, h, w, c]` in f32;
/// `dims` = `[n, h, w, c, k, stride, pad, ho, wo]`.
pub fn col2im(cols: &CudaStorage, l: &Layout, dims: [usize; 9]) -> Result<(CudaStorage, Shape)> {
    let [n, h, w, c, k, _, _, ho, wo] = dims;
    let (a, b) = fold_input(l, n * ho * wo * c * k * k, "col2im")?;
    let ints = fold_ints(dims, "col2im")?;
    let dev = device(cols).clone();
    let total = n * h * w * c;
    // SAFETY: every element is written by the kernel below.
    let mut dx = unsafe { dev.alloc::<f32>(total.max(1))? };
    match cols.dtype() {
        candle_core::DType::F32 => {
            let v = cols.as_cuda_slice::<f32>()?.slice(a..b);
            launch_fold!(dev, "osrt_col2im_f32", &v, &mut dx, total, ints);
        }
        candle_core::DType::BF16 => {
            // Read as their 16 bits.
            let v = cols.as_cuda_slice::<half::bf16>()?.slice(a..b);
            launch_fold!(dev, "osrt_col2im_bf16", &v, &mut dx, total, ints);
        }
        other => candle_core::bail!("col2im: columns of {other:?}, expected f32 or bf16"),
    }
    Ok((
        CudaStorage::wrap_cuda_slice(dx, dev),
        Shape::from((n, h, w, c)),
    ))
}
