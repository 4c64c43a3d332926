//! The CUDA launches of the row kernels: LayerNorm and softmax forward and backward (a
//! warp per row), and the column sums of their gradients (fixed chunks of rows, the
//! chunks summed in order).

#![allow(unsafe_code)]

use super::device_kernels::{self as geometry, PARAM_CHUNK};
use super::launch::{column_launch, device, input, launch, output, row_launch, rows_cols};
use candle_core::{CudaStorage, Layout, Result, Shape};

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
    // SAFETY: the arguments match the kernel's signature; sizes were checked above.
    unsafe {
        launch!(dev, "osrt_layer_norm_fwd", row_launch(rows);
            &xv, &gv, &bv, &mut y, &rows, &dd, &eps)
    }?;
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
        // SAFETY: the arguments match the kernel's signature; sizes were checked above.
        unsafe {
            launch!(dev, "osrt_layer_norm_bwd", row_launch(rows);
                &xv, &gv, &dyv, &mut dx, &mut stats, &rows, &dd, &eps)
        }?;
    }
    // SAFETY: as above; `partial` holds 2·d floats per chunk.
    unsafe {
        launch!(dev, "osrt_layer_norm_bwd_params", column_launch(dd, chunks);
            &xv, &dyv, &stats, &mut partial, &rows, &dd, &chunk)
    }?;
    {
        let mut dgb = out.slice_mut(n..n + 2 * d);
        // SAFETY: as above; the last 2·d floats of `out` take the sums.
        unsafe {
            launch!(dev, "osrt_sum_chunks", column_launch(width, 1);
                &partial, &mut dgb, &nchunks, &width)
        }?;
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
    // SAFETY: the arguments match the kernel's signature; sizes were checked above.
    unsafe { launch!(dev, "osrt_softmax_fwd", row_launch(rows); &xv, &mut y, &rows, &dd) }?;
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
    // SAFETY: the arguments match the kernel's signature; sizes were checked above.
    unsafe { launch!(dev, "osrt_softmax_bwd", row_launch(rows); &yv, &dyv, &mut dx, &rows, &dd) }?;
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
    // SAFETY: the arguments match the kernel's signature; sizes were checked above.
    unsafe {
        launch!(dev, "osrt_softmax_bwd_scaled_inplace", row_launch(rows);
            &yv, &mut dyv, &rows, &dd, &scale)
    }?;
    Ok(())
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
    // SAFETY: the arguments match the kernel's signature; `partial` holds d per chunk.
    unsafe {
        launch!(dev, "osrt_column_partials", column_launch(cols, chunks);
            &av, &mut partial, &rows, &cols, &chunk)
    }?;
    // SAFETY: as above.
    unsafe {
        launch!(dev, "osrt_sum_chunks", column_launch(cols, 1);
            &partial, &mut out, &nchunks, &cols)
    }?;
    Ok((
        CudaStorage::wrap_cuda_slice(out, dev.clone()),
        Shape::from(d),
    ))
}
