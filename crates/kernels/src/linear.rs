use crate::gemm::{self, MatRef, Threads};
use crate::*;
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
        let db = grad
            .contiguous()?
            .apply_op1_no_bwd(&ColumnSum { d: b.elem_count() })?
            .reshape(b.shape())?;
        Ok((Some(grad.clone()), Some(db)))
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

/// `x: [.., d] + bias: [d]`.
pub fn bias_add(x: &Tensor, bias: &Tensor) -> Result<Tensor> {
    crate::profile::op("bias_add", &[x, bias], |t| bias_add_here(&t[0], &t[1]))
}

fn bias_add_here(x: &Tensor, bias: &Tensor) -> Result<Tensor> {
    if usable(&[x, bias]) && x.dim(D::Minus1)? == bias.elem_count() && bias.rank() == 1 {
        return x.contiguous()?.apply_op2(&bias.contiguous()?, BiasAddOp);
    }
    x.broadcast_add(bias)
}

// ---------------------------------------------------------------- linear

/// `x: [n, in] · W: [out, in]ᵀ` as an f32 buffer `[n, out]`.
pub(crate) fn matmul_xwt(
    s1: &CpuStorage,
    l1: &Layout,
    s2: &CpuStorage,
    l2: &Layout,
) -> Result<Vec<f32>> {
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
pub(crate) fn weight_grad(
    a: &CpuStorage,
    a_l: &Layout,
    b: &CpuStorage,
    b_l: &Layout,
) -> Result<Vec<f32>> {
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
pub(crate) fn rows_layout(l: &Layout) -> Result<Layout> {
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
pub(crate) fn with_last_dim(l: &Layout, last: usize) -> Shape {
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
    let mut all = vec![x, weight];
    all.extend(bias);
    crate::profile::op("linear", &all, |t| linear_here(&t[0], &t[1], t.get(2)))
}

fn linear_here(x: &Tensor, weight: &Tensor, bias: Option<&Tensor>) -> Result<Tensor> {
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
    // On the device graph a layer with a bias is the one-layer MLP node: the same ops (the
    // product, then the bias added in f32), without the product kept beside the output
    // for the backward pass (a bias add's needs neither).
    if let Some(b) = bias
        && fits
        && crate::enabled()
        && crate::usable_with_cuda_any(&all)
        && crate::device_graph(x)
    {
        let bf16 = crate::precision() == crate::Precision::Bf16;
        // The activation is never applied: the one layer is the last.
        let layer = [(weight, Some(b))];
        if let Some(y) = crate::mlp_node::mlp_node(x, &layer, MlpAct::Relu, bf16)? {
            return Ok(y);
        }
    }
    linear_act(x, weight, bias, None)
}

/// [`linear`] without a bias, the output stored as the bf16 product returns it where the
/// products run in bf16 on the device graph ([`crate::matmul_low`]: for an output whose
/// one reader is another product or an op that reads it in f32, such as attention's
/// projections); elsewhere [`linear`].
///
/// # Shapes
/// `x: [.., in]`, `weight: [out, in]` → `[.., out]`
pub fn linear_low(x: &Tensor, weight: &Tensor) -> Result<Tensor> {
    crate::profile::op("linear", &[x, weight], |t| {
        let (x, w) = (&t[0], &t[1]);
        if !(w.rank() == 2 && crate::stores_low(&[x, w])) {
            return linear_here(x, w, None);
        }
        let Some((&k, lead)) = x.dims().split_last() else {
            candle_core::bail!("linear: a scalar input")
        };
        let mut out = lead.to_vec();
        out.push(w.dim(0)?);
        crate::matmul_low(&x.reshape(((), k))?, &w.t()?)?.reshape(out)
    })
}

/// [`linear`] followed by `act`, from candle's matrix product, with the bias and the
/// activation as one node where [`crate::bias_act`] applies (f32 on a GPU): the path of
/// every linear layer on a GPU.
pub(crate) fn linear_act(
    x: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    act: Option<MlpAct>,
) -> Result<Tensor> {
    let composed = |x: &Tensor| -> Result<Tensor> {
        let y = matmul(x, &weight.t()?)?;
        match (bias, act) {
            (Some(b), _) => crate::bias_act(&y, b, act),
            (None, Some(a)) => a.apply(&y),
            (None, None) => Ok(y),
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
mod tests {
    use super::*;
    use crate::testing::*;
    use candle_core::{Device, Var};

    /// On the device graph a layer with a bias (the one-layer MLP node) gives the bits of
    /// the product followed by the bias node, values and the gradients of input, weight
    /// and bias, in f32 and in bf16 (with an f32 input and with a bf16-stored one).
    #[test]
    fn the_device_graph_biased_layer_gives_the_product_and_bias_bits() {
        use crate::{Kernels, Precision, with_kernels, with_precision};
        use candle_core::DType;
        for (p, dtype) in [
            (Precision::F32, DType::F32),
            (Precision::Bf16, DType::F32),
            (Precision::Bf16, DType::BF16),
        ] {
            let x =
                Var::from_tensor(&randn(&[2, 9, 11], 1.0, 41).to_dtype(dtype).unwrap()).unwrap();
            let w = Var::from_tensor(&randn(&[6, 11], 0.5, 42)).unwrap();
            let b = Var::from_tensor(&randn(&[6], 0.5, 43)).unwrap();
            let run = |node: bool| -> Vec<Vec<u32>> {
                with_kernels(Kernels::Device, || {
                    with_precision(p, || {
                        let (xt, wt, bt) = (x.as_tensor(), w.as_tensor(), b.as_tensor());
                        let y = match node {
                            true => linear(xt, wt, Some(bt)),
                            false => linear_act(xt, wt, Some(bt), None),
                        }
                        .unwrap();
                        let r = randn(y.dims(), 1.0, 44);
                        let g = (&y * &r).unwrap().sum_all().unwrap().backward().unwrap();
                        let dx = g.get(xt).unwrap();
                        assert_eq!(dx.dtype(), dtype);
                        vec![
                            f32_bits(&y),
                            f32_bits(dx),
                            f32_bits(g.get(wt).unwrap()),
                            f32_bits(g.get(bt).unwrap()),
                        ]
                    })
                })
            };
            assert_eq!(run(true), run(false), "{p} {dtype:?}");
        }
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
}
