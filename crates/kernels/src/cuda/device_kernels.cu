// osrt's CUDA kernels, compiled by NVRTC at first use (`cuda.rs`) and launched with the
// geometry of `device_kernels.rs`. In the CPU build's tests the same text is compiled by
// the host's C++ compiler under a CUDA emulator (`emulated.rs`, `emulated/cuda_host.hpp`)
// and checked against the CPU ops. So: only what NVRTC and that header both know
// (no CUDA headers, no math library beyond the f32 functions the header names).

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

// The chunks of `chunk` rows a column sum splits `rows` into (one, empty, for no rows).
__device__ __forceinline__ long row_chunks(int rows, int chunk) {
    return rows > 0 ? ((long)rows + chunk - 1) / chunk : 1;
}

// Per chunk of `chunk` rows and column: sums of dy * xhat and of dy. The chunks are
// blockIdx.y, then every gridDim.y-th after it (a grid's y is at most 65,535).
extern "C" __global__ void osrt_layer_norm_bwd_params(const float* x, const float* dy,
                                                      const float* stats, float* partial,
                                                      int rows, int d, int chunk) {
    int col = blockIdx.x * blockDim.x + threadIdx.x;
    if (col >= d) return;
    for (long c = blockIdx.y; c < row_chunks(rows, chunk); c += gridDim.y) {
        long r0 = c * chunk;
        long r1 = min((long)rows, r0 + chunk);
        float ag = 0.f, ab = 0.f;
        for (long r = r0; r < r1; ++r) {
            float dyv = dy[r * d + col];
            ag += dyv * ((x[r * d + col] - stats[2 * r]) * stats[2 * r + 1]);
            ab += dyv;
        }
        partial[c * 2 * d + col] = ag;
        partial[c * 2 * d + d + col] = ab;
    }
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

// In place on a buffer the caller owns: x = act(x + b[col]) (osrt_bias_act_fwd with y = x).
extern "C" __global__ void osrt_bias_act_fwd_inplace(float* x, const float* b, long n, int cols,
                                                     int kind, float slope) {
    for (long i = (long)blockIdx.x * blockDim.x + threadIdx.x; i < n;
         i += (long)gridDim.x * blockDim.x)
        x[i] = act_f(x[i] + b[i % cols], kind, slope);
}

// In place: x = dy * act'(x + b[col]) (osrt_bias_act_bwd with dz = x).
extern "C" __global__ void osrt_bias_act_bwd_inplace(float* x, const float* b, const float* dy,
                                                     long n, int cols, int kind, float slope) {
    for (long i = (long)blockIdx.x * blockDim.x + threadIdx.x; i < n;
         i += (long)gridDim.x * blockDim.x) {
        float z = x[i] + b[i % cols];
        x[i] = dy[i] * act_grad(z, kind, slope);
    }
}

// f32 -> bf16 rounded to nearest, ties to even (as candle's and the `half` crate's
// conversions round), a NaN to a quiet NaN of the same sign.
__device__ __forceinline__ unsigned short bf16_of(float f) {
    unsigned int u = __float_as_uint(f);
    if ((u & 0x7fffffffu) > 0x7f800000u) return (unsigned short)((u >> 16) | 0x0040u);
    u += 0x7fffu + ((u >> 16) & 1u);
    return (unsigned short)(u >> 16);
}

// y = bf16(act(f32(z) + b[col])): a bf16 product's bias and activation, rounded back to
// bf16 for the next product, with no f32 tensor of the layer's size.
extern "C" __global__ void osrt_bias_act_low(const unsigned short* z, const float* b,
                                             unsigned short* y, long n, int cols, int kind,
                                             float slope) {
    for (long i = (long)blockIdx.x * blockDim.x + threadIdx.x; i < n;
         i += (long)gridDim.x * blockDim.x) {
        float x = __uint_as_float(((unsigned int)z[i]) << 16);
        y[i] = bf16_of(act_f(x + b[i % cols], kind, slope));
    }
}

// dz = f32(dy) * act'(f32(z) + b[col]): a bf16 hidden layer's gradient from its bf16 product
// and the bf16 gradient the layer after gave it, in f32 (osrt_bias_act_bwd of both widened).
extern "C" __global__ void osrt_bias_act_bwd_low(const unsigned short* z, const float* b,
                                                 const unsigned short* dy, float* dz, long n,
                                                 int cols, int kind, float slope) {
    for (long i = (long)blockIdx.x * blockDim.x + threadIdx.x; i < n;
         i += (long)gridDim.x * blockDim.x) {
        float x = __uint_as_float(((unsigned int)z[i]) << 16);
        float g = __uint_as_float(((unsigned int)dy[i]) << 16);
        dz[i] = g * act_grad(x + b[i % cols], kind, slope);
    }
}

// Per chunk of `chunk` rows and column: the column's sum over the chunk (chunks as in
// osrt_layer_norm_bwd_params).
extern "C" __global__ void osrt_column_partials(const float* a, float* partial, int rows,
                                                int cols, int chunk) {
    int col = blockIdx.x * blockDim.x + threadIdx.x;
    if (col >= cols) return;
    for (long c = blockIdx.y; c < row_chunks(rows, chunk); c += gridDim.y) {
        long r0 = c * chunk;
        long r1 = min((long)rows, r0 + chunk);
        float s = 0.f;
        for (long r = r0; r < r1; ++r) s += a[r * cols + col];
        partial[c * cols + col] = s;
    }
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

// In place over dy: dy = (y * (dy - dot)) * scale + 0 per row, the softmax backward of
// osrt_softmax_bwd followed by candle's affine (scale, 0): the attention's scaled-logit
// gradient written over the weights' gradient. Each lane writes only the elements it read
// for the dot, and all reads precede the warp's reduction.
extern "C" __global__ void osrt_softmax_bwd_scaled_inplace(const float* y, float* dy, int rows,
                                                           int d, float scale) {
    long row = (long)blockIdx.x * blockDim.y + threadIdx.y;
    if (row >= rows) return;
    int lane = threadIdx.x;
    const float* yr = y + row * d;
    float* dyr = dy + row * d;
    float dot = 0.f;
    for (int i = lane; i < d; i += 32) dot += yr[i] * dyr[i];
    dot = warp_sum(dot);
    for (int i = lane; i < d; i += 32) {
        float g = yr[i] * (dyr[i] - dot);
        dyr[i] = g * scale + 0.f;
    }
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
