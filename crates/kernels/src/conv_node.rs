//! A convolution over channels-last input as one graph node built from tensor ops, for
//! devices without osrt's own convolution kernel (a GPU: candle's unfolding and cuBLAS).
//!
//! Why: composed, the device convolution runs over groups of images (`conv.rs`: candle's
//! unfolded buffer is indexed with 32-bit numbers), each group is its own chain of graph
//! nodes, and the concatenation of their outputs keeps every group's output beside the
//! whole output until the backward pass; in bf16 each group also keeps the bf16 copies
//! of its input and of its output. This node runs the same ops in the same order on
//! detached tensors and keeps only its f32 operands (the input, which the step keeps for
//! the previous op anyway, and the kernel). Its backward pass goes group by group in the
//! forward pass's precision. For the input: the columns' gradient as one matrix product
//! of the output's gradient with the kernel (cuBLAS on a GPU), summed back onto the
//! pixels (`conv::col2im`, in f32, deterministic); candle's own input gradient, a
//! transposed convolution, is a direct loop over every output pixel's channels and taps
//! on a GPU. For the kernel: candle's convolution of the transposed input with the
//! transposed gradient (an unfolding and a product). The result is handed to the graph
//! through the node's forward pass, which returns a copy of it (the size of the output).

use crate::conv::{ConvGeom, col2im};
use crate::handover::Handover;
use candle_core::{CpuStorage, CustomOp2, DType, Layout, Result, Shape, Tensor};

/// `x: [n, h, w, c_in]`, `kernel: [c_out, c_in, k, k]` → `[n, h_out, w_out, c_out]`, over
/// groups of `group` images, with bf16 operands (the result in f32) where `bf16` is set.
pub(crate) fn conv2d_node(
    x: &Tensor,
    kernel: &Tensor,
    stride: usize,
    padding: usize,
    group: usize,
    bf16: bool,
) -> Result<Tensor> {
    let geom = Geom {
        stride,
        padding,
        group: group.max(1),
        bf16,
    };
    let y = geom.forward(&x.detach(), &kernel.detach())?;
    let node = ConvNode {
        out: Handover::new(y)?,
        geom,
    };
    x.apply_op2(kernel, node)
}

#[derive(Debug, Clone, Copy)]
struct Geom {
    stride: usize,
    padding: usize,
    /// Images per group.
    group: usize,
    bf16: bool,
}

impl Geom {
    /// An operand in the products' precision.
    fn low(&self, t: &Tensor) -> Result<Tensor> {
        match self.bf16 && t.dtype() == DType::F32 {
            true => t.to_dtype(DType::BF16),
            false => Ok(t.clone()),
        }
    }

    /// A result back in f32 (where the products ran in bf16).
    fn high(&self, t: Tensor) -> Result<Tensor> {
        match self.bf16 && t.dtype() == DType::BF16 {
            true => t.to_dtype(DType::F32),
            false => Ok(t),
        }
    }

    /// The groups' starts and lengths over `n` images.
    fn groups(&self, n: usize) -> Vec<(usize, usize)> {
        let g = self.group;
        (0..n).step_by(g).map(|i| (i, g.min(n - i))).collect()
    }

    /// The forward pass as `conv.rs` composes it: per group, the operands in the products'
    /// precision, candle's convolution in NCHW, the result back in NHWC and f32.
    fn forward(&self, x: &Tensor, kernel: &Tensor) -> Result<Tensor> {
        let k = self.low(kernel)?;
        let one = |x: &Tensor| -> Result<Tensor> {
            let y = self
                .low(x)?
                .permute((0, 3, 1, 2))?
                .conv2d(&k, self.padding, self.stride, 1, 1)?
                .permute((0, 2, 3, 1))?;
            self.high(y)
        };
        let n = x.dim(0)?;
        if n <= self.group {
            return one(x);
        }
        let parts = self
            .groups(n)
            .into_iter()
            .map(|(i, len)| one(&x.narrow(0, i, len)?))
            .collect::<Result<Vec<_>>>()?;
        Tensor::cat(&parts, 0)
    }
}

/// `[n, h, w, c]` → `[n·h·w, c]`, contiguous (the rows a matrix product takes).
fn dy_rows(dy: &Tensor) -> Result<Tensor> {
    let (n, h, w, c) = dy.dims4()?;
    dy.contiguous()?.reshape((n * h * w, c))
}

struct ConvNode {
    out: Handover,
    geom: Geom,
}

impl CustomOp2 for ConvNode {
    fn name(&self) -> &'static str {
        "osrt-conv-node"
    }

    fn cpu_fwd(
        &self,
        _: &CpuStorage,
        _: &Layout,
        _: &CpuStorage,
        _: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        self.out.cpu("conv node")
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        _: &candle_core::CudaStorage,
        _: &Layout,
        _: &candle_core::CudaStorage,
        _: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        self.out.cuda("conv node")
    }

    /// Per group (see the module docs): the input's gradient by product and col2im, the
    /// kernel's by candle's convolution; the kernel's gradient is the groups' sum, in
    /// group order.
    fn bwd(
        &self,
        x: &Tensor,
        kernel: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let g = self.geom;
        let (n, h, w, ci) = x.dims4()?;
        let (_, _, kh, kw) = kernel.dims4()?;
        let k = g.low(kernel)?;
        let (mut dxs, mut dk) = (Vec::new(), None::<Tensor>);
        for (i, len) in g.groups(n) {
            // The group's output gradient in the products' precision; NCHW for candle.
            let dy_nhwc = g.low(&grad.narrow(0, i, len)?)?;
            let dy = dy_nhwc.permute((0, 3, 1, 2))?;
            if x.track_op() {
                // The columns' gradient, one product with the kernel matrix (cuBLAS on a
                // GPU), summed back onto the pixels they were read from (col2im, in f32).
                let rows = dy_rows(&dy_nhwc)?;
                let dcols = rows.matmul(&k.reshape((k.dim(0)?, ci * kh * kw))?)?;
                let geom = ConvGeom::new(len, (h, w, ci), kh, g.stride, g.padding);
                dxs.push(col2im(&dcols, geom)?);
            }
            if kernel.track_op() {
                let xg = g.low(&x.narrow(0, i, len)?)?.permute((0, 3, 1, 2))?;
                let mut d = xg
                    .transpose(0, 1)?
                    .conv2d(&dy.transpose(0, 1)?, g.padding, 1, g.stride, 1)?
                    .transpose(0, 1)?;
                let (_, _, dh, dw) = d.dims4()?;
                if dh != kh || dw != kw {
                    d = d.narrow(2, 0, kh)?.narrow(3, 0, kw)?;
                }
                let d = g.high(d)?;
                dk = Some(match dk {
                    Some(acc) => (acc + d)?,
                    None => d,
                });
            }
        }
        let dx = match dxs.len() {
            0 => None,
            1 => dxs.pop(),
            _ => Some(Tensor::cat(&dxs, 0)?),
        };
        Ok((dx, dk))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{assert_matches_composed, finite_difference_check, randn};
    use crate::{Precision, enabled, with_fused, with_precision};
    use candle_core::Var;

    /// `conv.rs`'s composed device path: per group, `in_precision` around candle's
    /// convolution, the groups concatenated.
    fn composed(x: &Tensor, k: &Tensor, stride: usize, pad: usize, group: usize) -> Tensor {
        crate::conv::in_groups(x, group, |x| {
            crate::in_precision(&[x, k], |t| {
                t[0].permute((0, 3, 1, 2))?
                    .conv2d(&t[1], pad, stride, 1, 1)?
                    .permute((0, 2, 3, 1))
            })
        })
        .unwrap()
    }

    fn bits(t: &Tensor) -> Vec<u32> {
        let v = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        v.iter().map(|x| x.to_bits()).collect()
    }

    fn values(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    }

    /// Within f32 rounding of another summation order: relative L2 error ≤ 1e-6.
    fn assert_close(a: &[f32], b: &[f32], what: &str) {
        let norm = b.iter().map(|v| v * v).sum::<f32>().sqrt();
        let err = a
            .iter()
            .zip(b)
            .map(|(p, q)| (p - q).powi(2))
            .sum::<f32>()
            .sqrt();
        assert!(err <= 1e-6 * norm, "{what}: {err} of {norm}");
    }

    /// Against the composed groups, one group and several, strides 1 and 2, ordinary
    /// and extreme scales: the same output bits; the input gradient (a product and
    /// col2im, where candle's is a transposed convolution) within f32 rounding of another
    /// summation order; the kernel's gradient the same where there is one group, within
    /// f32 rounding of a different summation order over groups otherwise. All finite. In f32 only: candle's CPU convolution
    /// has no bf16 product; the bf16 node runs in `osrt check-device`'s bf16 steps on a
    /// GPU (the `tiny` and `clevr-lite-cpu` encoders), against the CPU's f32 step.
    #[test]
    fn the_node_computes_the_composed_groups() {
        for (scale, bf16) in [(1.0f32, false), (1e-30, false), (1e18, false)] {
            for (stride, pad, group) in [(1, 1, 8), (2, 1, 2), (1, 0, 3)] {
                let x = Var::from_tensor(&randn(&[5, 9, 7, 4], scale, 1)).unwrap();
                let k = Var::from_tensor(&randn(&[6, 4, 3, 3], 0.3, 2)).unwrap();
                let p = if bf16 {
                    Precision::Bf16
                } else {
                    Precision::F32
                };
                let run = |node: bool| {
                    with_precision(p, || {
                        let (xt, kt) = (x.as_tensor(), k.as_tensor());
                        let y = match node {
                            true => conv2d_node(xt, kt, stride, pad, group, bf16).unwrap(),
                            false => composed(xt, kt, stride, pad, group),
                        };
                        let w = randn(y.dims(), 1.0, 3);
                        let g = (&y * &w).unwrap().sum_all().unwrap().backward().unwrap();
                        (y, g.get(xt).unwrap().clone(), g.get(kt).unwrap().clone())
                    })
                };
                let ((y1, dx1, dk1), (y0, dx0, dk0)) = (run(true), run(false));
                let case = format!("scale {scale:e} bf16 {bf16} stride {stride} group {group}");
                assert_eq!(bits(&y1), bits(&y0), "values, {case}");
                let (a, b) = (values(&dk1), values(&dk0));
                if group >= 5 {
                    assert_eq!(a, b, "kernel gradient, {case}");
                }
                assert_close(&a, &b, &format!("kernel gradient, {case}"));
                assert_close(
                    &values(&dx1),
                    &values(&dx0),
                    &format!("input gradient, {case}"),
                );
                assert!(
                    a.iter().chain(&values(&dx1)).all(|v| v.is_finite()),
                    "{case}"
                );
            }
        }
    }

    /// The f32 node against finite differences in f64 (where `f` takes candle's own
    /// convolution) and against candle's composed version.
    #[test]
    fn the_f32_node_matches_finite_differences() {
        let args = [randn(&[3, 6, 6, 2], 1.0, 4), randn(&[3, 2, 3, 3], 0.5, 5)];
        let f = |t: &[Tensor]| match enabled() {
            true => conv2d_node(&t[0], &t[1], 2, 1, 2, false),
            false => t[0]
                .permute((0, 3, 1, 2))?
                .conv2d(&t[1], 1, 2, 1, 1)?
                .permute((0, 2, 3, 1)),
        };
        assert_matches_composed(&args, f, 1e-5);
        finite_difference_check(&args, f);
        // Inputs that carry no gradient get none.
        let k = Var::from_tensor(&args[1]).unwrap();
        let g = with_fused(true, || {
            let y = conv2d_node(&args[0], k.as_tensor(), 1, 1, 2, false).unwrap();
            y.sum_all().unwrap().backward().unwrap()
        });
        assert!(g.get(&args[0]).is_none() && g.get(k.as_tensor()).is_some());
        // A non-square input whose rows and columns leave different remainders at stride
        // 2 (candle's transposed convolution takes one output padding for both, so the
        // node's gradient could not use it): col2im shapes it.
        let args = [randn(&[2, 6, 5, 2], 1.0, 6), args[1].clone()];
        finite_difference_check(&args, |t| conv2d_node(&t[0], &t[1], 2, 1, 2, false));
    }
}
