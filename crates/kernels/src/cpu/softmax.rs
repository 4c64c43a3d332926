//! Softmax over the last dimension on the CPU: the row kernels (shared with attention),
//! the one-node softmax with its backward pass (both with CUDA kernels too), and
//! no-grad forward and backward passes for hand-written backward passes elsewhere.

use super::{ROWS_PER_TASK, f32_slice, f32_slice_mut, fastmath, usable_with_cuda_any};
use candle_core::{CpuStorage, CustomOp1, CustomOp2, InplaceOp2, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// `o = softmax(x)` of one row.
pub(crate) fn softmax_row(o: &mut [f32], x: &[f32]) {
    // Shift by the row's maximum: exp never overflows, the largest term is 1.
    let m = x.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    // The exp kernel vectorises; the ordered sum stays a separate loop.
    fastmath::exp_shifted_slice(o, x, m);
    let sum: f32 = o.iter().sum();
    let inv = 1.0 / sum;
    o.iter_mut().for_each(|v| *v *= inv);
}

/// `o = y ⊙ (dy − Σ y ⊙ dy)` of one row: the softmax's input gradient from its output `y`.
pub(crate) fn softmax_row_grad(o: &mut [f32], y: &[f32], dy: &[f32]) {
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

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s: &candle_core::CudaStorage,
        l: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        crate::cuda::softmax_fwd(s, l)
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

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        crate::cuda::softmax_bwd(s1, l1, s2, l2)
    }
}

/// Softmax over the last dimension with no graph node (a forward pass whose backward is
/// written by hand: [`softmax_grad`]).
pub(crate) fn softmax_no_grad(x: &Tensor) -> Result<Tensor> {
    let x = x.detach();
    if usable_with_cuda_any(&[&x]) {
        return x.contiguous()?.apply_op1_no_bwd(&SoftmaxOp);
    }
    candle_nn::ops::softmax_last_dim(&x)
}

/// The input gradient of a last-dimension softmax from its output `y` and the output's
/// gradient `dy`: `y ⊙ (dy − Σ y ⊙ dy)` per row, with no graph node.
pub(crate) fn softmax_grad(y: &Tensor, dy: &Tensor) -> Result<Tensor> {
    let (y, dy) = (y.detach(), dy.detach());
    if usable_with_cuda_any(&[&y, &dy]) {
        return y
            .contiguous()?
            .apply_op2_no_bwd(&dy.contiguous()?, &SoftmaxBwd);
    }
    let dot = (&y * &dy)?.sum_keepdim(candle_core::D::Minus1)?;
    y * dy.broadcast_sub(&dot)?
}

/// `scale · softmax_grad(y, dy)` (candle's affine: `x · scale + 0`), written over `dy`
/// where the one-node ops apply: the caller gives up `dy`, which must be its own (no
/// other tensor sharing its storage), and gets it back as the result. Elsewhere the two
/// ops. The attention node's backward pass: the logits' gradient without a buffer of the
/// weights' size beside the weights' gradient.
pub(crate) fn softmax_grad_scaled(y: &Tensor, dy: Tensor, scale: f64) -> Result<Tensor> {
    let y = y.detach();
    let dy = dy.detach();
    if usable_with_cuda_any(&[&y, &dy]) && y.shape() == dy.shape() {
        let (y, dy) = (y.contiguous()?, dy.contiguous()?);
        dy.inplace_op2(
            &y,
            &SoftmaxBwdScaled {
                scale: scale as f32,
            },
        )?;
        return Ok(dy);
    }
    let g = softmax_grad(&y, &dy)?;
    drop(dy);
    g * scale
}

/// [`SoftmaxBwd`] times a scale, in place over the gradient (the first operand).
struct SoftmaxBwdScaled {
    scale: f32,
}

impl InplaceOp2 for SoftmaxBwdScaled {
    fn name(&self) -> &'static str {
        "osrt-softmax-last-dim-bwd-scaled-in-place"
    }

    fn cpu_fwd(
        &self,
        s1: &mut CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<()> {
        let y = f32_slice(s2, l2, "softmax backward in place output")?;
        let dy = f32_slice_mut(s1, l1, "softmax backward in place gradient")?;
        let d = l2.dims().last().copied().unwrap_or(1).max(1);
        if dy.len() != y.len() {
            candle_core::bail!(
                "softmax backward in place: {} gradients for {} outputs",
                dy.len(),
                y.len()
            );
        }
        let scale = self.scale;
        dy.par_chunks_mut(d * ROWS_PER_TASK)
            .zip(y.par_chunks(d * ROWS_PER_TASK))
            .for_each(|(o, y)| {
                for (o, y) in o.chunks_mut(d).zip(y.chunks(d)) {
                    // `softmax_row_grad`'s sum and products, then the affine's.
                    let dot: f32 = y.iter().zip(o.iter()).map(|(a, b)| a * b).sum();
                    for (o, y) in o.iter_mut().zip(y) {
                        *o = y * (*o - dot) * scale + 0.0;
                    }
                }
            });
        Ok(())
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &mut candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> Result<()> {
        crate::cuda::softmax_bwd_scaled_in_place(s2, l2, s1, l1, self.scale)
    }
}

/// Softmax over the last dimension as one node (f32 on the CPU or a CUDA device).
pub(crate) fn softmax_last_dim(x: &Tensor) -> Result<Tensor> {
    x.contiguous()?.apply_op1(SoftmaxOp)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::randn;
    use candle_core::Device;

    /// The scaled backward written over the gradient gives the bits of the backward op
    /// followed by candle's affine, on rows of one, ragged row counts, extreme logits and
    /// a non-power-of-two scale; it returns the tensor it was given.
    #[test]
    fn the_scaled_backward_in_place_gives_the_two_ops_bits() {
        let bits = |t: &Tensor| -> Vec<u32> {
            let v: Vec<f32> = t.flatten_all().unwrap().to_vec1().unwrap();
            v.iter().map(|x| x.to_bits()).collect()
        };
        for (i, dims) in [[3usize, 1], [37, 5], [301, 33], [6, 300]]
            .iter()
            .enumerate()
        {
            let mut x = randn(dims, 2.0, 70 + i as u64)
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            if dims[1] > 1 {
                x[0] = 1e30;
                x[1] = -3e38;
            }
            let x = Tensor::from_vec(x, &dims[..], &Device::Cpu).unwrap();
            let y = softmax_no_grad(&x).unwrap();
            let dy = randn(dims, 1.0, 80 + i as u64);
            for scale in [0.125, 1.0 / 128f64.sqrt()] {
                let want = (softmax_grad(&y, &dy).unwrap() * scale).unwrap();
                let mine = dy.copy().unwrap();
                let got = softmax_grad_scaled(&y, mine, scale).unwrap();
                assert_eq!(bits(&got), bits(&want), "{dims:?} scale {scale}");
            }
            // Where the one-node ops do not apply (bf16): the two ops.
            let (y16, dy16) = (
                y.to_dtype(candle_core::DType::BF16).unwrap(),
                dy.to_dtype(candle_core::DType::BF16).unwrap(),
            );
            let want = (softmax_grad(&y16, &dy16).unwrap() * 0.5).unwrap();
            let got = softmax_grad_scaled(&y16, dy16.copy().unwrap(), 0.5).unwrap();
            assert_eq!(
                bits(&got.to_dtype(candle_core::DType::F32).unwrap()),
                bits(&want.to_dtype(candle_core::DType::F32).unwrap())
            );
        }
        // The result is the gradient's own buffer: nothing of its size is allocated.
        let y = softmax_no_grad(&randn(&[4, 9], 1.0, 1)).unwrap();
        let dy = randn(&[4, 9], 1.0, 2);
        let mine = dy.copy().unwrap();
        let id = mine.id();
        let got = softmax_grad_scaled(&y, mine, 2.0).unwrap();
        assert_eq!(got.id(), id);
    }
}
