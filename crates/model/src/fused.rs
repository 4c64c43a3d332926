//! Fused CPU ops with hand-written backward passes: LayerNorm, softmax, erf-GELU, ReLU,
//! the bias add and the whole of a linear layer, a convolution, a whole MLP (`mlp.rs`),
//! the core of multi-head attention (`attention.rs`) and a whole transformer block
//! (`block.rs`); their matrix products go through `gemm.rs`.
//!
//! Why: candle 0.11 composes these from elementwise and broadcast ops, and its backward
//! pass is slow exactly there (a broadcast's gradient is a `sum_keepdim` over leading
//! dims, done as a scalar div/mod loop; every graph node also costs a zero tensor and an
//! add in gradient accumulation). One node per op with a row-wise kernel removes both.
//! Each op computes the same function as the composed version (`nn::LayerNorm` before,
//! `candle_nn::ops::softmax`, `Tensor::gelu_erf`, `broadcast_add`); tests check values and gradients against those
//! and against finite differences.
//!
//! The kernels need contiguous f32 on the CPU; anything else (or `OSRT_FUSED_OPS=0`, or
//! [`with_fused`]`(false, ..)`) takes the composed path.

mod attention;
mod block;
mod buffer;
mod gemm;
mod mix;
mod mlp;

pub use attention::{attention, attention_composed};
pub use block::{BlockParams, block};
pub use mix::slot_mix;
pub use mlp::{MlpAct, MlpLayer, mlp, mlp_cat, mlp_layer_by_layer};

use crate::fastmath;
use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, D, Layout, Result, Shape, Tensor};
use gemm::{MatRef, Threads};
use rayon::prelude::*;
use std::cell::Cell;
use std::sync::{Mutex, OnceLock};

thread_local! {
    static OVERRIDE: Cell<Option<bool>> = const { Cell::new(None) };
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

/// `a · b` (candle's batched matmul) in this thread's [`precision`].
pub fn matmul(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    in_precision(&[a, b], |t| t[0].matmul(&t[1]))
}

/// Runs a product-like op on its f32 operands rounded to bf16 when the thread's precision
/// asks for it (the result back in f32; the casts carry the gradient back to f32).
fn in_precision(ts: &[&Tensor], op: impl FnOnce(&[Tensor]) -> Result<Tensor>) -> Result<Tensor> {
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

fn enabled_by_env() -> bool {
    static ON: OnceLock<bool> = OnceLock::new();
    env_switch("OSRT_FUSED_OPS", &ON)
}

/// Whether the environment leaves the switch `var` on (unset or anything but `0`), read
/// once into `cache`.
fn env_switch(var: &str, cache: &'static OnceLock<bool>) -> bool {
    *cache.get_or_init(|| std::env::var(var).map_or(true, |v| v != "0"))
}

/// Whether graphs built on this thread use the fused ops.
pub fn enabled() -> bool {
    OVERRIDE.with(|o| o.get()).unwrap_or_else(enabled_by_env)
}

/// Runs `f` with the fused ops switched on or off on this thread (comparisons, tests).
pub fn with_fused<T>(on: bool, f: impl FnOnce() -> T) -> T {
    let prev = OVERRIDE.with(|o| o.replace(Some(on)));
    let out = f();
    OVERRIDE.with(|o| o.set(prev));
    out
}

/// Runs `f` on candle's CPU thread pool (`Device::with_context`), with this thread's
/// fused-ops setting carried along (it is thread-local). Every parallel section inside —
/// gemm, candle's elementwise maps, the fused ops — then runs on the pool's own threads;
/// called from outside a pool, each of the thousands of sections in a step is handed
/// across threads and waited for (the step took 1.04–1.12× as long at 1 thread in
/// interleaved runs: docs/performance.md).
pub fn on_device_pool<T: Send>(device: &candle_core::Device, f: impl FnOnce() -> T + Send) -> T {
    let (on, p) = (enabled(), precision());
    device.with_context(|| with_fused(on, || with_precision(p, f)))
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

pub(crate) fn f32_slice<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> Result<&'a [f32]> {
    let CpuStorage::F32(v) = s else {
        candle_core::bail!("{what}: fused ops take f32");
    };
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&v[a..b]),
        None => candle_core::bail!("{what}: fused ops take contiguous tensors"),
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
    enabled()
        && ts
            .iter()
            .all(|t| t.dtype() == candle_core::DType::F32 && t.device().is_cpu() && t.rank() >= 1)
}

// ---------------------------------------------------------------- LayerNorm

struct LayerNormOp {
    eps: f32,
}

/// Mean and 1/σ of one row.
fn row_stats(x: &[f32], eps: f32) -> (f32, f32) {
    let d = x.len() as f32;
    let mean = x.iter().sum::<f32>() / d;
    let var = x.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / d;
    (mean, 1.0 / (var + eps).sqrt())
}

impl CustomOp3 for LayerNormOp {
    fn name(&self) -> &'static str {
        "osrt-layer-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1, "layer_norm x")?;
        let g = f32_slice(s2, l2, "layer_norm weight")?;
        let b = f32_slice(s3, l3, "layer_norm bias")?;
        let d = g.len();
        let per = d * ROWS_PER_TASK;
        let out = buffer::par_filled(x.len(), per, |t, o| {
            let x = &x[t * per..][..o.len()];
            for (o, x) in o.chunks_mut(d).zip(x.chunks(d)) {
                let (mean, rstd) = row_stats(x, self.eps);
                for i in 0..d {
                    o[i] = (x[i] - mean) * rstd * g[i] + b[i];
                }
            }
        });
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        g: &Tensor,
        _b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let d = g.elem_count();
        let rows = x.elem_count() / d;
        let packed = x.apply_op3_no_bwd(g, &grad.contiguous()?, &LayerNormBwd { eps: self.eps })?;
        let dx = packed.narrow(0, 0, rows)?.reshape(x.shape())?;
        let dg = packed.get(rows)?.reshape(g.shape())?;
        let db = packed.get(rows + 1)?.reshape(g.shape())?;
        Ok((Some(dx), Some(dg), Some(db)))
    }
}

/// LayerNorm's backward in one pass: `[rows + 2, d]` = dx rows, then dγ, then dβ.
struct LayerNormBwd {
    eps: f32,
}

impl CustomOp3 for LayerNormBwd {
    fn name(&self) -> &'static str {
        "osrt-layer-norm-bwd"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1, "layer_norm backward x")?;
        let g = f32_slice(s2, l2, "layer_norm backward weight")?;
        let dy = f32_slice(s3, l3, "layer_norm backward gradient")?;
        let d = g.len();
        let rows = x.len() / d;
        let per = d * ROWS_PER_TASK;
        // Per task: dx rows, and partial dγ / dβ sums reduced afterwards in task order
        // (a fixed order: the result does not depend on the thread count's scheduling).
        // The last 2·d values (dγ, dβ) are left zero by the tasks.
        let partials = Mutex::new(vec![None; rows.div_ceil(ROWS_PER_TASK)]);
        let mut out = buffer::par_filled((rows + 2) * d, per, |t, o| {
            let start = t * per;
            let n = (rows * d).saturating_sub(start).min(o.len());
            if n == 0 {
                return;
            }
            let (x, dy) = (&x[start..start + n], &dy[start..start + n]);
            let mut acc = vec![0f32; 2 * d];
            let mut xhat = vec![0f32; d];
            for ((dx, x), dy) in o[..n].chunks_mut(d).zip(x.chunks(d)).zip(dy.chunks(d)) {
                let (mean, rstd) = row_stats(x, self.eps);
                let (mut m1, mut m2) = (0f32, 0f32);
                for i in 0..d {
                    xhat[i] = (x[i] - mean) * rstd;
                    let gy = dy[i] * g[i];
                    m1 += gy;
                    m2 += gy * xhat[i];
                    acc[i] += dy[i] * xhat[i];
                    acc[d + i] += dy[i];
                }
                let (m1, m2) = (m1 / d as f32, m2 / d as f32);
                for i in 0..d {
                    dx[i] = rstd * (dy[i] * g[i] - m1 - xhat[i] * m2);
                }
            }
            partials.lock().unwrap_or_else(|e| e.into_inner())[t] = Some(acc);
        });
        let dgb = &mut out[rows * d..];
        let partials = partials.into_inner().unwrap_or_else(|e| e.into_inner());
        for p in partials.into_iter().flatten() {
            for (o, v) in dgb.iter_mut().zip(p) {
                *o += v;
            }
        }
        Ok((CpuStorage::F32(out), Shape::from((rows + 2, d))))
    }
}

/// LayerNorm over the last dimension: `x: [.., d]`, `weight`, `bias: [d]` → `[.., d]`.
pub fn layer_norm(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Tensor> {
    if usable(&[x, weight, bias]) {
        return x.contiguous()?.apply_op3(
            &weight.contiguous()?,
            &bias.contiguous()?,
            LayerNormOp { eps: eps as f32 },
        );
    }
    let mean = x.mean_keepdim(D::Minus1)?;
    let centred = x.broadcast_sub(&mean)?;
    let var = centred.sqr()?.mean_keepdim(D::Minus1)?;
    let normed = centred.broadcast_div(&(var + eps)?.sqrt()?)?;
    normed.broadcast_mul(weight)?.broadcast_add(bias)
}

// ---------------------------------------------------------------- softmax

/// `o = softmax(x)` of one row.
fn softmax_row(o: &mut [f32], x: &[f32]) {
    // Shift by the row's maximum: exp never overflows, the largest term is 1.
    let m = x.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    // The exp kernel vectorises; the ordered sum stays a separate loop.
    fastmath::exp_shifted_slice(o, x, m);
    let sum: f32 = o.iter().sum();
    let inv = 1.0 / sum;
    o.iter_mut().for_each(|v| *v *= inv);
}

/// `o = y ⊙ (dy − Σ y ⊙ dy)` of one row: the softmax's input gradient from its output `y`.
fn softmax_row_grad(o: &mut [f32], y: &[f32], dy: &[f32]) {
    let dot: f32 = y.iter().zip(dy).map(|(a, b)| a * b).sum();
    for ((o, y), dy) in o.iter_mut().zip(y).zip(dy) {
        *o = y * (dy - dot);
    }
}

struct SoftmaxOp;

impl CustomOp1 for SoftmaxOp {
    fn name(&self) -> &'static str {
        "osrt-softmax-last-dim"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s, l, "softmax")?;
        let d = l.dims().last().copied().unwrap_or(1).max(1);
        let mut out = vec![0f32; x.len()];
        out.par_chunks_mut(d * ROWS_PER_TASK)
            .zip(x.par_chunks(d * ROWS_PER_TASK))
            .for_each(|(o, x)| {
                for (o, x) in o.chunks_mut(d).zip(x.chunks(d)) {
                    softmax_row(o, x);
                }
            });
        Ok((CpuStorage::F32(out), l.shape().clone()))
    }

    fn bwd(&self, _x: &Tensor, res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(
            res.apply_op2_no_bwd(&grad.contiguous()?, &SoftmaxBwd)?,
        ))
    }
}

/// `dx = y ⊙ (dy − Σ y ⊙ dy)` per row, from the softmax output `y`.
struct SoftmaxBwd;

impl CustomOp2 for SoftmaxBwd {
    fn name(&self) -> &'static str {
        "osrt-softmax-last-dim-bwd"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let y = f32_slice(s1, l1, "softmax backward output")?;
        let dy = f32_slice(s2, l2, "softmax backward gradient")?;
        let d = l1.dims().last().copied().unwrap_or(1).max(1);
        let mut out = vec![0f32; y.len()];
        out.par_chunks_mut(d * ROWS_PER_TASK)
            .zip(
                y.par_chunks(d * ROWS_PER_TASK)
                    .zip(dy.par_chunks(d * ROWS_PER_TASK)),
            )
            .for_each(|(o, (y, dy))| {
                for ((o, y), dy) in o.chunks_mut(d).zip(y.chunks(d)).zip(dy.chunks(d)) {
                    softmax_row_grad(o, y, dy);
                }
            });
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }
}

/// Softmax over dimension `dim` (any; other than the last it goes through a transpose).
pub fn softmax<Dim: candle_core::shape::Dim>(x: &Tensor, dim: Dim) -> Result<Tensor> {
    let dim = dim.to_index(x.shape(), "softmax")?;
    if !usable(&[x]) {
        return candle_nn::ops::softmax(x, dim);
    }
    let last = x.rank() - 1;
    if dim == last {
        x.contiguous()?.apply_op1(SoftmaxOp)
    } else {
        x.transpose(dim, last)?
            .contiguous()?
            .apply_op1(SoftmaxOp)?
            .transpose(dim, last)
    }
}

// ---------------------------------------------------------------- convolution

/// Geometry of a square-kernel convolution over NHWC input.
#[derive(Debug, Clone, Copy)]
struct ConvGeom {
    n: usize,
    h: usize,
    w: usize,
    c: usize,
    k: usize,
    stride: usize,
    pad: usize,
    ho: usize,
    wo: usize,
}

impl ConvGeom {
    /// Input position of output `(oy, ox)` at kernel tap `(ky, kx)`, if inside the image.
    #[inline]
    fn source(&self, oy: usize, ox: usize, ky: usize, kx: usize) -> Option<(usize, usize)> {
        let iy = (oy * self.stride + ky).checked_sub(self.pad)?;
        let ix = (ox * self.stride + kx).checked_sub(self.pad)?;
        (iy < self.h && ix < self.w).then_some((iy, ix))
    }

    /// Columns per patch, ordered (channel, ky, kx) like a `[c_out, c_in, k, k]` kernel.
    fn patch(&self) -> usize {
        self.c * self.k * self.k
    }
}

/// Patches of NHWC input as rows: `[n·ho·wo, c·k·k]`.
struct Im2Col(ConvGeom);

impl CustomOp1 for Im2Col {
    fn name(&self) -> &'static str {
        "osrt-im2col"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s, l, "im2col")?;
        let g = self.0;
        let p = g.patch();
        // Each task zeroes its chunk (the padding stays 0) before writing the patches.
        let out = buffer::par_filled(g.n * g.ho * g.wo * p, p * g.wo, |row, o| {
            let (b, oy) = (row / g.ho, row % g.ho);
            for ox in 0..g.wo {
                let o = &mut o[ox * p..(ox + 1) * p];
                for ky in 0..g.k {
                    for kx in 0..g.k {
                        if let Some((iy, ix)) = g.source(oy, ox, ky, kx) {
                            let src = &x[((b * g.h + iy) * g.w + ix) * g.c..][..g.c];
                            for (ci, v) in src.iter().enumerate() {
                                o[(ci * g.k + ky) * g.k + kx] = *v;
                            }
                        }
                    }
                }
            }
        });
        Ok((CpuStorage::F32(out), Shape::from((g.n * g.ho * g.wo, p))))
    }

    fn bwd(&self, _x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(grad.contiguous()?.apply_op1_no_bwd(&Col2Im(self.0))?))
    }
}

/// Im2col's adjoint: patch gradients summed back into NHWC `[n, h, w, c]`.
struct Col2Im(ConvGeom);

impl CustomOp1 for Col2Im {
    fn name(&self) -> &'static str {
        "osrt-col2im"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let cols = f32_slice(s, l, "col2im")?;
        let g = self.0;
        let p = g.patch();
        let img = g.h * g.w * g.c;
        let mut out = vec![0f32; g.n * img];
        // One task per image: every write of an image lands in its own slice.
        out.par_chunks_mut(img).enumerate().for_each(|(b, o)| {
            for oy in 0..g.ho {
                for ox in 0..g.wo {
                    let row = &cols[((b * g.ho + oy) * g.wo + ox) * p..][..p];
                    for ky in 0..g.k {
                        for kx in 0..g.k {
                            if let Some((iy, ix)) = g.source(oy, ox, ky, kx) {
                                let dst = &mut o[(iy * g.w + ix) * g.c..][..g.c];
                                for (ci, d) in dst.iter_mut().enumerate() {
                                    *d += row[(ci * g.k + ky) * g.k + kx];
                                }
                            }
                        }
                    }
                }
            }
        });
        Ok((CpuStorage::F32(out), Shape::from((g.n, g.h, g.w, g.c))))
    }
}

/// 2-D convolution without bias on channels-last input, as im2col + one matmul.
///
/// Why: candle's CPU `conv2d` is a direct loop and its input gradient a transposed
/// convolution; together they were ~40 % of a CPU train step. Here the work is one gemm
/// each way plus two memory passes. Channels-last also lets the encoder skip permutes.
///
/// # Shapes
/// `x: [n, h, w, c_in]`, `kernel: [c_out, c_in, k, k]` → `[n, h_out, w_out, c_out]`
pub fn conv2d_nhwc(x: &Tensor, kernel: &Tensor, stride: usize, padding: usize) -> Result<Tensor> {
    let (n, h, w, c) = x.dims4()?;
    let (co, ci, k, k2) = kernel.dims4()?;
    if ci != c || k != k2 {
        candle_core::bail!(
            "conv2d: input has {c} channels, kernel is [{co}, {ci}, {k}, {k2}] (square, c_in = {c})"
        );
    }
    if h + 2 * padding < k || w + 2 * padding < k || stride == 0 {
        candle_core::bail!(
            "conv2d: a {k}×{k} kernel does not fit a {h}×{w} input padded by {padding}"
        );
    }
    let ho = (h + 2 * padding - k) / stride + 1;
    let wo = (w + 2 * padding - k) / stride + 1;
    if !usable(&[x, kernel]) {
        return in_precision(&[x, kernel], |t| {
            t[0].permute((0, 3, 1, 2))?
                .conv2d(&t[1], padding, stride, 1, 1)?
                .permute((0, 2, 3, 1))
        });
    }
    let geom = ConvGeom {
        n,
        h,
        w,
        c,
        k,
        stride,
        pad: padding,
        ho,
        wo,
    };
    let op = ConvOp {
        geom,
        co,
        keep: x.track_op() || kernel.track_op(),
        saved: Kept::new(None),
    };
    x.contiguous()?.apply_op2(&kernel.contiguous()?, op)
}

/// The convolution as one graph node: im2col and the product with the kernel inside.
///
/// Why one node: as im2col, `linear` and a reshape it was three, and candle's backward
/// gives each node a zero tensor and an add of its gradient; the columns are the largest
/// tensors of the encoder (`[4096, 576]` on the CPU preset, 9 MB), so those accumulations
/// were a serial share of the step. The columns are kept for the kernel's gradient
/// instead. The arithmetic is `linear`'s on the same columns (the same products), and for
/// an input that is data (the image, the ray encoding) the backward pass skips the
/// columns' gradient and so the col2im scatter.
struct ConvOp {
    geom: ConvGeom,
    co: usize,
    /// Whether a backward pass can follow: only then are the columns kept.
    keep: bool,
    saved: Kept<CpuStorage>,
}

impl ConvOp {
    /// The kernel `[c_out, c_in, k, k]` as the `[c_out, c_in·k·k]` matrix the columns
    /// multiply.
    fn kernel_matrix(&self, l: &Layout) -> Layout {
        Layout::contiguous_with_offset((self.co, self.geom.patch()), l.start_offset())
    }
}

impl CustomOp2 for ConvOp {
    fn name(&self) -> &'static str {
        "osrt-conv2d"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let g = self.geom;
        let (cols, _) = Im2Col(g).cpu_fwd(s1, l1)?;
        let rows = g.n * g.ho * g.wo;
        let y = matmul_xwt(
            &cols,
            &Layout::contiguous((rows, g.patch())),
            s2,
            &self.kernel_matrix(l2),
        )?;
        if self.keep {
            self.saved.put(cols);
        }
        Ok((CpuStorage::F32(y), Shape::from((g.n, g.ho, g.wo, self.co))))
    }

    fn bwd(
        &self,
        x: &Tensor,
        kernel: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        // Taken, not cloned: a second backward through the same graph recomputes them.
        let bwd = ConvBwd {
            geom: self.geom,
            co: self.co,
            saved: Kept::new(self.saved.take()),
            input_grad: x.track_op(),
        };
        let flat = x.apply_op3_no_bwd(kernel, &grad.contiguous()?, &bwd)?;
        let nk = kernel.elem_count();
        let dk = flat
            .narrow(0, flat.dim(0)? - nk, nk)?
            .reshape(kernel.shape())?;
        let dx = match bwd.input_grad {
            true => Some(flat.narrow(0, 0, x.elem_count())?.reshape(x.shape())?),
            false => None,
        };
        Ok((dx, Some(dk)))
    }
}

/// The backward pass of [`ConvOp`] as a no-grad op over `(x, kernel, grad)`: one flat
/// buffer `[dx (when the input carries a gradient) | d kernel]`.
struct ConvBwd {
    geom: ConvGeom,
    co: usize,
    saved: Kept<CpuStorage>,
    input_grad: bool,
}

impl CustomOp3 for ConvBwd {
    fn name(&self) -> &'static str {
        "osrt-conv2d-bwd"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let g = self.geom;
        let (rows, p) = (g.n * g.ho * g.wo, g.patch());
        let cols = match self.saved.take() {
            Some(c) => c,
            None => Im2Col(g).cpu_fwd(s1, l1)?.0,
        };
        let cols_l = Layout::contiguous((rows, p));
        let grad_l = Layout::contiguous_with_offset((rows, self.co), l3.start_offset());
        // d kernel = gradᵀ · columns: `[c_out, rows] · [rows, c·k·k]`.
        let dk = weight_grad(s3, &grad_l, &cols, &cols_l)?;
        let mut out = match self.input_grad {
            true => {
                // d columns = grad · kernel, then scattered back to the image.
                let kmat = Layout::contiguous_with_offset((self.co, p), l2.start_offset());
                let dcols = gemm::matmul(
                    MatRef::of(s3, &grad_l)?,
                    MatRef::of(s2, &kmat)?,
                    Threads::Pool,
                )?;
                match Col2Im(g).cpu_fwd(&CpuStorage::F32(dcols), &cols_l)?.0 {
                    CpuStorage::F32(v) => v,
                    _ => candle_core::bail!("conv2d: fused ops take f32"),
                }
            }
            false => Vec::with_capacity(dk.len()),
        };
        out.extend_from_slice(&dk);
        let len = out.len();
        Ok((CpuStorage::F32(out), Shape::from(len)))
    }
}

// ---------------------------------------------------------------- GELU (erf)

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
fn par_elementwise(x: &[f32], kernel: impl Fn(&mut [f32], &[f32]) + Sync) -> Vec<f32> {
    const E: usize = ELEMENTS_PER_TASK;
    buffer::par_filled(x.len(), E, |i, o| kernel(o, &x[i * E..][..o.len()]))
}

/// `dx = kernel(x, dy)`, chunk by chunk in parallel: an elementwise op's backward.
fn par_elementwise_grad(
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
    if usable(&[x]) {
        return x.contiguous()?.apply_op1(LeakyReluOp { slope: 0.0 });
    }
    x.relu()
}

/// `x` where `x ≥ 0`, `slope · x` below (gradient 1 at 0); composed:
/// `maximum(x, slope · x)` for slopes in (0, 1).
pub fn leaky_relu(x: &Tensor, slope: f32) -> Result<Tensor> {
    if usable(&[x]) {
        return x.contiguous()?.apply_op1(LeakyReluOp { slope });
    }
    x.maximum(&(x * slope as f64)?)
}

// ---------------------------------------------------------------- bias add

/// `rows[i, :] += b` for every row of a `[rows, b.len()]` buffer, in place.
fn add_bias_rows(rows: &mut [f32], b: &[f32]) {
    let d = b.len().max(1);
    rows.par_chunks_mut(d * ROWS_PER_TASK).for_each(|o| {
        for row in o.chunks_mut(d) {
            row.iter_mut().zip(b).for_each(|(o, b)| *o += b);
        }
    });
}

struct BiasAddOp;

impl CustomOp2 for BiasAddOp {
    fn name(&self) -> &'static str {
        "osrt-bias-add"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1, "bias add x")?;
        let b = f32_slice(s2, l2, "bias add bias")?;
        let mut out = x.to_vec();
        add_bias_rows(&mut out, b);
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    fn bwd(
        &self,
        _x: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let db = grad
            .contiguous()?
            .apply_op1_no_bwd(&ColumnSum { d: b.elem_count() })?
            .reshape(b.shape())?;
        Ok((Some(grad.clone()), Some(db)))
    }
}

/// Sum over rows of a `[rows, d]` buffer → `[d]`, in a fixed order of row blocks.
struct ColumnSum {
    d: usize,
}

impl CustomOp1 for ColumnSum {
    fn name(&self) -> &'static str {
        "osrt-column-sum"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = f32_slice(s, l, "column sum")?;
        let d = self.d;
        let partials: Vec<Vec<f32>> = x
            .par_chunks(d * ROWS_PER_TASK * 4)
            .map(|block| {
                let mut acc = vec![0f32; d];
                for row in block.chunks(d) {
                    acc.iter_mut().zip(row).for_each(|(a, v)| *a += v);
                }
                acc
            })
            .collect();
        let mut out = vec![0f32; d];
        for p in partials {
            out.iter_mut().zip(p).for_each(|(o, v)| *o += v);
        }
        Ok((CpuStorage::F32(out), Shape::from(d)))
    }
}

/// `x: [.., d] + bias: [d]`.
pub fn bias_add(x: &Tensor, bias: &Tensor) -> Result<Tensor> {
    if usable(&[x, bias]) && x.dim(D::Minus1)? == bias.elem_count() && bias.rank() == 1 {
        return x.contiguous()?.apply_op2(&bias.contiguous()?, BiasAddOp);
    }
    x.broadcast_add(bias)
}

// ---------------------------------------------------------------- linear

/// `x: [n, in] · W: [out, in]ᵀ` as an f32 buffer `[n, out]`.
fn matmul_xwt(s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<Vec<f32>> {
    let (x, w) = (MatRef::of(s1, l1)?, MatRef::of(s2, l2)?);
    if x.dims().1 != w.dims().1 {
        candle_core::bail!("linear: input {:?}, weight {:?}", x.dims(), w.dims());
    }
    gemm::matmul(x, w.t(), Threads::Pool)
}

/// Rows per block of a weight gradient's split reduction ([`weight_grad`]).
const WGRAD_BLOCK_ROWS: usize = 2048;

/// The weight gradient `aᵀ·b` of a linear layer, `a: [rows, o]` (the output gradient),
/// `b: [rows, k]` (the layer input), both contiguous → `[o, k]`.
///
/// Why not one gemm: gemm parallelises over blocks of the output and walks the reduction
/// (here the rows, 8,192 target rays in the decoder) in one sequence, so for a 128 × 128
/// output the second core mostly waits: at 2 threads such a product took 1.5–1.7 ms
/// against 2.5–2.7 at 1 (and 4.2–4.5 against 5.6–5.8 ms for 128 × 230). Here the rows are
/// cut into fixed blocks of [`WGRAD_BLOCK_ROWS`], the blocks' products computed in
/// parallel and summed in block order: 1.3 and 2.8–3.0 ms at 2 threads. The blocks do not
/// depend on the thread count, so neither do the bits.
fn weight_grad(a: &CpuStorage, a_l: &Layout, b: &CpuStorage, b_l: &Layout) -> Result<Vec<f32>> {
    let (a, b) = (MatRef::of(a, a_l)?, MatRef::of(b, b_l)?);
    let (rows, rows_b) = (a.dims().0, b.dims().0);
    if rows != rows_b {
        candle_core::bail!("weight gradient: {:?}ᵀ · {:?}", a.dims(), b.dims());
    }
    let block = |r0: usize, len: usize, threads: Threads| -> Result<Vec<f32>> {
        gemm::matmul(a.rows(r0, len)?.t(), b.rows(r0, len)?, threads)
    };
    let blocks = rows.div_ceil(WGRAD_BLOCK_ROWS);
    if blocks <= 1 {
        return block(0, rows, Threads::Pool);
    }
    let parts: Vec<Vec<f32>> = (0..blocks)
        .into_par_iter()
        .map(|i| {
            let r0 = i * WGRAD_BLOCK_ROWS;
            block(r0, WGRAD_BLOCK_ROWS.min(rows - r0), Threads::One)
        })
        .collect::<Result<_>>()?;
    let mut parts = parts.into_iter();
    let mut sum = parts.next().unwrap_or_default();
    for p in parts {
        sum.iter_mut().zip(p).for_each(|(s, v)| *s += v);
    }
    Ok(sum)
}

/// [`weight_grad`] as a no-grad op over `(grad: [rows, o], x: [rows, k])` → `[o, k]`.
struct WeightGrad;

impl CustomOp2 for WeightGrad {
    fn name(&self) -> &'static str {
        "osrt-weight-grad"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (o, k) = (l1.dims()[1], l2.dims()[1]);
        Ok((
            CpuStorage::F32(weight_grad(s1, l1, s2, l2)?),
            Shape::from((o, k)),
        ))
    }
}

/// `grad: [rows, o] · W: [o, k]` → `[rows, k]` as a no-grad op: a linear layer's input
/// gradient.
struct InputGrad;

impl CustomOp2 for InputGrad {
    fn name(&self) -> &'static str {
        "osrt-input-grad"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (g, w) = (MatRef::of(s1, l1)?, MatRef::of(s2, l2)?);
        let dx = gemm::matmul(g, w, Threads::Pool)?;
        Ok((CpuStorage::F32(dx), Shape::from((g.dims().0, w.dims().1))))
    }
}

/// Gradients of `x·Wᵀ` for upstream `grad: [.., out]`: `dx = grad·W` only when `x` carries
/// a gradient (candle's matmul backward computes it for data inputs too), `dW = gradᵀ·x`.
fn linear_grads(x: &Tensor, w: &Tensor, grad: &Tensor) -> Result<(Option<Tensor>, Tensor)> {
    // `x: [.., in]` and `grad: [.., out]` as the 2-D `[rows, ·]` views the op computed on.
    let (x2, grad) = (
        x.reshape(((), x.dim(D::Minus1)?))?.contiguous()?,
        grad.reshape(((), w.dim(0)?))?.contiguous()?,
    );
    let dx = if x.track_op() {
        let dx = grad.apply_op2_no_bwd(&w.contiguous()?, &InputGrad)?;
        Some(dx.reshape(x.shape())?)
    } else {
        None
    };
    Ok((dx, grad.apply_op2_no_bwd(&x2, &WeightGrad)?))
}

/// A contiguous `[.., k]` layout as the 2-D `[rows, k]` the matmul kernels take: the
/// same memory with the leading dims flattened. The ops take N-D inputs themselves
/// because a `reshape` around them would be two more graph nodes, each costing a zero
/// tensor and an add of the whole activation in candle's backward pass.
fn rows_layout(l: &Layout) -> Result<Layout> {
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
fn with_last_dim(l: &Layout, last: usize) -> Shape {
    let mut dims = l.dims().to_vec();
    if let Some(d) = dims.last_mut() {
        *d = last;
    }
    Shape::from(dims)
}

/// `y = x·Wᵀ + b` as one graph node (`x: [.., in]`, `W: [out, in]`, `b: [out]`): the bias
/// is added into the matmul's output in place, and backward skips `dx` for data inputs
/// and one `[n, out]` gradient accumulation (zeros + add) that matmul + bias add cost.
struct LinearOp;

impl CustomOp3 for LinearOp {
    fn name(&self) -> &'static str {
        "osrt-linear"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let b = f32_slice(s3, l3, "linear bias")?;
        let rows = rows_layout(l1)?;
        let mut y = matmul_xwt(s1, &rows, s2, l2)?;
        let (n, d) = (rows.dims()[0], b.len());
        if y.len() != n * d {
            candle_core::bail!("linear: bias of {d} for an output of {} values", y.len());
        }
        add_bias_rows(&mut y, b);
        Ok((CpuStorage::F32(y), with_last_dim(l1, d)))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        let (dx, dw) = linear_grads(x, w, &grad)?;
        let db = grad.apply_op1_no_bwd(&ColumnSum { d: b.elem_count() })?;
        Ok((dx, Some(dw), Some(db)))
    }
}

/// `y = x·Wᵀ` as one graph node (see [`LinearOp`]).
struct LinearNoBiasOp;

impl CustomOp2 for LinearNoBiasOp {
    fn name(&self) -> &'static str {
        "osrt-linear-no-bias"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let y = matmul_xwt(s1, &rows_layout(l1)?, s2, l2)?;
        Ok((CpuStorage::F32(y), with_last_dim(l1, l2.dims()[0])))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (dx, dw) = linear_grads(x, w, &grad.contiguous()?)?;
        Ok((dx, Some(dw)))
    }
}

/// `x: [.., in]`, `weight: [out, in]`, `bias: [out]` → `x·weightᵀ + bias: [.., out]`, one
/// 2-D product over all leading dims (candle's broadcast matmul is slower).
pub fn linear(x: &Tensor, weight: &Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
    let fits = weight.rank() == 2 && bias.is_none_or(|b| b.rank() == 1);
    let mut all = vec![x, weight];
    all.extend(bias);
    if fits && usable(&all) {
        let (x, w) = (x.contiguous()?, weight.contiguous()?);
        return match bias {
            Some(b) => x.apply_op3(&w, &b.contiguous()?, LinearOp),
            None => x.apply_op2(&w, LinearNoBiasOp),
        };
    }
    let composed = |x: &Tensor| -> Result<Tensor> {
        let y = matmul(x, &weight.t()?)?;
        match bias {
            Some(b) => bias_add(&y, b),
            None => Ok(y),
        }
    };
    if x.rank() == 2 {
        return composed(x);
    }
    let Some((&k, lead)) = x.dims().split_last() else {
        candle_core::bail!("linear: a scalar input")
    };
    let mut out = lead.to_vec();
    out.push(weight.dim(0)?);
    composed(&x.reshape(((), k))?)?.reshape(out)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use candle_core::{Device, Var};
    use rand::SeedableRng;

    pub(super) fn randn(shape: &[usize], scale: f32, seed: u64) -> Tensor {
        let n: usize = shape.iter().product();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let v: Vec<f32> = crate::params::normal_samples(&mut rng, n)
            .into_iter()
            .map(|x| x * scale)
            .collect();
        Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
    }

    /// bf16 products (the composed path, as on a GPU): values and gradients within bf16's
    /// rounding of the f32 ones, the gradient arrives in f32, and inputs near f32's range
    /// limits neither underflow nor overflow (bf16 keeps f32's exponent range). The
    /// precision setting also travels to the pool thread.
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

    pub(super) fn max_abs(a: &Tensor) -> f32 {
        a.abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar()
            .unwrap()
    }

    pub(crate) fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    }

    /// Value and gradients of `Σ f(args) · w` (w fixed random), fused and composed.
    pub(super) fn both(
        args: &[Tensor],
        f: impl Fn(&[Tensor]) -> Result<Tensor>,
    ) -> [(Tensor, Vec<Tensor>); 2] {
        [true, false].map(|on| {
            with_fused(on, || {
                let vars: Vec<Var> = args.iter().map(|a| Var::from_tensor(a).unwrap()).collect();
                let ts: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();
                let y = f(&ts).unwrap();
                let w = randn(y.dims(), 1.0, 99);
                let loss = (&y * &w).unwrap().sum_all().unwrap();
                let g = loss.backward().unwrap();
                let grads = vars
                    .iter()
                    .map(|v| g.get(v.as_tensor()).unwrap().clone())
                    .collect();
                (y, grads)
            })
        })
    }

    pub(super) fn assert_matches_composed(
        args: &[Tensor],
        f: impl Fn(&[Tensor]) -> Result<Tensor>,
        tol: f32,
    ) {
        let [(yf, gf), (yc, gc)] = both(args, f);
        assert!(
            max_diff(&yf, &yc) <= tol,
            "forward differs by {}",
            max_diff(&yf, &yc)
        );
        for (i, (a, b)) in gf.iter().zip(&gc).enumerate() {
            let d = max_diff(a, b);
            assert!(d <= tol, "gradient {i} differs by {d}");
            assert!(
                a.flatten_all()
                    .unwrap()
                    .to_vec1::<f32>()
                    .unwrap()
                    .iter()
                    .all(|v| v.is_finite())
            );
        }
    }

    /// Central finite differences of `Σ f(args) · w`, computed in f64 (where `f` takes the
    /// composed path: the same function), against the fused backward in f32.
    pub(super) fn finite_difference_check(
        args: &[Tensor],
        f: impl Fn(&[Tensor]) -> Result<Tensor>,
    ) {
        let [(y, grads), _] = both(args, &f);
        let f64_ = candle_core::DType::F64;
        let w64 = randn(y.dims(), 1.0, 99).to_dtype(f64_).unwrap();
        let args64: Vec<Tensor> = args.iter().map(|a| a.to_dtype(f64_).unwrap()).collect();
        let h = 1e-5;
        for (a, grad) in grads.iter().enumerate() {
            let base: Vec<f64> = args64[a].flatten_all().unwrap().to_vec1().unwrap();
            let g: Vec<f32> = grad.flatten_all().unwrap().to_vec1().unwrap();
            for i in (0..base.len()).step_by((base.len() / 12).max(1)) {
                let eval = |delta: f64| -> f64 {
                    let mut v = base.clone();
                    v[i] += delta;
                    let mut xs = args64.clone();
                    xs[a] = Tensor::from_vec(v, args64[a].shape(), &Device::Cpu).unwrap();
                    (f(&xs).unwrap() * &w64)
                        .unwrap()
                        .sum_all()
                        .unwrap()
                        .to_scalar::<f64>()
                        .unwrap()
                };
                let num = (eval(h) - eval(-h)) / (2.0 * h);
                let err = (num - g[i] as f64).abs();
                assert!(
                    err <= 1e-3 * (1.0 + num.abs()),
                    "arg {a} element {i}: finite difference {num}, backward {}",
                    g[i]
                );
            }
        }
    }

    fn ln(ts: &[Tensor]) -> Result<Tensor> {
        layer_norm(&ts[0], &ts[1], &ts[2], 1e-5)
    }

    #[test]
    fn layer_norm_matches_the_composed_version_and_finite_differences() {
        let args = [
            randn(&[3, 70, 16], 1.0, 1),
            randn(&[16], 1.0, 2),
            randn(&[16], 1.0, 3),
        ];
        assert_matches_composed(&args, ln, 2e-5);
        let small = [
            randn(&[2, 3, 8], 1.0, 4),
            randn(&[8], 1.0, 5),
            randn(&[8], 1.0, 6),
        ];
        finite_difference_check(&small, ln);
    }

    #[test]
    fn layer_norm_is_finite_on_extreme_and_constant_rows() {
        // Large magnitudes, a constant row (zero variance) and tiny values.
        let mut v = vec![1e6f32, -3e6, 2e6, 5e5];
        v.extend([7.0f32; 4]);
        v.extend([1e-20f32, -1e-20, 0.0, 2e-20]);
        let x = Tensor::from_vec(v, (3, 4), &Device::Cpu).unwrap();
        let args = [x, randn(&[4], 1.0, 7), randn(&[4], 1.0, 8)];
        let [(y, grads), _] = both(&args, ln);
        for t in std::iter::once(&y).chain(&grads) {
            let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            assert!(v.iter().all(|x| x.is_finite()), "{v:?}");
        }
        // The constant row normalises to exactly the bias.
        let row: Vec<f32> = y.get(1).unwrap().to_vec1().unwrap();
        let bias: Vec<f32> = args[2].to_vec1().unwrap();
        assert_eq!(row, bias);
        assert_matches_composed(&args, ln, 1e-3);
    }

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
    fn linear_matches_the_composed_version_and_finite_differences() {
        let (x, w, b) = (
            randn(&[37, 11], 1.0, 31),
            randn(&[6, 11], 1.0, 32),
            randn(&[6], 1.0, 33),
        );
        let with_bias = [x.clone(), w.clone(), b];
        assert_matches_composed(&with_bias, |t| linear(&t[0], &t[1], Some(&t[2])), 1e-5);
        assert_matches_composed(&with_bias[..2], |t| linear(&t[0], &t[1], None), 1e-5);
        let small = [
            randn(&[4, 5], 1.0, 34),
            randn(&[3, 5], 1.0, 35),
            randn(&[3], 1.0, 36),
        ];
        finite_difference_check(&small, |t| linear(&t[0], &t[1], Some(&t[2])));
        finite_difference_check(&small[..2], |t| linear(&t[0], &t[1], None));
        // Extremes: huge and constant rows give the composed op's values and finite
        // gradients where the composed op's are finite.
        let big = [
            Tensor::new(&[[1e18f32, -1e18, 3.0], [2.0, 2.0, 2.0]], &Device::Cpu).unwrap(),
            randn(&[4, 3], 1.0, 37),
            randn(&[4], 1.0, 38),
        ];
        let [(yf, gf), (yc, gc)] = both(&big, |t| linear(&t[0], &t[1], Some(&t[2])));
        let rel = |a: &Tensor, b: &Tensor| max_diff(a, b) / (1.0 + max_abs(b));
        assert!(rel(&yf, &yc) <= 1e-6, "forward differs");
        for (a, b) in gf.iter().zip(&gc) {
            assert!(rel(a, b) <= 1e-6, "gradient differs");
        }
    }

    /// The weight gradient summed over row blocks (here three, the last one short) agrees
    /// with candle's single product `gradᵀ·x` to float tolerance, both through the linear
    /// op's backward and directly, and its bits do not depend on the thread count.
    #[test]
    fn blocked_weight_gradient_matches_one_product_at_any_thread_count() {
        let rows = 2 * WGRAD_BLOCK_ROWS + 37;
        let (g, x) = (randn(&[rows, 5], 1.0, 61), randn(&[rows, 7], 1.0, 62));
        let want = g.t().unwrap().matmul(&x).unwrap();
        let blocked = |threads: usize| -> Vec<f32> {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| g.apply_op2_no_bwd(&x, &WeightGrad).unwrap())
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap()
        };
        let one = blocked(1);
        assert_eq!(one, blocked(2), "bits depend on the thread count");
        assert_eq!(one, blocked(3), "bits depend on the thread count");
        let got = Tensor::from_vec(one, (5, 7), &Device::Cpu).unwrap();
        assert!(max_diff(&got, &want) <= 1e-4 * (1.0 + max_abs(&want)));
        // And as the gradient of a linear layer's weight.
        let w = Var::from_tensor(&randn(&[5, 7], 1.0, 63)).unwrap();
        let y = linear(&x, w.as_tensor(), None).unwrap();
        let grads = (y * &g).unwrap().sum_all().unwrap().backward().unwrap();
        let dw = grads.get(w.as_tensor()).unwrap();
        assert!(max_diff(dw, &want) <= 1e-4 * (1.0 + max_abs(&want)));
    }

    /// Inputs with several leading dims (or none) give the bits of the same rows as one
    /// `[rows, in]` matrix, forward and backward, fused (the ops flatten the leading dims
    /// themselves, with no reshape nodes around them) and composed; so does the MLP.
    #[test]
    fn linear_and_mlp_take_any_leading_dims() {
        let (w, b) = (randn(&[6, 11], 1.0, 52), randn(&[6], 1.0, 53));
        let (w2, b2) = (randn(&[4, 6], 1.0, 54), randn(&[4], 1.0, 55));
        let lin = |t: &[Tensor]| linear(&t[0], &t[1], Some(&t[2]));
        let lin_nb = |t: &[Tensor]| linear(&t[0], &t[1], None);
        let two = |t: &[Tensor]| {
            mlp(
                &t[0],
                &[(&t[1], Some(&t[2])), (&t[3], Some(&t[4]))],
                MlpAct::Gelu,
            )
        };
        // Each with the number of arguments it takes (each gets a gradient).
        type Case<'a> = (&'a dyn Fn(&[Tensor]) -> Result<Tensor>, usize);
        let fs: [Case; 3] = [(&lin, 3), (&lin_nb, 2), (&two, 5)];
        for shape in [vec![3, 5, 11], vec![2, 3, 4, 11], vec![11]] {
            let x = randn(&shape, 1.0, 51);
            let all = [x, w.clone(), b.clone(), w2.clone(), b2.clone()];
            for (f, n) in fs {
                let args = &all[..n];
                let nd = both(args, f);
                let as_rows = both(args, |t: &[Tensor]| {
                    let mut t = t.to_vec();
                    t[0] = t[0].reshape(((), 11))?;
                    let y = f(&t)?;
                    let mut out = shape[..shape.len() - 1].to_vec();
                    out.push(y.dim(1)?);
                    y.reshape(out)
                });
                for ((y, g), (y2, g2)) in nd.iter().zip(&as_rows) {
                    assert_eq!(y.dims(), y2.dims());
                    assert_eq!(max_diff(y, y2), 0.0, "{shape:?}: forward");
                    for (a, b) in g.iter().zip(g2) {
                        assert_eq!(a.dims(), b.dims());
                        assert_eq!(max_diff(a, b), 0.0, "{shape:?}: gradient");
                    }
                }
                // The point of taking N-D inputs: the fused graph has as many nodes as for
                // a 2-D input (no reshape nodes around the op, each of which would cost a
                // zero tensor and an add in backward).
                let nodes = |x: Tensor| {
                    with_fused(true, || {
                        let x = Var::from_tensor(&x).unwrap().as_tensor().clone();
                        let mut t = args.to_vec();
                        t[0] = x;
                        f(&t).unwrap().sorted_nodes().len()
                    })
                };
                let flat = randn(&[shape.iter().product::<usize>() / 11, 11], 1.0, 56);
                let nd_input = flat.reshape(shape.as_slice()).unwrap();
                assert_eq!(nodes(nd_input), nodes(flat), "{shape:?}: extra graph nodes");
                // And fused agrees with composed for these shapes.
                assert!(
                    max_diff(&nd[0].0, &nd[1].0) <= 1e-5,
                    "{shape:?}: fused vs composed"
                );
            }
        }
    }

    /// Backward computes no gradient for a data input (and so skips that matmul), and the
    /// weight and bias gradients are those of the composed ops.
    #[test]
    fn linear_skips_the_gradient_of_data_inputs() {
        let x = randn(&[9, 4], 1.0, 41);
        let w = Var::from_tensor(&randn(&[3, 4], 1.0, 42)).unwrap();
        let b = Var::from_tensor(&randn(&[3], 1.0, 43)).unwrap();
        let grads = |on: bool| {
            with_fused(on, || {
                let y = linear(&x, w.as_tensor(), Some(b.as_tensor())).unwrap();
                y.sqr().unwrap().sum_all().unwrap().backward().unwrap()
            })
        };
        let (fused, composed) = (grads(true), grads(false));
        assert!(fused.get(&x).is_none(), "a data input got a gradient");
        assert!(composed.get(&x).is_some(), "candle's matmul computes it");
        for v in [w.as_tensor(), b.as_tensor()] {
            let d = max_diff(fused.get(v).unwrap(), composed.get(v).unwrap());
            assert!(d <= 1e-5, "parameter gradient differs by {d}");
        }
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

    #[test]
    fn bias_add_matches_the_composed_version_and_finite_differences() {
        let args = [randn(&[4, 9, 33], 1.0, 21), randn(&[33], 1.0, 22)];
        assert_matches_composed(&args, |t| bias_add(&t[0], &t[1]), 1e-4);
        finite_difference_check(&[randn(&[3, 5], 1.0, 23), randn(&[5], 1.0, 24)], |t| {
            bias_add(&t[0], &t[1])
        });
        let big = [
            Tensor::new(&[[3e38f32, -3e38], [1.0, 2.0]], &Device::Cpu).unwrap(),
            randn(&[2], 1.0, 25),
        ];
        assert_matches_composed(&big, |t| bias_add(&t[0], &t[1]), 0.0);
    }

    #[test]
    fn softmax_matches_the_composed_version_and_finite_differences() {
        let x = randn(&[3, 5, 40], 2.0, 41);
        for dim in [2, 1] {
            assert_matches_composed(std::slice::from_ref(&x), |t| softmax(&t[0], dim), 1e-5);
            finite_difference_check(&[randn(&[2, 3, 6], 1.5, 42)], |t| softmax(&t[0], dim));
        }
        // Extremes: huge logits pick one entry, a constant row is uniform, nothing overflows.
        let x = Tensor::new(
            &[
                [1e30f32, -1e30, 0.0, 5.0],
                [7.0, 7.0, 7.0, 7.0],
                [-1e30, -1e30, -1e30, -2e30],
            ],
            &Device::Cpu,
        )
        .unwrap();
        let [(y, g), _] = both(std::slice::from_ref(&x), |t| softmax(&t[0], 1));
        let y: Vec<Vec<f32>> = y.to_vec2().unwrap();
        assert_eq!(y[0], vec![1.0, 0.0, 0.0, 0.0]);
        assert_eq!(y[1], vec![0.25; 4]);
        assert_eq!(y[2], vec![1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0, 0.0]);
        let g: Vec<f32> = g[0].flatten_all().unwrap().to_vec1().unwrap();
        assert!(g.iter().all(|v| v.is_finite()), "{g:?}");
        assert_matches_composed(&[x], |t| softmax(&t[0], 1), 1e-6);
    }

    #[test]
    fn conv2d_matches_candle_and_finite_differences() {
        for (stride, pad, k, h, w) in [
            (1, 1, 3, 7, 6),
            (2, 1, 3, 8, 8),
            (1, 0, 1, 4, 5),
            (2, 0, 3, 9, 7),
        ] {
            let args = [randn(&[2, h, w, 5], 1.0, 51), randn(&[4, 5, k, k], 0.5, 52)];
            assert_matches_composed(&args, |t| conv2d_nhwc(&t[0], &t[1], stride, pad), 1e-4);
        }
        // (5×5, not 5×4: candle 0.11's own conv2d backward, which `both` also runs, fails
        // with a shape mismatch on a 5×4 input at stride 2.)
        finite_difference_check(
            &[randn(&[1, 5, 5, 2], 1.0, 53), randn(&[3, 2, 3, 3], 1.0, 54)],
            |t| conv2d_nhwc(&t[0], &t[1], 2, 1),
        );
        // Large magnitudes stay finite and equal to candle's.
        let big = [
            randn(&[1, 4, 4, 2], 1e15, 55),
            randn(&[2, 2, 3, 3], 1e15, 56),
        ];
        let [(y, g), _] = both(&big, |t| conv2d_nhwc(&t[0], &t[1], 1, 1));
        for t in std::iter::once(&y).chain(&g) {
            let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            assert!(v.iter().all(|x| x.is_finite()));
        }
        // One node gives the bits of the same convolution in pieces (im2col, `linear`,
        // reshapes), forward and backward, with and without the input's gradient, and
        // twice over the same graph (the second backward recomputes the columns).
        let pieces = |x: &Tensor, kernel: &Tensor, stride: usize, pad: usize| {
            let (n, h, w, c) = x.dims4().unwrap();
            let (co, _, k, _) = kernel.dims4().unwrap();
            let (ho, wo) = (
                (h + 2 * pad - k) / stride + 1,
                (w + 2 * pad - k) / stride + 1,
            );
            let geom = ConvGeom {
                n,
                h,
                w,
                c,
                k,
                stride,
                pad,
                ho,
                wo,
            };
            let cols = x.apply_op1(Im2Col(geom)).unwrap();
            let kmat = kernel.reshape((co, c * k * k)).unwrap();
            linear(&cols, &kmat, None)
                .unwrap()
                .reshape((n, ho, wo, co))
                .unwrap()
        };
        for (x_is_var, stride, pad) in [(true, 2, 1), (false, 1, 1), (true, 1, 0)] {
            let x = randn(&[2, 9, 8, 3], 1.0, 59);
            let x = match x_is_var {
                true => Var::from_tensor(&x).unwrap().as_tensor().clone(),
                false => x,
            };
            let kv = Var::from_tensor(&randn(&[4, 3, 3, 3], 0.5, 60)).unwrap();
            let kernel = kv.as_tensor();
            let u = randn(pieces(&x, kernel, stride, pad).dims(), 1.0, 61);
            let run = |y: Tensor| {
                let loss = (&y * &u).unwrap().sum_all().unwrap();
                let first = loss.backward().unwrap();
                let second = loss.backward().unwrap();
                let bits = |t: Option<&Tensor>| -> Option<Vec<f32>> {
                    t.map(|t| t.flatten_all().unwrap().to_vec1().unwrap())
                };
                let all =
                    |g: &candle_core::backprop::GradStore| (bits(g.get(&x)), bits(g.get(kernel)));
                (
                    y.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
                    all(&first),
                    all(&second),
                    y.sorted_nodes().len(),
                )
            };
            let one = run(conv2d_nhwc(&x, kernel, stride, pad).unwrap());
            let three = run(pieces(&x, kernel, stride, pad));
            assert_eq!(one.0, three.0, "forward");
            assert_eq!(one.1, three.1, "gradients");
            assert_eq!(one.2, one.1, "a second backward");
            assert_eq!(one.1.0.is_some(), x_is_var);
            // One node instead of `linear`, the reshapes of kernel and output and (when
            // the input is tracked) im2col.
            assert_eq!(one.3 + 2 + usize::from(x_is_var), three.3);
        }
        // A kernel that does not match the input is an error, not a panic.
        let bad = conv2d_nhwc(
            &randn(&[1, 4, 4, 3], 1.0, 57),
            &randn(&[2, 2, 3, 3], 1.0, 58),
            1,
            1,
        );
        assert!(bad.unwrap_err().to_string().contains("3 channels"));
    }

    #[test]
    fn non_contiguous_inputs_take_the_same_values() {
        let x = randn(&[6, 8], 1.0, 31).t().unwrap(); // [8, 6], strided
        let g = randn(&[6], 1.0, 32);
        let b = randn(&[6], 1.0, 33);
        let a = with_fused(true, || layer_norm(&x, &g, &b, 1e-5)).unwrap();
        let c = with_fused(false, || layer_norm(&x, &g, &b, 1e-5)).unwrap();
        assert!(max_diff(&a, &c) < 1e-5);
    }
}
