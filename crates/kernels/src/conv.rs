use crate::gemm::{self, MatRef, Threads};
use crate::*;
use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// Geometry of a square-kernel convolution over NHWC input.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ConvGeom {
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
    /// `n` images of `h × w × c`, a `k × k` kernel (that fits the padded input).
    pub(crate) fn new(
        n: usize,
        (h, w, c): (usize, usize, usize),
        k: usize,
        stride: usize,
        pad: usize,
    ) -> Self {
        Self {
            n,
            h,
            w,
            c,
            k,
            stride,
            pad,
            ho: (h + 2 * pad - k) / stride + 1,
            wo: (w + 2 * pad - k) / stride + 1,
        }
    }

    /// Input position of output `(oy, ox)` at kernel tap `(ky, kx)`, if inside the image.
    #[inline]
    fn source(&self, oy: usize, ox: usize, ky: usize, kx: usize) -> Option<(usize, usize)> {
        let iy = (oy * self.stride + ky).checked_sub(self.pad)?;
        let ix = (ox * self.stride + kx).checked_sub(self.pad)?;
        (iy < self.h && ix < self.w).then_some((iy, ix))
    }

    /// `[n, h, w, c, k, stride, pad, ho, wo]`, as the CUDA kernels take them.
    #[cfg(any(feature = "cuda", test))]
    pub(crate) fn sizes(&self) -> [usize; 9] {
        let g = self;
        [g.n, g.h, g.w, g.c, g.k, g.stride, g.pad, g.ho, g.wo]
    }

    /// The output's size `[n, ho, wo]`.
    pub(crate) fn output(&self) -> (usize, usize, usize) {
        (self.n, self.ho, self.wo)
    }

    /// Row `row` = (image, oy) of the unfolding of NHWC `x` into `o` (`wo` patches,
    /// zeroed: the padding stays 0).
    fn unfold_row<T: Copy>(&self, x: &[T], row: usize, o: &mut [T]) {
        let (b, oy) = (row / self.ho, row % self.ho);
        let (p, k) = (self.patch(), self.k);
        for ox in 0..self.wo {
            let o = &mut o[ox * p..(ox + 1) * p];
            for ky in 0..k {
                for kx in 0..k {
                    if let Some((iy, ix)) = self.source(oy, ox, ky, kx) {
                        let src = &x[((b * self.h + iy) * self.w + ix) * self.c..][..self.c];
                        for (ci, v) in src.iter().enumerate() {
                            o[(ci * k + ky) * k + kx] = *v;
                        }
                    }
                }
            }
        }
    }

    /// Image `b`'s patch gradients in `cols` added onto its pixels in `o` (NHWC, zeroed),
    /// output rows ascending: the order every device adds them in.
    fn fold_image<T: Copy + std::ops::AddAssign>(&self, cols: &[T], b: usize, o: &mut [T]) {
        let (p, k) = (self.patch(), self.k);
        for oy in 0..self.ho {
            for ox in 0..self.wo {
                let row = &cols[((b * self.ho + oy) * self.wo + ox) * p..][..p];
                for ky in 0..k {
                    for kx in 0..k {
                        if let Some((iy, ix)) = self.source(oy, ox, ky, kx) {
                            let dst = &mut o[(iy * self.w + ix) * self.c..][..self.c];
                            for (ci, d) in dst.iter_mut().enumerate() {
                                *d += row[(ci * k + ky) * k + kx];
                            }
                        }
                    }
                }
            }
        }
    }

    /// Columns per patch, ordered (channel, ky, kx) like a `[c_out, c_in, k, k]` kernel.
    fn patch(&self) -> usize {
        self.c * self.k * self.k
    }
}

/// Patches of NHWC input as rows, without a backward pass (the GPU's convolution node
/// differentiates itself).
///
/// # Shapes
/// `x: [n, h, w, c]` (f32; on a GPU also bf16) → `[n·ho·wo, c·k·k]` in `x`'s type
pub(crate) fn im2col(x: &Tensor, g: ConvGeom) -> Result<Tensor> {
    x.contiguous()?.apply_op1_no_bwd(&Im2Col(g))
}

/// Patches of NHWC input as rows: `[n·ho·wo, c·k·k]`.
struct Im2Col(ConvGeom);

impl CustomOp1 for Im2Col {
    fn name(&self) -> &'static str {
        "osrt-im2col"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let g = self.0;
        let p = g.patch();
        let shape = Shape::from((g.n * g.ho * g.wo, p));
        if let CpuStorage::F64(v) = s {
            // For gradient checks in f64 (`conv_node.rs`), serially.
            let Some((a, b)) = l.contiguous_offsets() else {
                candle_core::bail!("im2col: contiguous input expected")
            };
            let mut out = vec![0f64; g.n * g.ho * g.wo * p];
            for (row, o) in out.chunks_mut(p * g.wo).enumerate() {
                g.unfold_row(&v[a..b], row, o);
            }
            return Ok((CpuStorage::F64(out), shape));
        }
        if let CpuStorage::BF16(v) = s {
            // The GPU's bf16 graph on the CPU (`--kernels device`): the same copies.
            let Some((a, b)) = l.contiguous_offsets() else {
                candle_core::bail!("im2col: contiguous input expected")
            };
            let mut out = vec![half::bf16::ZERO; g.n * g.ho * g.wo * p];
            out.par_chunks_mut((p * g.wo).max(1))
                .enumerate()
                .for_each(|(row, o)| g.unfold_row(&v[a..b], row, o));
            return Ok((CpuStorage::BF16(out), shape));
        }
        let x = f32_slice(s, l, "im2col")?;
        // Each task zeroes its chunk (the padding stays 0) before writing the patches.
        let out = buffer::par_filled(g.n * g.ho * g.wo * p, p * g.wo, |row, o| {
            g.unfold_row(x, row, o)
        });
        Ok((CpuStorage::F32(out), shape))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s: &candle_core::CudaStorage,
        l: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        crate::cuda::im2col(s, l, self.0.sizes())
    }

    fn bwd(&self, _x: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(grad.contiguous()?.apply_op1_no_bwd(&Col2Im(self.0))?))
    }
}

/// Im2col's adjoint: patch gradients summed back into NHWC `[n, h, w, c]`.
///
/// # Shapes
/// `cols: [n·ho·wo, c·k·k]` (f32; on a GPU also bf16) → `[n, h, w, c]` (f32)
pub(crate) fn col2im(cols: &Tensor, g: ConvGeom) -> Result<Tensor> {
    cols.contiguous()?.apply_op1_no_bwd(&Col2Im(g))
}

/// Every pixel's sum is added in one order on every device: output rows ascending (the
/// CPU's scatter), which the GPU's gather follows tap by tap, so both give the same bits.
struct Col2Im(ConvGeom);

impl CustomOp1 for Col2Im {
    fn name(&self) -> &'static str {
        "osrt-col2im"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let g = self.0;
        let img = g.h * g.w * g.c;
        let shape = Shape::from((g.n, g.h, g.w, g.c));
        if let CpuStorage::F64(v) = s {
            // For gradient checks in f64 (`conv_node.rs`), serially.
            let Some((a, b)) = l.contiguous_offsets() else {
                candle_core::bail!("col2im: contiguous columns expected")
            };
            let mut out = vec![0f64; g.n * img];
            for (b_i, o) in out.chunks_mut(img).enumerate() {
                g.fold_image(&v[a..b], b_i, o);
            }
            return Ok((CpuStorage::F64(out), shape));
        }
        let wide;
        let cols = match s {
            // bf16 columns (the GPU's bf16 graph on the CPU) sum in f32, as on a GPU: the
            // widening is exact.
            CpuStorage::BF16(v) => {
                let Some((a, b)) = l.contiguous_offsets() else {
                    candle_core::bail!("col2im: contiguous columns expected")
                };
                wide = v[a..b].iter().map(|x| x.to_f32()).collect::<Vec<_>>();
                &wide[..]
            }
            _ => f32_slice(s, l, "col2im")?,
        };
        let mut out = vec![0f32; g.n * img];
        // One task per image: every write of an image lands in its own slice.
        out.par_chunks_mut(img)
            .enumerate()
            .for_each(|(b, o)| g.fold_image(cols, b, o));
        Ok((CpuStorage::F32(out), shape))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s: &candle_core::CudaStorage,
        l: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        crate::cuda::col2im(s, l, self.0.sizes())
    }
}

/// Most values of one unfolded (im2col) buffer on a device (candle's convolution, and the
/// convolution node's forward and backward passes): 2²⁵ (128 MiB in f32). candle's 32-bit
/// indexing alone would allow 2³²; the cap is for memory: the kernel's gradient unfolds
/// the input again at the end of the backward pass, when the step holds most of its
/// gradients, so that buffer sits on the step's peak (the `paper` preset's first
/// convolution unfolds 27 M values per 128×128 image).
const MAX_UNFOLDED: usize = 1 << 25;

/// 2-D convolution without bias on channels-last input, as im2col + one matmul.
///
/// Why: candle's CPU `conv2d` is a direct loop and its input gradient a transposed
/// convolution; together they were ~40 % of a CPU train step. Here the work is one gemm
/// each way plus two memory passes. Channels-last also lets the encoder skip permutes.
///
/// # Shapes
/// `x: [n, h, w, c_in]`, `kernel: [c_out, c_in, k, k]` → `[n, h_out, w_out, c_out]`
pub fn conv2d_nhwc(x: &Tensor, kernel: &Tensor, stride: usize, padding: usize) -> Result<Tensor> {
    crate::profile::op("conv2d", &[x, kernel], move |t| {
        conv2d_nhwc_here(&t[0], &t[1], stride, padding, false)
    })
}

/// `relu(conv2d_nhwc(x, kernel, stride, padding))`; on the device graph one node that keeps
/// a one-byte mask where the graph of the two ops would keep the convolution's f32
/// output (`conv_node.rs`). The same values and gradients.
///
/// # Shapes
/// `x: [n, h, w, c_in]`, `kernel: [c_out, c_in, k, k]` → `[n, h_out, w_out, c_out]`
pub fn conv2d_relu_nhwc(
    x: &Tensor,
    kernel: &Tensor,
    stride: usize,
    padding: usize,
) -> Result<Tensor> {
    crate::profile::op("conv2d_relu", &[x, kernel], move |t| {
        conv2d_nhwc_here(&t[0], &t[1], stride, padding, true)
    })
}

fn conv2d_nhwc_here(
    x: &Tensor,
    kernel: &Tensor,
    stride: usize,
    padding: usize,
    relu: bool,
) -> Result<Tensor> {
    // Elsewhere than the device graph's node, ReLU is its own op after the convolution.
    let then_relu = |y: Tensor| match relu {
        true => crate::relu(&y),
        false => Ok(y),
    };
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
        let conv = |x: &Tensor| {
            in_precision(&[x, kernel], |t| {
                t[0].permute((0, 3, 1, 2))?
                    .conv2d(&t[1], padding, stride, 1, 1)?
                    .permute((0, 2, 3, 1))
            })
        };
        // candle's CUDA convolution unfolds its input (im2col) into one buffer indexed with
        // 32-bit thread numbers, forward and for the kernel's gradient alike: past 2³²
        // values the unfolded buffer is silently left partly unwritten (the `paper`
        // preset's first convolution over 5 views at batch 32 needs 4.3 G). Images go
        // through in groups whose unfolded size stays far below that; the groups also cap
        // the buffer's memory.
        let per_image = ho * wo * c * k * k;
        let group = (MAX_UNFOLDED / per_image.max(1)).max(1);
        if enabled() && device_graph(x) {
            // One node over all groups, keeping no per-group copies (`conv_node.rs`).
            let f32s = x.dtype() == candle_core::DType::F32 && kernel.dtype() == x.dtype();
            let bf16 = precision() == Precision::Bf16 && f32s;
            return crate::conv_node::conv2d_node(x, kernel, stride, padding, group, bf16, relu);
        }
        if x.device().is_cpu() {
            return then_relu(conv(x)?);
        }
        return then_relu(in_groups(x, group, conv)?);
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
    then_relu(x.contiguous()?.apply_op2(&kernel.contiguous()?, op)?)
}

/// `f` over groups of at most `group` leading entries of `x`, concatenated.
pub(crate) fn in_groups(
    x: &Tensor,
    group: usize,
    f: impl Fn(&Tensor) -> Result<Tensor>,
) -> Result<Tensor> {
    let n = x.dim(0)?;
    if n <= group {
        return f(x);
    }
    let parts = (0..n)
        .step_by(group.max(1))
        .map(|i| f(&x.narrow(0, i, group.min(n - i))?))
        .collect::<Result<Vec<_>>>()?;
    Tensor::cat(&parts, 0)
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::*;
    use candle_core::Var;

    /// The grouped convolution (a GPU's path for big batches) gives the one-shot values and
    /// gradients.
    #[test]
    fn a_convolution_in_groups_equals_one_over_the_whole_batch() {
        let args = [randn(&[5, 6, 8, 4], 1.0, 91), randn(&[3, 4, 3, 3], 0.5, 92)];
        let conv = |t: &[Tensor], group: usize| {
            in_groups(&t[0], group, |x| {
                x.permute((0, 3, 1, 2))?
                    .conv2d(&t[1], 1, 2, 1, 1)?
                    .permute((0, 2, 3, 1))
            })
        };
        let [(y1, g1), _] = both(&args, |t| conv(t, 2));
        let [(y5, g5), _] = both(&args, |t| conv(t, 5));
        assert_eq!(y1.dims(), y5.dims());
        assert!(max_diff(&y1, &y5) < 1e-6);
        for (a, b) in g1.iter().zip(&g5) {
            assert!(max_diff(a, b) < 1e-5 * max_abs(b).max(1.0));
        }
    }

    /// bf16 input (the GPU's bf16 graph on the CPU): the unfolding is the f32 unfolding
    /// of the same values, and col2im of bf16 columns is col2im of their exact f32
    /// widening, in f32.
    #[test]
    fn bf16_unfolding_and_col2im_are_the_f32_ones_of_the_same_values() {
        use candle_core::DType;
        let g = ConvGeom::new(2, (5, 7, 3), 3, 2, 1);
        let x = randn(&[2, 5, 7, 3], 1.0, 9).to_dtype(DType::BF16).unwrap();
        let wide = x.to_dtype(DType::F32).unwrap();
        let cols = im2col(&x, g).unwrap();
        assert_eq!(cols.dtype(), DType::BF16);
        let f = |t: &Tensor| t.to_dtype(DType::F32).unwrap().flatten_all().unwrap();
        let want = im2col(&wide, g).unwrap();
        assert_eq!(
            f(&cols).to_vec1::<f32>().unwrap(),
            f(&want).to_vec1::<f32>().unwrap()
        );
        let dcols = randn(cols.dims(), 1.0, 10).to_dtype(DType::BF16).unwrap();
        let back = col2im(&dcols, g).unwrap();
        assert_eq!(back.dtype(), DType::F32);
        let want = col2im(&dcols.to_dtype(DType::F32).unwrap(), g).unwrap();
        assert_eq!(
            f(&back).to_vec1::<f32>().unwrap(),
            f(&want).to_vec1::<f32>().unwrap()
        );
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

    /// `conv2d_relu_nhwc` is `relu(conv2d_nhwc(..))` to the bit, values and gradients,
    /// with every kernel set and precision the step runs.
    #[test]
    fn conv_relu_is_relu_of_the_convolution() {
        use crate::{Kernels, Precision, with_kernels, with_precision};
        let x = Var::from_tensor(&randn(&[2, 7, 7, 3], 1.0, 50)).unwrap();
        let k = Var::from_tensor(&randn(&[4, 3, 3, 3], 0.5, 51)).unwrap();
        for (kern, p) in [
            (Kernels::Fused, Precision::F32),
            (Kernels::Composed, Precision::F32),
            (Kernels::Device, Precision::F32),
            (Kernels::Device, Precision::Bf16),
        ] {
            let run = |one: bool| {
                with_kernels(kern, || {
                    with_precision(p, || {
                        let (xt, kt) = (x.as_tensor(), k.as_tensor());
                        let y = match one {
                            true => conv2d_relu_nhwc(xt, kt, 2, 1).unwrap(),
                            false => crate::relu(&conv2d_nhwc(xt, kt, 2, 1).unwrap()).unwrap(),
                        };
                        let w = randn(y.dims(), 1.0, 52);
                        let g = (&y * &w).unwrap().sum_all().unwrap().backward().unwrap();
                        [&y, g.get(xt).unwrap(), g.get(kt).unwrap()].map(|t| {
                            let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
                            v.iter().map(|f| f.to_bits()).collect::<Vec<u32>>()
                        })
                    })
                })
            };
            assert_eq!(run(true), run(false), "{kern} {p}");
        }
    }
}
