//! CUDA versions of the one-node ops whose composed form costs the most memory on a GPU:
//! LayerNorm (candle's composition keeps five full-size intermediates for the backward
//! pass; this op keeps its input), softmax (four; this op keeps its output) and a bias
//! with its activation (`bias_act.rs`: up to three; this op none), forward and backward,
//! and the column sums their gradients need. The kernels are compiled once per process with NVRTC, so a build needs
//! no GPU; they compute what the CPU ops compute, in f32, with reductions in a fixed
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

const SOURCE: &str = r#"
__device__ __forceinline__ float warp_sum(float v) {
    for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(0xffffffffu, v, o);
    return v;
}
__device__ __forceinline__ float warp_max(float v) {
    for (int o = 16; o > 0; o >>= 1) v = fmaxf(v, __shfl_xor_sync(0xffffffffu, v, o));
    return v;
}

// One warp (threadIdx.x) per row (threadIdx.y + blockIdx.x * blockDim.y): a whole warp
// leaves together, so the shuffles always see 32 active lanes.
extern "C" __global__ void osrt_layer_norm_fwd(const float* x, const float* g, const float* b,
                                               float* y, int rows, int d, float eps) {
    long row = (long)blockIdx.x * blockDim.y + threadIdx.y;
    if (row >= rows) return;
    int lane = threadIdx.x;
    const float* xr = x + row * d;
    float s = 0.f;
    for (int i = lane; i < d; i += 32) s += xr[i];
    float mean = warp_sum(s) / d;
    float q = 0.f;
    for (int i = lane; i < d; i += 32) { float c = xr[i] - mean; q += c * c; }
    float rstd = 1.f / sqrtf(warp_sum(q) / d + eps);
    float* yr = y + row * d;
    for (int i = lane; i < d; i += 32) yr[i] = (xr[i] - mean) * rstd * g[i] + b[i];
}

// dx of each row, and the row's mean and 1/sigma for the parameter gradients.
extern "C" __global__ void osrt_layer_norm_bwd(const float* x, const float* g, const float* dy,
                                               float* dx, float* stats, int rows, int d,
                                               float eps) {
    long row = (long)blockIdx.x * blockDim.y + threadIdx.y;
    if (row >= rows) return;
    int lane = threadIdx.x;
    const float* xr = x + row * d;
    const float* dyr = dy + row * d;
    float s = 0.f;
    for (int i = lane; i < d; i += 32) s += xr[i];
    float mean = warp_sum(s) / d;
    float q = 0.f;
    for (int i = lane; i < d; i += 32) { float c = xr[i] - mean; q += c * c; }
    float rstd = 1.f / sqrtf(warp_sum(q) / d + eps);
    float m1 = 0.f, m2 = 0.f;
    for (int i = lane; i < d; i += 32) {
        float gy = dyr[i] * g[i];
        m1 += gy;
        m2 += gy * ((xr[i] - mean) * rstd);
    }
    m1 = warp_sum(m1) / d;
    m2 = warp_sum(m2) / d;
    float* dxr = dx + row * d;
    for (int i = lane; i < d; i += 32) {
        float xhat = (xr[i] - mean) * rstd;
        dxr[i] = rstd * (dyr[i] * g[i] - m1 - xhat * m2);
    }
    if (lane == 0) { stats[2 * row] = mean; stats[2 * row + 1] = rstd; }
}

// Per chunk of `chunk` rows (blockIdx.y) and column: sums of dy * xhat and of dy.
extern "C" __global__ void osrt_layer_norm_bwd_params(const float* x, const float* dy,
                                                      const float* stats, float* partial,
                                                      int rows, int d, int chunk) {
    int col = blockIdx.x * blockDim.x + threadIdx.x;
    if (col >= d) return;
    long r0 = (long)blockIdx.y * chunk;
    long r1 = min((long)rows, r0 + chunk);
    float ag = 0.f, ab = 0.f;
    for (long r = r0; r < r1; ++r) {
        float dyv = dy[r * d + col];
        ag += dyv * ((x[r * d + col] - stats[2 * r]) * stats[2 * r + 1]);
        ab += dyv;
    }
    partial[(long)blockIdx.y * 2 * d + col] = ag;
    partial[(long)blockIdx.y * 2 * d + d + col] = ab;
}

// out[col] = sum over chunks, in chunk order.
extern "C" __global__ void osrt_sum_chunks(const float* partial, float* out, int chunks,
                                           int width) {
    int col = blockIdx.x * blockDim.x + threadIdx.x;
    if (col >= width) return;
    float s = 0.f;
    for (int c = 0; c < chunks; ++c) s += partial[(long)c * width + col];
    out[col] = s;
}

// The activation after a bias: kind 0 none, 1 (leaky) ReLU with `slope`, 2 erf-GELU.
__device__ __forceinline__ float act_f(float z, int kind, float slope) {
    if (kind == 1) return z < 0.f ? (slope == 0.f ? 0.f : slope * z) : z;
    if (kind == 2) return 0.5f * z * (1.f + erff(z * 0.70710678118654752f));
    return z;
}
__device__ __forceinline__ float act_grad(float z, int kind, float slope) {
    if (kind == 1) return z < 0.f ? slope : 1.f;
    if (kind == 2) {
        float cdf = 0.5f * (1.f + erff(z * 0.70710678118654752f));
        return cdf + z * 0.3989422804014327f * expf(-0.5f * z * z);
    }
    return 1.f;
}

// y = act(x + b[col]) over `n` elements of rows of `cols`.
extern "C" __global__ void osrt_bias_act_fwd(const float* x, const float* b, float* y, long n,
                                             int cols, int kind, float slope) {
    for (long i = (long)blockIdx.x * blockDim.x + threadIdx.x; i < n;
         i += (long)gridDim.x * blockDim.x)
        y[i] = act_f(x[i] + b[i % cols], kind, slope);
}

// dz = dy * act'(x + b[col]).
extern "C" __global__ void osrt_bias_act_bwd(const float* x, const float* b, const float* dy,
                                             float* dz, long n, int cols, int kind,
                                             float slope) {
    for (long i = (long)blockIdx.x * blockDim.x + threadIdx.x; i < n;
         i += (long)gridDim.x * blockDim.x) {
        float z = x[i] + b[i % cols];
        // A zero gradient stays zero where act' is not finite (as the CPU op's x·0 is not
        // taken either: dy is multiplied by the derivative's value).
        dz[i] = dy[i] * act_grad(z, kind, slope);
    }
}

// Per chunk of `chunk` rows (blockIdx.y) and column: the column's sum over the chunk.
extern "C" __global__ void osrt_column_partials(const float* a, float* partial, int rows,
                                                int cols, int chunk) {
    int col = blockIdx.x * blockDim.x + threadIdx.x;
    if (col >= cols) return;
    long r0 = (long)blockIdx.y * chunk;
    long r1 = min((long)rows, r0 + chunk);
    float s = 0.f;
    for (long r = r0; r < r1; ++r) s += a[r * cols + col];
    partial[(long)blockIdx.y * cols + col] = s;
}

// Softmax of each row, shifted by the row's maximum (the largest term is exp(0) = 1).
extern "C" __global__ void osrt_softmax_fwd(const float* x, float* y, int rows, int d) {
    long row = (long)blockIdx.x * blockDim.y + threadIdx.y;
    if (row >= rows) return;
    int lane = threadIdx.x;
    const float* xr = x + row * d;
    float* yr = y + row * d;
    float m = -__int_as_float(0x7f800000);  // -inf (no math header under NVRTC)
    for (int i = lane; i < d; i += 32) m = fmaxf(m, xr[i]);
    m = warp_max(m);
    float s = 0.f;
    for (int i = lane; i < d; i += 32) { float e = expf(xr[i] - m); yr[i] = e; s += e; }
    float inv = 1.f / warp_sum(s);
    for (int i = lane; i < d; i += 32) yr[i] *= inv;
}

// dx = y * (dy - sum(y * dy)) per row, from the softmax output y.
extern "C" __global__ void osrt_softmax_bwd(const float* y, const float* dy, float* dx, int rows,
                                            int d) {
    long row = (long)blockIdx.x * blockDim.y + threadIdx.y;
    if (row >= rows) return;
    int lane = threadIdx.x;
    const float* yr = y + row * d;
    const float* dyr = dy + row * d;
    float dot = 0.f;
    for (int i = lane; i < d; i += 32) dot += yr[i] * dyr[i];
    dot = warp_sum(dot);
    float* dxr = dx + row * d;
    for (int i = lane; i < d; i += 32) dxr[i] = yr[i] * (dyr[i] - dot);
}

// The gradient of an unfolding (col2im): dx[b, y, x, c] (NHWC) is the sum of the entries
// of `cols` ([b·ho·wo, c·k·k], each row's entries ordered (channel, ky, kx)) that the
// unfolding read from that pixel. A thread per pixel gathers them; the taps are visited
// last to first, which is the order the CPU's scatter adds them in (output rows
// ascending), so both give the same bits. No atomics: the sums do not depend on timing.
__device__ __forceinline__ float load_col(const float* c, long i) { return c[i]; }
__device__ __forceinline__ float load_col(const unsigned short* c, long i) {
    return __uint_as_float(((unsigned int)c[i]) << 16);  // bf16 is f32's upper half
}
template <typename T>
__device__ void col2im(const T* cols, float* dx, long total, int h, int w, int ch, int k,
                       int stride, int pad, int ho, int wo) {
    long patch = (long)ch * k * k;
    for (long i = (long)blockIdx.x * blockDim.x + threadIdx.x; i < total;
         i += (long)gridDim.x * blockDim.x) {
        int c = (int)(i % ch);
        long r = i / ch;
        int x = (int)(r % w);
        r /= w;
        int y = (int)(r % h);
        long b = r / h;
        float s = 0.f;
        for (int ky = k - 1; ky >= 0; --ky) {
            int ty = y + pad - ky;
            if (ty < 0 || ty % stride) continue;
            int oy = ty / stride;
            if (oy >= ho) continue;
            for (int kx = k - 1; kx >= 0; --kx) {
                int tx = x + pad - kx;
                if (tx < 0 || tx % stride) continue;
                int ox = tx / stride;
                if (ox >= wo) continue;
                s += load_col(cols, ((b * ho + oy) * wo + ox) * patch + ((long)c * k + ky) * k + kx);
            }
        }
        dx[i] = s;
    }
}
// The unfolding (im2col) of NHWC x: cols[r, j] for row r = (b, oy, ox) and column
// j = (c, ky, kx) is x[b, oy·stride + ky − pad, ox·stride + kx − pad, c], 0 outside the
// image. A thread per column entry; values are copied, never converted.
template <typename T>
__device__ void im2col(const T* x, T* cols, long total, int h, int w, int ch, int k,
                       int stride, int pad, int ho, int wo) {
    long patch = (long)ch * k * k;
    for (long i = (long)blockIdx.x * blockDim.x + threadIdx.x; i < total;
         i += (long)gridDim.x * blockDim.x) {
        long j = i % patch;
        long r = i / patch;
        int kx = (int)(j % k);
        int ky = (int)((j / k) % k);
        int c = (int)(j / ((long)k * k));
        int ox = (int)(r % wo);
        int oy = (int)((r / wo) % ho);
        long b = r / ((long)wo * ho);
        int iy = oy * stride + ky - pad;
        int ix = ox * stride + kx - pad;
        bool inside = iy >= 0 && iy < h && ix >= 0 && ix < w;
        cols[i] = inside ? x[((b * h + iy) * w + ix) * ch + c] : (T)0;
    }
}
extern "C" __global__ void osrt_im2col_f32(const float* x, float* cols, long total, int h,
                                           int w, int ch, int k, int stride, int pad, int ho,
                                           int wo) {
    im2col(x, cols, total, h, w, ch, k, stride, pad, ho, wo);
}
extern "C" __global__ void osrt_im2col_bf16(const unsigned short* x, unsigned short* cols,
                                            long total, int h, int w, int ch, int k,
                                            int stride, int pad, int ho, int wo) {
    im2col(x, cols, total, h, w, ch, k, stride, pad, ho, wo);
}
extern "C" __global__ void osrt_col2im_f32(const float* cols, float* dx, long total, int h,
                                           int w, int ch, int k, int stride, int pad, int ho,
                                           int wo) {
    col2im(cols, dx, total, h, w, ch, k, stride, pad, ho, wo);
}
extern "C" __global__ void osrt_col2im_bf16(const unsigned short* cols, float* dx, long total,
                                            int h, int w, int ch, int k, int stride, int pad,
                                            int ho, int wo) {
    col2im(cols, dx, total, h, w, ch, k, stride, pad, ho, wo);
}
"#;

/// Module name under which the device caches the loaded kernels.
const MODULE: &str = "osrt_kernels_rows";
/// Rows (warps) per block of the row kernels.
const ROWS_PER_BLOCK: u32 = 8;
/// Rows per chunk of LayerNorm's parameter-gradient sums.
const PARAM_CHUNK: usize = 64;

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

/// `(rows, d)` of a `[.., d]` layout, as the kernels' `int`s.
fn rows_cols(l: &Layout, d: usize, what: &str) -> Result<(i32, i32)> {
    let n = l.shape().elem_count();
    if d == 0 || !n.is_multiple_of(d) {
        candle_core::bail!("{what}: {n} elements are not rows of {d}")
    }
    match (i32::try_from(n / d), i32::try_from(d)) {
        (Ok(r), Ok(d)) => Ok((r, d)),
        _ => candle_core::bail!("{what}: {n} elements are too many for one launch"),
    }
}

fn row_launch(rows: i32) -> LaunchConfig {
    LaunchConfig {
        grid_dim: ((rows as u32).div_ceil(ROWS_PER_BLOCK).max(1), 1, 1),
        block_dim: (32, ROWS_PER_BLOCK, 1),
        shared_mem_bytes: 0,
    }
}

fn column_launch(width: i32, chunks: u32) -> LaunchConfig {
    LaunchConfig {
        grid_dim: ((width as u32).div_ceil(128).max(1), chunks, 1),
        block_dim: (128, 1, 1),
        shared_mem_bytes: 0,
    }
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
    let (xv, gv, dyv) = (
        input(x, lx, "layer_norm backward x")?,
        input(g, lg, "layer_norm backward weight")?,
        input(dy, ldy, "layer_norm backward gradient")?,
    );
    let n = rows as usize * d;
    let chunks = (rows as usize).div_ceil(PARAM_CHUNK).max(1);
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
        unsafe { l.launch(column_launch(dd, chunks as u32)) }.w()?;
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

fn elementwise_launch(n: usize) -> LaunchConfig {
    LaunchConfig {
        grid_dim: (n.div_ceil(256).clamp(1, 65_535 * 16) as u32, 1, 1),
        block_dim: (256, 1, 1),
        shared_mem_bytes: 0,
    }
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
    let chunks = (rows as usize).div_ceil(PARAM_CHUNK).max(1);
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
        unsafe { l.launch(column_launch(cols, chunks as u32)) }.w()?;
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
