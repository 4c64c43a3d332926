//! The linear layer on the CPU: the bias add over rows, column sums (with a CUDA kernel
//! too), `x·Wᵀ` through `gemm`, the weight gradient summed over fixed row blocks, and the
//! one-node bias add and linear layer (with and without a bias) with their backward
//! passes.

use super::gemm;
use super::matrix::{MatRef, Threads};
use super::{ROWS_PER_TASK, f32_slice, rows_layout, with_last_dim};
use crate::Precision;
use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, D, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// `rows[i, :] += b` for every row of a `[rows, b.len()]` buffer, in place.
pub(crate) fn add_bias_rows(rows: &mut [f32], b: &[f32]) {
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
        crate::ledger::backward("", "linear", || {
            let db = grad
                .contiguous()?
                .apply_op1_no_bwd(&ColumnSum { d: b.elem_count() })?
                .reshape(b.shape())?;
            Ok((Some(grad.clone()), Some(db)))
        })
    }
}

/// Sum over rows of a `[rows, d]` buffer → `[d]`, in a fixed order of row blocks.
pub(crate) struct ColumnSum {
    pub(crate) d: usize,
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

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s: &candle_core::CudaStorage,
        l: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        crate::cuda::column_sum(s, l, self.d)
    }
}

/// `x: [.., d] + bias: [d]` as one node (f32 on the CPU).
pub(crate) fn bias_add(x: &Tensor, bias: &Tensor) -> Result<Tensor> {
    x.contiguous()?.apply_op2(&bias.contiguous()?, BiasAddOp)
}

// ---------------------------------------------------------------- linear

/// `x: [n, in] · W: [out, in]ᵀ` as an f32 buffer `[n, out]`, the product in `p`.
pub(crate) fn matmul_xwt(
    s1: &CpuStorage,
    l1: &Layout,
    s2: &CpuStorage,
    l2: &Layout,
    p: Precision,
) -> Result<Vec<f32>> {
    let (x, w) = (MatRef::of(s1, l1)?, MatRef::of(s2, l2)?);
    if x.dims().1 != w.dims().1 {
        candle_core::bail!("linear: input {:?}, weight {:?}", x.dims(), w.dims());
    }
    gemm::matmul(x, w.t(), Threads::Pool, p)
}

/// Rows per block of a weight gradient's split reduction ([`weight_grad`]).
pub(crate) const WGRAD_BLOCK_ROWS: usize = 2048;

/// The weight gradient `aᵀ·b` of a linear layer, `a: [rows, o]` (the output gradient),
/// `b: [rows, k]` (the layer input), both contiguous → `[o, k]`; the products in `p`.
///
/// Why not one gemm: gemm parallelises over blocks of the output and walks the reduction
/// (here the rows, 8,192 target rays in the decoder) in one sequence, so for a 128 × 128
/// output the second core mostly waits: at 2 threads such a product took 1.5–1.7 ms
/// against 2.5–2.7 at 1 (and 4.2–4.5 against 5.6–5.8 ms for 128 × 230). Here the rows are
/// cut into fixed blocks of [`WGRAD_BLOCK_ROWS`], the blocks' products computed in
/// parallel and summed in block order: 1.3 and 2.8–3.0 ms at 2 threads. The blocks do not
/// depend on the thread count, so neither do the bits.
pub(crate) fn weight_grad(
    a: &CpuStorage,
    a_l: &Layout,
    b: &CpuStorage,
    b_l: &Layout,
    p: Precision,
) -> Result<Vec<f32>> {
    let (a, b) = (MatRef::of(a, a_l)?, MatRef::of(b, b_l)?);
    let (rows, rows_b) = (a.dims().0, b.dims().0);
    if rows != rows_b {
        candle_core::bail!("weight gradient: {:?}ᵀ · {:?}", a.dims(), b.dims());
    }
    let block = |r0: usize, len: usize, threads: Threads| -> Result<Vec<f32>> {
        gemm::matmul(a.rows(r0, len)?.t(), b.rows(r0, len)?, threads, p)
    };
    let blocks = rows.div_ceil(WGRAD_BLOCK_ROWS);
    if blocks <= 1 {
        return block(0, rows, Threads::Pool);
    }
    let (f, dims) = (candle_core::DType::F32, (1, a.dims().1, b.dims().1, rows));
    let t = gemm::operand_type(p);
    crate::ledger::product(dims, (t, t, f), [true, false], [false; 2]);
    if t != f {
        crate::ledger::cast_of(rows * (a.dims().1 + b.dims().1), f, t);
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
pub(crate) struct WeightGrad(pub(crate) Precision);

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
            CpuStorage::F32(weight_grad(s1, l1, s2, l2, self.0)?),
            Shape::from((o, k)),
        ))
    }
}

/// `grad: [rows, o] · W: [o, k]` → `[rows, k]` as a no-grad op: a linear layer's input
/// gradient.
struct InputGrad(Precision);

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
        let dx = gemm::matmul(g, w, Threads::Pool, self.0)?;
        Ok((CpuStorage::F32(dx), Shape::from((g.dims().0, w.dims().1))))
    }
}

/// Gradients of `x·Wᵀ` for upstream `grad: [.., out]`: `dx = grad·W` only when `x` carries
/// a gradient (candle's matmul backward computes it for data inputs too), `dW = gradᵀ·x`.
fn linear_grads(
    x: &Tensor,
    w: &Tensor,
    grad: &Tensor,
    p: Precision,
) -> Result<(Option<Tensor>, Tensor)> {
    // `x: [.., in]` and `grad: [.., out]` as the 2-D `[rows, ·]` views the op computed on.
    let (x2, grad) = (
        x.reshape(((), x.dim(D::Minus1)?))?.contiguous()?,
        grad.reshape(((), w.dim(0)?))?.contiguous()?,
    );
    let dx = if x.track_op() {
        let dx = grad.apply_op2_no_bwd(&w.contiguous()?, &InputGrad(p))?;
        Some(dx.reshape(x.shape())?)
    } else {
        None
    };
    Ok((dx, grad.apply_op2_no_bwd(&x2, &WeightGrad(p))?))
}

/// `y = x·Wᵀ + b` as one graph node (`x: [.., in]`, `W: [out, in]`, `b: [out]`): the bias
/// is added into the matmul's output in place, and backward skips `dx` for data inputs
/// and one `[n, out]` gradient accumulation (zeros + add) that matmul + bias add cost.
/// The products, forward and backward, in the precision the node was made in.
struct LinearOp(Precision);

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
        let mut y = matmul_xwt(s1, &rows, s2, l2, self.0)?;
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
        crate::ledger::backward("", "linear", || {
            let grad = grad.contiguous()?;
            let (dx, dw) = linear_grads(x, w, &grad, self.0)?;
            let db = grad.apply_op1_no_bwd(&ColumnSum { d: b.elem_count() })?;
            Ok((dx, Some(dw), Some(db)))
        })
    }
}

/// `y = x·Wᵀ` as one graph node (see [`LinearOp`]).
struct LinearNoBiasOp(Precision);

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
        let y = matmul_xwt(s1, &rows_layout(l1)?, s2, l2, self.0)?;
        Ok((CpuStorage::F32(y), with_last_dim(l1, l2.dims()[0])))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        crate::ledger::backward("", "linear", || {
            let (dx, dw) = linear_grads(x, w, &grad.contiguous()?, self.0)?;
            Ok((dx, Some(dw)))
        })
    }
}

/// `x·weightᵀ (+ bias)` over all leading dims of `x: [.., in]` as one node (f32 on the
/// CPU; `weight: [out, in]`, `bias: [out]`), the products in this thread's precision.
pub(crate) fn linear(x: &Tensor, weight: &Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
    let (x, w) = (x.contiguous()?, weight.contiguous()?);
    let p = crate::precision();
    match bias {
        Some(b) => x.apply_op3(&w, &b.contiguous()?, LinearOp(p)),
        None => x.apply_op2(&w, LinearNoBiasOp(p)),
    }
}
