//! The matrix product every node is built from: [`matmul`] and [`matmul_low`] in the
//! thread's precision, as one graph node (`MatmulNode`) where the one-node ops are on,
//! else candle's product; and the precision helpers of the products ([`stores_low`],
//! [`in_precision`]).
//!
//! The node is a matrix product of f32 tensors, in f32 or on bf16 operands.
//!
//! Why, in bf16: composed from candle's ops, `a · b` in bf16 is four nodes (two casts
//! down, the bf16 product, the cast of the product back up), and candle's graph keeps
//! every node's inputs until the backward pass: the bf16 copies of both operands and the
//! bf16 product stay alive beside the f32 tensors the step keeps anyway, so a bf16 step
//! held more memory than the f32 one (the `paper` preset at batch 32 on a GPU: 89.6
//! against 83.0 GiB). This node computes the same ops in the same order (cast, product,
//! cast) and keeps only its f32 operands; its backward pass casts them again.
//!
//! Why, in f32 too: candle's backward pass of its own product computes a weight's
//! gradient as `aᵀ · grad` from the tracked activation `a`, so that gradient carries a
//! graph holding the output's gradient (the size of the output), and candle's gradient
//! store keeps it until the whole backward pass has ended: one output gradient per
//! linear layer, pinned beside the activations. This node's backward pass multiplies
//! detached operands, so its gradients hold nothing else.
//!
//! The values and gradients are candle's (f32) or the composed version's (bf16) bit for
//! bit.
//!
//! In bf16 the product can also be stored as it comes out of the bf16 product (see
//! [`crate::matmul_low`]), and either operand may be such a stored bf16 tensor: a bf16
//! operand is read where it lies (row-major or transposed; other layouts are copied
//! first) and its gradient is returned in bf16 (the bf16 product's
//! result, which the f32 version would cast up exactly), so the values and gradients
//! are the f32-stored version's, while the graph holds half the bytes.

use crate::{Precision, device_graph, enabled, ledger, precision, profile};
use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp2, DType, Layout, Result, Shape, Tensor};

/// `a · b` (candle's batched matmul) in this thread's [`precision`]; with the fused ops
/// on, as one node that keeps no bf16 copies and whose gradients hold no graph
/// (`MatmulNode`).
pub fn matmul(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    profile::op("matmul", &[a, b], |t| {
        let f32s = t.iter().all(|t| t.dtype() == candle_core::DType::F32);
        if enabled() && (f32s || stores_low(&[&t[0], &t[1]])) {
            let bf16 = precision() == Precision::Bf16;
            if bf16 && f32s && fused_cpu(&t[0], &t[1]) {
                // The fused CPU kernels' products: bf16 where the CPU has a unit for them,
                // else f32, as theirs.
                return match crate::cpu::gemm::operand_type(Precision::Bf16) == DType::BF16 {
                    true => t[0].apply_op2(&t[1], MatmulNode::fused_cpu()),
                    false => matmul_node(&t[0], &t[1], false),
                };
            }
            return matmul_node(&t[0], &t[1], bf16);
        }
        composed(&t[0], &t[1])
    })
}

/// candle's product in this thread's precision (`in_precision`), entered in the ledger
/// with what candle's backward pass of it will compute: the two products, and in bf16
/// the gradient's cast down and the operands' gradients' casts back up.
fn composed(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    let y = in_precision(&[a, b], |t| ledger::mm(&t[0], &t[1]))?;
    if ledger::on() && (a.track_op() || b.track_op()) {
        let low = precision() == Precision::Bf16 && [a, b].iter().all(|t| t.dtype() == DType::F32);
        let (p, out) = match low {
            true => (DType::BF16, DType::BF16),
            false => (a.dtype(), y.dtype()),
        };
        ledger::in_phase(ledger::Phase::Backward, || {
            if low {
                ledger::cast_of(y.elem_count(), DType::F32, DType::BF16);
                for t in [a, b].into_iter().filter(|t| t.track_op()) {
                    ledger::cast_of(t.elem_count(), DType::BF16, DType::F32);
                }
            }
            let (batch, m, n, k) = ledger::bmnk(a.dims(), b.dims());
            ledger::product((batch, m, k, n), (p, p, out), [false, true], [false, false]);
            ledger::product((batch, k, n, m), (p, p, out), [true, false], [false, false]);
        });
    }
    Ok(y)
}

/// [`matmul`], the product stored as the bf16 product returns it where the products run
/// in bf16 on the device graph (else as [`matmul`]): for a product whose one reader is
/// another bf16 product or an op that reads it in f32, where storing it in f32 would
/// only double the bytes the graph keeps (autocast stores a product in bf16 too). The
/// values and gradients are [`matmul`]'s (`MatmulNode`).
pub fn matmul_low(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    profile::op("matmul", &[a, b], |t| {
        if stores_low(&[&t[0], &t[1]]) {
            return matmul_node_low(&t[0], &t[1]);
        }
        matmul(&t[0], &t[1])
    })
}

/// Whether products of `ts` run on bf16 operands with the device graph's nodes, which
/// also take (and may store) bf16 tensors ([`matmul_low`]).
pub(crate) fn stores_low(ts: &[&Tensor]) -> bool {
    enabled()
        && precision() == Precision::Bf16
        && ts.iter().all(|t| {
            matches!(t.dtype(), DType::F32 | DType::BF16)
                && t.rank() >= 1
                && device_graph(t)
                && (t.device().is_cpu() || (cfg!(feature = "cuda") && t.device().is_cuda()))
        })
}

/// Runs a product-like op on its f32 operands rounded to bf16 when the thread's precision
/// asks for it (the result back in f32; the casts carry the gradient back to f32).
pub(crate) fn in_precision(
    ts: &[&Tensor],
    op: impl FnOnce(&[Tensor]) -> Result<Tensor>,
) -> Result<Tensor> {
    let cast = precision() == Precision::Bf16 && ts.iter().all(|t| t.dtype() == DType::F32);
    if !cast {
        let owned: Vec<Tensor> = ts.iter().map(|t| (*t).clone()).collect();
        return op(&owned);
    }
    let low = ts
        .iter()
        .map(|t| ledger::cast(t, DType::BF16))
        .collect::<Result<Vec<_>>>()?;
    ledger::cast(&op(&low)?, DType::F32)
}

/// `a · b` in f32, or with both operands rounded to bf16 and the product returned in f32
/// where `bf16` is set (see the module docs). `a: [.., m, k]`, `b: [.., k, n]` (the same
/// leading dims) → `[.., m, n]`.
pub(crate) fn matmul_node(a: &Tensor, b: &Tensor, bf16: bool) -> Result<Tensor> {
    a.apply_op2(
        b,
        MatmulNode {
            bf16,
            low: false,
            made: ledger::context().0,
            fused_cpu: false,
        },
    )
}

/// [`matmul_node`] in bf16, the product stored in bf16 (as the bf16 product returns it).
pub(crate) fn matmul_node_low(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    a.apply_op2(
        b,
        MatmulNode {
            bf16: true,
            low: true,
            made: ledger::context().0,
            fused_cpu: false,
        },
    )
}

struct MatmulNode {
    bf16: bool,
    /// The product stays in bf16 (only with `bf16`).
    low: bool,
    /// The ledger's op kind where the node was made (its backward pass's kind).
    made: &'static str,
    /// The fused CPU kernels' bf16 products (`crate::cpu::gemm`) on f32 operands as they
    /// lie, forward and backward, where the CPU has bf16 products (only with `bf16`).
    fused_cpu: bool,
}

/// Whether a bf16 product of `a` and `b` is the fused CPU kernels': the `fused` kernels,
/// f32 operands on the CPU.
fn fused_cpu(a: &Tensor, b: &Tensor) -> bool {
    crate::kernels() == crate::Kernels::Fused
        && [a, b]
            .iter()
            .all(|t| t.device().is_cpu() && t.dtype() == DType::F32)
}

impl MatmulNode {
    fn fused_cpu() -> Self {
        Self {
            bf16: true,
            low: false,
            made: ledger::context().0,
            fused_cpu: true,
        }
    }
}

/// Whether a product reads an operand of layout `l` as it lies: its last two dims
/// row-major or transposed by strides, its leading dims one after the other (what
/// candle's products take without a copy).
fn readable(l: &Layout) -> bool {
    let (d, s) = (l.dims(), l.stride());
    let r = d.len();
    let Some(_) = ledger::reads_as(l) else {
        return false;
    };
    // Each leading dim's stride is the size of everything after it.
    let mut size = d[r.saturating_sub(2)..].iter().product::<usize>();
    for i in (0..r.saturating_sub(2)).rev() {
        if d[i] > 1 && s[i] != size {
            return false;
        }
        size *= d[i];
    }
    true
}

/// `(batch, m, n, k)` and the product's shape, as `Tensor::matmul` checks them.
fn dims(la: &Layout, lb: &Layout) -> Result<((usize, usize, usize, usize), Shape)> {
    let (a, b) = (la.dims(), lb.dims());
    let r = a.len();
    if r < 2 || b.len() != r || a[..r - 2] != b[..r - 2] || a[r - 1] != b[r - 2] {
        candle_core::bail!("bf16 matmul: shapes {a:?} and {b:?} do not multiply");
    }
    let (m, k, n) = (a[r - 2], a[r - 1], b[r - 1]);
    let batch = a[..r - 2].iter().product();
    Ok(((batch, m, n, k), Shape::from(&a[..r - 2]).extend(&[m, n])))
}

/// The forward pass on any backend's storage: in bf16 cast down, multiply, cast up; in
/// f32 the product as candle's `Tensor::matmul` computes it.
fn forward<S: BackendStorage>(
    a: &S,
    la: &Layout,
    b: &S,
    lb: &Layout,
    node: &MatmulNode,
) -> Result<(S, Shape)> {
    let takes = |d: DType| d == DType::F32 || (node.bf16 && d == DType::BF16);
    if !takes(a.dtype()) || !takes(b.dtype()) {
        candle_core::bail!("matmul node: takes f32 operands (or bf16 ones in bf16)");
    }
    let (bmnk, shape) = dims(la, lb)?;
    let read = |l: &Layout| ledger::reads_as(l).unwrap_or(false);
    if !node.bf16 {
        let y = a.matmul(b, bmnk, la, lb)?;
        let types = (a.dtype(), b.dtype(), y.dtype());
        ledger::product(bmnk, types, [read(la), read(lb)], [false, false]);
        return Ok((y, shape));
    }
    // An operand already in bf16 that the product reads as it lies (row-major, or
    // transposed by strides) is read in place; any other is cast, which writes a
    // contiguous copy (the values are the same either way).
    let cast = |s: &S, l: &Layout| -> Result<Option<S>> {
        if s.dtype() == DType::BF16 && readable(l) {
            return Ok(None);
        }
        ledger::cast_of(l.shape().elem_count(), s.dtype(), DType::BF16);
        s.to_dtype(l, DType::BF16).map(Some)
    };
    let (a16, b16) = (cast(a, la)?, cast(b, lb)?);
    // A cast's copy is contiguous; an operand read in place keeps its layout.
    let layout = |cast: &Option<S>, l: &Layout| match cast {
        Some(_) => Layout::contiguous(l.shape()),
        None => l.clone(),
    };
    let (ca, cb) = (layout(&a16, la), layout(&b16, lb));
    let (sa, sb) = (a16.as_ref().unwrap_or(a), b16.as_ref().unwrap_or(b));
    let out = if node.low { DType::BF16 } else { DType::F32 };
    let types = (DType::BF16, DType::BF16, out);
    let copied = [a16.is_some(), b16.is_some()];
    ledger::product(bmnk, types, [read(&ca), read(&cb)], copied);
    let y16 = sa.matmul(sb, bmnk, &ca, &cb)?;
    if node.low {
        return Ok((y16, shape));
    }
    ledger::cast_of(shape.elem_count(), DType::BF16, DType::F32);
    let y = y16.to_dtype(&Layout::contiguous(&shape), DType::F32)?;
    Ok((y, shape))
}

impl CustomOp2 for MatmulNode {
    fn name(&self) -> &'static str {
        "osrt-matmul"
    }

    fn cpu_fwd(
        &self,
        a: &CpuStorage,
        la: &Layout,
        b: &CpuStorage,
        lb: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        if self.fused_cpu {
            let (bmnk, shape) = dims(la, lb)?;
            let y = crate::cpu::gemm::batched((a, la), (b, lb), bmnk, Precision::Bf16)?;
            return Ok((CpuStorage::F32(y), shape));
        }
        forward(a, la, b, lb, self)
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        a: &candle_core::CudaStorage,
        la: &Layout,
        b: &candle_core::CudaStorage,
        lb: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        forward(a, la, b, lb, self)
    }

    /// What candle's backward pass of the composed version computes (in bf16: the
    /// gradient cast to bf16, multiplied with the other operand's bf16 copy, cast back to
    /// f32, or left in bf16 for a bf16 operand), on detached operands (see the module
    /// docs).
    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        ledger::backward(self.made, "matmul", || {
            let (ad, bd) = (a.detach(), b.detach());
            if self.fused_cpu {
                let g = grad.detach();
                let node = || MatmulNode {
                    made: self.made,
                    ..MatmulNode::fused_cpu()
                };
                let da = match a.track_op() {
                    true => Some(g.apply_op2_no_bwd(&bd.t()?, &node())?),
                    false => None,
                };
                let db = match b.track_op() {
                    true => Some(ad.t()?.apply_op2_no_bwd(&g, &node())?),
                    false => None,
                };
                return Ok((da, db));
            }
            let low = |t: &Tensor| match self.bf16 && t.dtype() != DType::BF16 {
                true => ledger::cast(t, DType::BF16),
                false => Ok(t.clone()),
            };
            // A gradient in its operand's type.
            let high = |t: Tensor, like: &Tensor| match self.bf16 && like.dtype() == DType::F32 {
                true => ledger::cast(&t, DType::F32),
                false => Ok(t),
            };
            let g = low(&grad.detach())?;
            let da = match a.track_op() {
                true => Some(high(ledger::mm(&g, &low(&bd)?.t()?)?, a)?),
                false => None,
            };
            let db = match b.track_op() {
                true => Some(high(ledger::mm(&low(&ad)?.t()?, &g)?, b)?),
                false => None,
            };
            Ok((da, db))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::randn;
    use candle_core::Var;

    /// The composed version: candle's product, in bf16 what `in_precision` builds from
    /// candle's ops.
    fn composed(a: &Tensor, b: &Tensor, bf16: bool) -> Result<Tensor> {
        match bf16 {
            true => a
                .to_dtype(DType::BF16)?
                .matmul(&b.to_dtype(DType::BF16)?)?
                .to_dtype(DType::F32),
            false => a.matmul(b),
        }
    }

    fn bits(t: &Tensor) -> Vec<u32> {
        let v = t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// Values and both gradients equal the composed version's bit for bit, in f32 and
    /// bf16, for plain, batched and transposed operands and for extreme inputs (tiny,
    /// huge, a mixture), and the node's gradients carry no graph (candle's own do); an
    /// operand that carries no gradient gets none.
    #[test]
    fn the_node_gives_the_composed_bits_forward_and_backward() {
        for bf16 in [false, true] {
            for (scale_a, scale_b) in [(1.0f32, 1.0f32), (1e-30, 1e-8), (1e18, 1e19), (1e-3, 3e4)] {
                for (sa, sb, transpose) in [
                    (&[7usize, 5][..], &[5usize, 3][..], false),
                    (&[2, 9, 6][..], &[2, 6, 4][..], false),
                    (&[2, 9, 6][..], &[2, 4, 6][..], true),
                ] {
                    let a = Var::from_tensor(&randn(sa, scale_a, 1)).unwrap();
                    let b = Var::from_tensor(&randn(sb, scale_b, 2)).unwrap();
                    let bt = |b: &Var| match transpose {
                        true => b.as_tensor().t().unwrap(),
                        false => b.as_tensor().clone(),
                    };
                    let g = Tensor::new(0.7f32, &candle_core::Device::Cpu).unwrap();
                    let run = |f: &dyn Fn(&Tensor, &Tensor) -> Result<Tensor>| {
                        let y = f(a.as_tensor(), &bt(&b)).unwrap();
                        let w = randn(y.dims(), 1.0, 4);
                        let loss = (y.clone() * &w).unwrap().sum_all().unwrap();
                        let grads = loss.broadcast_mul(&g).unwrap().backward().unwrap();
                        let ga = grads.get(a.as_tensor()).unwrap().clone();
                        let gb = grads.get(b.as_tensor()).unwrap().clone();
                        (y, ga, gb)
                    };
                    let (y0, ga0, gb0) = run(&|a, b| composed(a, b, bf16));
                    let (y1, ga1, gb1) = run(&|a, b| matmul_node(a, b, bf16));
                    let case = format!(
                        "bf16 {bf16}: {sa:?}×{sb:?} t{transpose} at {scale_a:e}, {scale_b:e}"
                    );
                    assert!(bf16 || ga0.track_op() || gb0.track_op(), "{case}");
                    assert!(!ga1.track_op() && !gb1.track_op(), "{case}");
                    assert_eq!(bits(&y1), bits(&y0), "values, {case}");
                    assert_eq!(bits(&ga1), bits(&ga0), "gradient of a, {case}");
                    assert_eq!(bits(&gb1), bits(&gb0), "gradient of b, {case}");
                    assert_eq!(y1.dtype(), DType::F32);
                }
            }
        }
        // A constant operand: its gradient is not computed, the other one's is.
        let a = randn(&[4, 3], 1.0, 5);
        let b = Var::from_tensor(&randn(&[3, 2], 1.0, 6)).unwrap();
        let grads = matmul_node(&a, b.as_tensor(), true)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        assert!(grads.get(&a).is_none() && grads.get(b.as_tensor()).is_some());
        assert!(matmul_node(&a, &randn(&[2, 2], 1.0, 7), true).is_err());
    }

    /// A product stored in bf16 and read by the next bf16 product gives the values and
    /// gradients of the same chain stored in f32, bit for bit, in half the bytes.
    #[test]
    fn a_product_stored_in_bf16_gives_the_f32_stored_bits() {
        for scale in [1.0f32, 1e-30, 1e18] {
            let x = Var::from_tensor(&randn(&[2, 5, 6], scale, 11)).unwrap();
            let w1 = Var::from_tensor(&randn(&[2, 6, 4], 1.0, 12)).unwrap();
            let w2 = Var::from_tensor(&randn(&[2, 4, 3], 1.0, 13)).unwrap();
            let run = |stored_low: bool| {
                let h = match stored_low {
                    true => matmul_node_low(x.as_tensor(), w1.as_tensor()).unwrap(),
                    false => matmul_node(x.as_tensor(), w1.as_tensor(), true).unwrap(),
                };
                let want = if stored_low { DType::BF16 } else { DType::F32 };
                assert_eq!(h.dtype(), want);
                let y = matmul_node(&h, w2.as_tensor(), true).unwrap();
                let w = randn(y.dims(), 1.0, 14);
                let g = (&y * &w).unwrap().sum_all().unwrap().backward().unwrap();
                let mut out = vec![bits(&y), bits(&h.to_dtype(DType::F32).unwrap())];
                for v in [&x, &w1, &w2] {
                    let gv = g.get(v.as_tensor()).unwrap();
                    assert_eq!(gv.dtype(), DType::F32);
                    out.push(bits(gv));
                }
                out
            };
            assert_eq!(run(true), run(false), "scale {scale:e}");
        }
        // Without bf16 products, a bf16 operand is refused.
        let h = randn(&[3, 4], 1.0, 15).to_dtype(DType::BF16).unwrap();
        assert!(matmul_node(&h, &randn(&[4, 2], 1.0, 16), false).is_err());
    }
}
