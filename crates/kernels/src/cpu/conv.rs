//! The convolution over channels-last input on the CPU: its geometry, the unfolding of
//! the input into patch rows (im2col) and its adjoint (col2im), both with CUDA kernels
//! too, and the convolution as one node (im2col and one product), forward and backward.

use super::gemm;
use super::linear::{matmul_xwt, weight_grad};
use super::matrix::{MatRef, Threads};
use super::{buffer, f32_slice};
use crate::Precision;
use crate::kept::Kept;
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
pub(crate) struct Im2Col(pub(crate) ConvGeom);

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
        crate::ledger::backward("", "conv2d", || {
            Ok(Some(grad.contiguous()?.apply_op1_no_bwd(&Col2Im(self.0))?))
        })
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
    /// The products' precision, forward and backward (the node's when it was made).
    precision: Precision,
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
            self.precision,
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
        crate::ledger::backward("", "conv2d", || {
            // Taken, not cloned: a second backward through the same graph recomputes them.
            let bwd = ConvBwd {
                geom: self.geom,
                co: self.co,
                saved: Kept::new(self.saved.take()),
                input_grad: x.track_op(),
                precision: self.precision,
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
        })
    }
}

/// The backward pass of [`ConvOp`] as a no-grad op over `(x, kernel, grad)`: one flat
/// buffer `[dx (when the input carries a gradient) | d kernel]`.
struct ConvBwd {
    geom: ConvGeom,
    co: usize,
    saved: Kept<CpuStorage>,
    input_grad: bool,
    precision: Precision,
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
        let dk = weight_grad(s3, &grad_l, &cols, &cols_l, self.precision)?;
        let mut out = match self.input_grad {
            true => {
                // d columns = grad · kernel, then scattered back to the image.
                let kmat = Layout::contiguous_with_offset((self.co, p), l2.start_offset());
                let dcols = gemm::matmul(
                    MatRef::of(s3, &grad_l)?,
                    MatRef::of(s2, &kmat)?,
                    Threads::Pool,
                    self.precision,
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

/// The convolution of `x: [n, h, w, c]` by `kernel: [co, c, k, k]` (`geom`) as one node
/// (f32 on the CPU) → `[n, ho, wo, co]`.
pub(crate) fn conv2d(x: &Tensor, kernel: &Tensor, geom: ConvGeom, co: usize) -> Result<Tensor> {
    let op = ConvOp {
        geom,
        co,
        keep: x.track_op() || kernel.track_op(),
        saved: Kept::new(None),
        precision: crate::precision(),
    };
    x.contiguous()?.apply_op2(&kernel.contiguous()?, op)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::randn;

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
}
