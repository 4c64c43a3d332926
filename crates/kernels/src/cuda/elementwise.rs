//! The CUDA launches of the elementwise kernels (grid-stride loops): a bias with its
//! activation, forward and backward, out of place, in place and from bf16; and the
//! convolution's unfolding (im2col) and its adjoint (col2im).

#![allow(unsafe_code)]

use super::launch::{device, elementwise_launch, input, launch, output, rows_cols};
use candle_core::backend::BackendStorage;
use candle_core::{CudaStorage, Layout, Result, Shape};

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
    // SAFETY: the arguments match the kernel's signature; sizes were checked above.
    unsafe {
        launch!(dev, "osrt_bias_act_fwd", elementwise_launch(n);
            &xv, &bv, &mut y, &n64, &cols, &kind, &slope)
    }?;
    Ok((
        CudaStorage::wrap_cuda_slice(y, dev.clone()),
        lx.shape().clone(),
    ))
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
    // SAFETY: the arguments match the kernel's signature; sizes were checked above.
    unsafe {
        launch!(dev, "osrt_bias_act_low", elementwise_launch(n);
            &zv, &bv, &mut y, &n64, &cols, &kind, &slope)
    }?;
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
    // SAFETY: the arguments match the kernel's signature; sizes were checked above.
    unsafe {
        launch!(dev, "osrt_bias_act_fwd_inplace", elementwise_launch(n);
            &mut xv, &bv, &n64, &cols, &kind, &slope)
    }?;
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
    // SAFETY: the arguments match the kernel's signature; sizes were checked above.
    unsafe {
        launch!(dev, "osrt_bias_act_bwd_inplace", elementwise_launch(n);
            &mut xv, &bv, &dyv, &n64, &cols, &kind, &slope)
    }?;
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
    // SAFETY: the arguments match the kernel's signature; sizes were checked above.
    unsafe {
        launch!(dev, "osrt_bias_act_bwd_low", elementwise_launch(n);
            &zv, &bv, &dyv, &mut dz, &n64, &cols, &kind, &slope)
    }?;
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
    // SAFETY: the arguments match the kernel's signature; sizes were checked above.
    unsafe {
        launch!(dev, "osrt_bias_act_bwd", elementwise_launch(n);
            &xv, &bv, &dyv, &mut dz, &n64, &cols, &kind, &slope)
    }?;
    Ok((
        CudaStorage::wrap_cuda_slice(dz, dev.clone()),
        lx.shape().clone(),
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

/// Runs unfolding kernel `$name` (arguments: input, output, total, then `ints`) over
/// `total` outputs; `$input` and `$out` are device buffers of the kernel's types.
macro_rules! launch_fold {
    ($dev:expr, $name:expr, $input:expr, $out:expr, $total:expr, $ints:expr) => {{
        let (dev, name, input, out) = (&$dev, $name, $input, $out);
        let total: usize = $total;
        let total64 = total as i64;
        let [h, w, c, k, stride, pad, ho, wo]: [i32; 8] = $ints;
        // SAFETY: the kernels take (input, output, total, h, w, c, k, stride, pad, ho,
        // wo); the input holds every value they read (its size was checked against the
        // geometry) and the output `total` values.
        unsafe {
            launch!(dev, name, elementwise_launch(total);
                input, out, &total64, &h, &w, &c, &k, &stride, &pad, &ho, &wo)
        }?;
    }};
}

/// Im2col (`cpu::conv`): NHWC `x: [n, h, w, c]` in f32 or bf16 → `[n·ho·wo, c·k·k]` in its
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

/// Col2im (`cpu::conv`): `cols: [n·ho·wo, c·k·k]` in f32 or bf16 → `[n, h, w, c]` in f32;
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
