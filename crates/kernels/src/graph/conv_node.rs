//! A convolution over channels-last input as one graph node, for devices without osrt's
//! fused convolution (a GPU): the input's unfolding (im2col, `cpu::conv`, a CUDA kernel on
//! a GPU) times the kernel matrix (cuBLAS), over groups of images.
//!
//! Why one node: composed, the device convolution runs over groups of images ([`in_groups`]:
//! candle's unfolded buffer is indexed with 32-bit numbers; the groups also cap the
//! unfolded buffer's memory here), each group is its own chain of graph nodes, and the
//! concatenation of their outputs keeps every group's output beside the whole output
//! until the backward pass; in bf16 each group also keeps the bf16 copies of its input
//! and of its output. This node keeps only its f32 operands (the input, which the step
//! keeps for the previous op anyway, and the kernel).
//!
//! Why its own unfolding: the output comes out channels-last, with no permuted copies of
//! the input and the output around candle's channels-first convolution; and the backward
//! pass is two products. Group by group in the forward pass's precision: the input's
//! gradient is the output's gradient times the kernel matrix, summed back onto the
//! pixels (col2im, in f32, deterministic); candle's own, a transposed convolution, is a
//! direct loop over every output pixel's channels and taps on a GPU. The kernel's
//! gradient is the output's gradient (transposed) times the input's unfolding, made
//! again. The result is handed to the graph through the node's forward pass, which
//! returns a copy of it (the size of the output).
//!
//! With `relu`, the node is the convolution followed by ReLU ([`crate::conv2d_relu_nhwc`],
//! the encoder's CNN). As two ops, candle's graph keeps both the
//! convolution's output (ReLU's input, for its gradient) and ReLU's output (the next
//! convolution's input; PyTorch's ReLU keeps only that one); this node keeps only where
//! the convolution's output was ≥ 0, one byte per value (a quarter of the f32 output), and
//! its backward pass masks the output's gradient as candle's ReLU does, so the values and
//! gradients are those of the convolution node followed by candle's `relu`, bit for bit.

use super::handover::Handover;
use super::node::{Node, TensorNode};
use crate::cpu::conv::{ConvGeom, col2im, im2col};
use crate::kept::Kept;
use crate::ledger;
use candle_core::{DType, Result, Tensor};

/// `x: [n, h, w, c_in]`, `kernel: [c_out, c_in, k, k]` → `[n, h_out, w_out, c_out]`, over
/// groups of `group` images, with bf16 operands (the result in f32) where `bf16` is set.
pub(crate) fn conv2d_node(
    x: &Tensor,
    kernel: &Tensor,
    stride: usize,
    padding: usize,
    group: usize,
    bf16: bool,
    relu: bool,
) -> Result<Tensor> {
    let geom = Geom {
        stride,
        padding,
        group: group.max(1),
        bf16,
    };
    let c = geom.forward(&x.detach(), &kernel.detach())?;
    let keep = x.track_op() || kernel.track_op();
    let (y, mask) = match relu {
        true => {
            let y = c.relu()?;
            ledger::op("relu", &[&c], &[&y]);
            (y, keep.then(|| relu_mask(&c)).transpose()?)
        }
        false => (c, None),
    };
    let node = ConvNode {
        out: Handover::new(y)?,
        geom,
        relu,
        mask: Kept::new(mask),
    };
    x.apply_op2(kernel, Node::new(node))
}

/// Where ReLU passes the gradient: the convolution's output `c` ≥ 0 (candle's `relu`
/// passes it at 0 too), as `u8`.
fn relu_mask(c: &Tensor) -> Result<Tensor> {
    let m = c.ge(&c.zeros_like()?)?;
    ledger::op("relu mask", &[c], &[&m]);
    Ok(m)
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
            true => ledger::cast(t, DType::BF16),
            false => Ok(t.clone()),
        }
    }

    /// A result back in f32 (where the products ran in bf16).
    fn high(&self, t: Tensor) -> Result<Tensor> {
        match self.bf16 && t.dtype() == DType::BF16 {
            true => ledger::cast(&t, DType::F32),
            false => Ok(t),
        }
    }

    /// The groups' starts and lengths over `n` images.
    fn groups(&self, n: usize) -> Vec<(usize, usize)> {
        let g = self.group;
        (0..n).step_by(g).map(|i| (i, g.min(n - i))).collect()
    }

    /// The unfolding of `len` images of `x`'s size under `kernel`.
    fn fold(&self, len: usize, x: &Tensor, kernel: &Tensor) -> Result<ConvGeom> {
        let (_, h, w, c) = x.dims4()?;
        let k = kernel.dim(2)?;
        Ok(ConvGeom::new(len, (h, w, c), k, self.stride, self.padding))
    }

    /// The forward pass: per group, the operands in the products' precision, the
    /// input's unfolding (im2col) times the kernel matrix's transpose (cuBLAS on a GPU),
    /// which is the output in NHWC, back in f32.
    fn forward(&self, x: &Tensor, kernel: &Tensor) -> Result<Tensor> {
        let k = self.low(kernel)?;
        let (co, ci, kh, kw) = k.dims4()?;
        let kmat_t = k.reshape((co, ci * kh * kw))?.t()?;
        let one = |x: &Tensor| -> Result<Tensor> {
            let geom = self.fold(x.dim(0)?, x, kernel)?;
            let y = ledger::mm(&unfold(&self.low(x)?, geom)?, &kmat_t)?;
            let (n, ho, wo) = geom.output();
            self.high(y.reshape((n, ho, wo, co))?)
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
        cat(&parts)
    }
}

/// [`im2col`], entered in the ledger.
fn unfold(x: &Tensor, geom: ConvGeom) -> Result<Tensor> {
    let cols = im2col(x, geom)?;
    ledger::op("im2col", &[x], &[&cols]);
    Ok(cols)
}

/// The groups' results side by side (a copy), entered in the ledger.
fn cat(parts: &[Tensor]) -> Result<Tensor> {
    let t = Tensor::cat(parts, 0)?;
    ledger::cast_of(t.elem_count(), t.dtype(), t.dtype());
    Ok(t)
}

/// `[n, h, w, c]` → `[n·h·w, c]`, contiguous (the rows a matrix product takes).
fn dy_rows(dy: &Tensor) -> Result<Tensor> {
    let (n, h, w, c) = dy.dims4()?;
    ledger::contiguous(dy)?.reshape((n * h * w, c))
}

struct ConvNode {
    out: Handover,
    geom: Geom,
    /// ReLU follows the convolution.
    relu: bool,
    /// With `relu`, where the convolution's output was ≥ 0 (`u8`), for the backward pass.
    mask: Kept<Tensor>,
}

impl TensorNode for ConvNode {
    fn name(&self) -> &'static str {
        "osrt-conv-node"
    }

    fn what(&self) -> &'static str {
        "conv node"
    }

    fn out(&self) -> &Handover {
        &self.out
    }

    /// Per group (see the module docs): the input's gradient by product and col2im, the
    /// kernel's by product with the unfolding; the kernel's gradient is the groups' sum,
    /// in group order. With `relu`, the output's gradient masked first.
    fn backward(&self, operands: &[&Tensor], grad: &Tensor) -> Result<Vec<Option<Tensor>>> {
        let &[x, kernel] = operands else {
            candle_core::bail!("conv node: {} operands", operands.len())
        };
        let g = self.geom;
        let (want_dx, want_dk) = (x.track_op(), kernel.track_op());
        // Detached: products of tracked operands would carry a graph (the unfolded
        // columns) into candle's gradient store until the backward pass ends.
        let (x, kernel) = (&x.detach(), &kernel.detach());
        let masked;
        let grad = match self.relu {
            false => grad,
            true => {
                let mask = match self.mask.take() {
                    Some(m) => m,
                    // A second backward pass: the convolution again.
                    None => relu_mask(&g.forward(x, kernel)?)?,
                };
                // candle's ReLU backward: the gradient times the mask, added to the zero
                // its gradient starts from (`+ 0` turns a -0 into +0, as that add does).
                let m = ledger::cast(&mask, grad.dtype())?;
                masked = (grad.detach() * m)?.affine(1.0, 0.0)?;
                ledger::op("relu backward", &[grad, &mask], &[&masked]);
                &masked
            }
        };
        let (n, _, _, ci) = x.dims4()?;
        let (_, _, kh, kw) = kernel.dims4()?;
        let k = g.low(kernel)?;
        let kmat = k.reshape((k.dim(0)?, ci * kh * kw))?;
        let (mut dxs, mut dk) = (Vec::new(), None::<Tensor>);
        for (i, len) in g.groups(n) {
            // The group's output gradient as rows, in the products' precision.
            let dy = dy_rows(&g.low(&grad.narrow(0, i, len)?)?)?;
            if want_dx {
                // The columns' gradient, one product with the kernel matrix (cuBLAS on a
                // GPU), summed back onto the pixels they were read from (col2im, in f32).
                let dcols = ledger::mm(&dy, &kmat)?;
                let dx = col2im(&dcols, g.fold(len, x, kernel)?)?;
                ledger::op("col2im", &[&dcols], &[&dx]);
                dxs.push(dx);
            }
            if want_dk {
                // The output's gradient (transposed) times the input's unfolding again.
                let xg = g.low(&x.narrow(0, i, len)?)?;
                let cols = unfold(&xg, g.fold(len, x, kernel)?)?;
                let d = ledger::mm(&dy.t()?, &cols)?;
                let d = g.high(d.reshape(kernel.shape())?)?;
                dk = Some(match dk {
                    Some(acc) => {
                        ledger::op("add", &[&acc, &d], &[&d]);
                        (acc + d)?
                    }
                    None => d,
                });
            }
        }
        let dx = match dxs.len() {
            0 => None,
            1 => dxs.pop(),
            _ => Some(cat(&dxs)?),
        };
        Ok(vec![dx, dk])
    }
}

/// `f` over groups of at most `group` leading entries of `x`, concatenated (the device's
/// convolution from candle's ops, in groups whose unfolded buffers stay small).
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::matmul::in_precision;
    use crate::testing::{
        assert_matches_composed, assert_second_backward_agrees, finite_difference_check, randn,
    };
    use crate::{Precision, enabled, with_fused, with_precision};
    use candle_core::Var;

    /// The composed device path of `crate::dispatch::conv`: per group, `in_precision`
    /// around candle's convolution, the groups concatenated.
    fn composed(x: &Tensor, k: &Tensor, stride: usize, pad: usize, group: usize) -> Tensor {
        in_groups(x, group, |x| {
            in_precision(&[x, k], |t| {
                t[0].permute((0, 3, 1, 2))?
                    .conv2d(&t[1], pad, stride, 1, 1)?
                    .permute((0, 2, 3, 1))
            })
        })
        .unwrap()
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

    /// Against the composed groups (candle's convolution and its backward pass), one
    /// group and several, strides 1 and 2, ordinary and extreme scales: values and both
    /// gradients (unfolding and products here) within f32 rounding of another summation
    /// order, relative L2 ≤ 1e-6. All finite. In f32 only: candle's CPU convolution
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
                            true => conv2d_node(xt, kt, stride, pad, group, bf16, false).unwrap(),
                            false => composed(xt, kt, stride, pad, group),
                        };
                        let w = randn(y.dims(), 1.0, 3);
                        let g = (&y * &w).unwrap().sum_all().unwrap().backward().unwrap();
                        (y, g.get(xt).unwrap().clone(), g.get(kt).unwrap().clone())
                    })
                };
                let ((y1, dx1, dk1), (y0, dx0, dk0)) = (run(true), run(false));
                let case = format!("scale {scale:e} bf16 {bf16} stride {stride} group {group}");
                assert_close(&values(&y1), &values(&y0), &format!("values, {case}"));
                let (a, b) = (values(&dk1), values(&dk0));
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
            true => conv2d_node(&t[0], &t[1], 2, 1, 2, false, false),
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
            let y = conv2d_node(&args[0], k.as_tensor(), 1, 1, 2, false, false).unwrap();
            y.sum_all().unwrap().backward().unwrap()
        });
        assert!(g.get(&args[0]).is_none() && g.get(k.as_tensor()).is_some());
        // A non-square input whose rows and columns leave different remainders at stride
        // 2 (candle's transposed convolution takes one output padding for both, so the
        // node's gradient could not use it): col2im shapes it.
        let args = [randn(&[2, 6, 5, 2], 1.0, 6), args[1].clone()];
        finite_difference_check(&args, |t| conv2d_node(&t[0], &t[1], 2, 1, 2, false, false));
    }

    /// The node with ReLU gives the bits of the node followed by candle's `relu` (values
    /// and both gradients, signs of zeros included), in f32 and bf16, over several groups,
    /// with an input whose zero regions make outputs exactly 0 (where ReLU's gradient is
    /// 1); it keeps a one-byte mask; it matches finite differences, and a second backward
    /// pass (the mask taken by the first) gives the same gradients.
    #[test]
    fn the_relu_node_is_the_node_followed_by_relu() {
        // Half of the images all zero: their outputs are exactly 0.
        let x = randn(&[4, 6, 5, 3], 1.0, 40);
        let zero = Tensor::zeros((2, 6, 5, 3), DType::F32, x.device()).unwrap();
        let x = Tensor::cat(&[&x.narrow(0, 0, 2).unwrap(), &zero], 0).unwrap();
        let k = randn(&[4, 3, 3, 3], 0.5, 41);
        for bf16 in [false, true] {
            let (xv, kv) = (Var::from_tensor(&x).unwrap(), Var::from_tensor(&k).unwrap());
            let run = |fused: bool| {
                let (xt, kt) = (xv.as_tensor(), kv.as_tensor());
                let y = match fused {
                    true => conv2d_node(xt, kt, 2, 1, 3, bf16, true).unwrap(),
                    false => conv2d_node(xt, kt, 2, 1, 3, bf16, false)
                        .unwrap()
                        .relu()
                        .unwrap(),
                };
                let w = randn(y.dims(), 1.0, 42);
                let g = (&y * &w).unwrap().sum_all().unwrap().backward().unwrap();
                let bits =
                    |t: &Tensor| -> Vec<u32> { values(t).iter().map(|v| v.to_bits()).collect() };
                [bits(&y), bits(g.get(xt).unwrap()), bits(g.get(kt).unwrap())]
            };
            assert_eq!(run(true), run(false), "bf16 {bf16}");
        }
        let c = Tensor::new(&[[-1f32, 0.0, -0.0, 2.0]], &candle_core::Device::Cpu).unwrap();
        let mask = relu_mask(&c).unwrap();
        assert_eq!(mask.dtype(), DType::U8);
        assert_eq!(mask.to_vec2::<u8>().unwrap(), [[0, 1, 1, 1]]);
        let args = [randn(&[2, 5, 4, 3], 1.0, 43), randn(&[2, 3, 3, 3], 0.5, 44)];
        let f = |t: &[Tensor]| match enabled() && t[0].dtype() == DType::F32 {
            true => conv2d_node(&t[0], &t[1], 1, 1, 1, false, true),
            false => conv2d_node(&t[0], &t[1], 1, 1, 1, false, false)?.relu(),
        };
        finite_difference_check(&args, f);
        assert_second_backward_agrees(&args, f);
    }
}
