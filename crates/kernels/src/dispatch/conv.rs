//! The choice of the convolution over channels-last input: the fused CPU node where it
//! applies, on the device graph the convolution node built from tensor ops, else
//! candle's convolution (on a GPU over groups of images), with ReLU after it where asked.

use super::{pointwise, usable};
use crate::cpu::conv::{self, ConvGeom};
use crate::graph::conv_node::{conv2d_node, in_groups};
use crate::graph::matmul::in_precision;
use crate::{Precision, device_graph, enabled, precision, profile};
use candle_core::{Result, Tensor};

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
    profile::op("conv2d", &[x, kernel], move |t| {
        conv2d_nhwc_here(&t[0], &t[1], stride, padding, false)
    })
}

/// `relu(conv2d_nhwc(x, kernel, stride, padding))`; on the device graph one node that keeps
/// a one-byte mask where the graph of the two ops would keep the convolution's f32
/// output (`graph::conv_node`). The same values and gradients.
///
/// # Shapes
/// `x: [n, h, w, c_in]`, `kernel: [c_out, c_in, k, k]` → `[n, h_out, w_out, c_out]`
pub fn conv2d_relu_nhwc(
    x: &Tensor,
    kernel: &Tensor,
    stride: usize,
    padding: usize,
) -> Result<Tensor> {
    profile::op("conv2d_relu", &[x, kernel], move |t| {
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
        true => pointwise::relu(&y),
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
            // One node over all groups, keeping no per-group copies (`graph::conv_node`).
            let f32s = x.dtype() == candle_core::DType::F32 && kernel.dtype() == x.dtype();
            let bf16 = precision() == Precision::Bf16 && f32s;
            return conv2d_node(x, kernel, stride, padding, group, bf16, relu);
        }
        if x.device().is_cpu() {
            return then_relu(conv(x)?);
        }
        return then_relu(in_groups(x, group, conv)?);
    }
    let geom = ConvGeom::new(n, (h, w, c), k, stride, padding);
    then_relu(conv::conv2d(x, kernel, geom, co)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cpu::conv::Im2Col;
    use crate::dispatch::linear::linear;
    use crate::testing::{
        assert_matches_composed, both, finite_difference_check, max_abs, max_diff, randn,
    };
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
            let geom = ConvGeom::new(n, (h, w, c), k, stride, pad);
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
                            false => pointwise::relu(&conv2d_nhwc(xt, kt, 2, 1).unwrap()).unwrap(),
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
