//! The fused ops' matrix products: `gemm` called directly (an `unsafe` function, so
//! this is one of the workspace's few `unsafe` modules, beside `fastmath` and the
//! trainer's `loan`).
//!
//! Why not candle's CPU matmul (which calls the same `gemm`): it zero-fills every output
//! before `gemm` overwrites it, a serial `memset` on the calling thread while the product
//! itself runs on all of them. In the decoder those outputs are `[8192, 96–230]`, twenty
//! of them a step. It also always hands `gemm` the whole pool, so a product inside one of
//! our parallel tasks cannot run on one thread. Here the output is written once, by
//! `gemm`, and the caller says how many threads a product may use.
//!
//! Soundness rests on two checks made before the call: every element of each operand's
//! view lies inside its slice ([`MatRef::new`]), and the output is a fresh buffer of
//! exactly `m·n` values, all of which `gemm` writes when it does not read the destination
//! (`read_dst = false`: `dst = lhs·rhs`, zeros when the inner dimension is 0; tested with a
//! NaN-filled destination).

#![allow(unsafe_code)]

use super::matrix::{MatRef, Threads};
use crate::Precision;
use candle_core::{CpuStorage, DType, Layout, Result};
use gemm::Parallelism;

/// The operands' type of a product in `p` on this CPU: bf16 where it has bf16 products.
pub(crate) fn operand_type(p: Precision) -> DType {
    #[cfg(target_arch = "x86_64")]
    if p == Precision::Bf16 && super::bf16::unit().is_some() {
        return DType::BF16;
    }
    let _ = p;
    DType::F32
}

/// `a · b` → `[a.rows, b.cols]`, row-major, in `p`: f32, or on bf16 operands with f32
/// sums where the CPU has bf16 products (`super::bf16`; f32 where it has none).
pub(crate) fn matmul(a: MatRef, b: MatRef, threads: Threads, p: Precision) -> Result<Vec<f32>> {
    let ((m, k), (k2, n)) = (a.dims(), b.dims());
    if k != k2 {
        candle_core::bail!("matmul: [{m}, {k}] · [{k2}, {n}]");
    }
    #[cfg(target_arch = "x86_64")]
    let unit = match p {
        Precision::Bf16 => super::bf16::unit(),
        Precision::F32 => None,
    };
    // bf16 products are x86-64's only: elsewhere they stay f32.
    #[cfg(not(target_arch = "x86_64"))]
    let unit: Option<()> = (p == Precision::Bf16).then_some(()).filter(|_| false);
    if threads == Threads::Pool {
        // A product that is one of the step's (not a block of one, run as a task).
        let (f, t) = (
            DType::F32,
            if unit.is_some() {
                DType::BF16
            } else {
                DType::F32
            },
        );
        crate::ledger::product(
            (1, m, n, k),
            (t, t, f),
            [a.raw().2.0 == 1, b.raw().2.0 == 1],
            [false; 2],
        );
        if unit.is_some() {
            // The packing rounds both operands to bf16 once per product.
            crate::ledger::cast_of(m * k + k * n, f, t);
        }
    }
    #[cfg(target_arch = "x86_64")]
    if let Some(u) = unit {
        return Ok(super::bf16::matmul(a, b, threads, u));
    }
    let len = m * n;
    let mut dst: Vec<f32> = Vec::with_capacity(len);
    // SAFETY: `dst` has room for `m·n` values, written as a row-major `[m, n]`
    // (strides `n`, 1); `a` and `b` are views checked by `MatRef::new` to lie inside their
    // slices, which outlive the call and do not overlap `dst` (a fresh allocation). With
    // `read_dst = false` gemm writes every destination element (`lhs·rhs`, or zeros when
    // `k = 0`), so all `m·n` values are initialised before `set_len`.
    unsafe {
        gemm_into(dst.as_mut_ptr(), a, b, threads);
        dst.set_len(len);
    }
    Ok(dst)
}

/// `a · b` for `a: [.., m, k]`, `b: [.., k, n]` (the same leading dims, `bmnk` =
/// `(batch, m, n, k)`) as they lie in their storage (each operand's last two dims with
/// any strides, its leading dims one after the other) → `[.., m, n]` row-major, each
/// batch element's product in `p` on the pool.
pub(crate) fn batched(
    (a, la): (&CpuStorage, &Layout),
    (b, lb): (&CpuStorage, &Layout),
    (batch, m, n, k): (usize, usize, usize, usize),
    p: Precision,
) -> Result<Vec<f32>> {
    let (va, vb) = (BatchView::of(a, la)?, BatchView::of(b, lb)?);
    let mut out = Vec::with_capacity(batch * m * n);
    for bi in 0..batch {
        let (x, y) = (va.at(bi, (m, k))?, vb.at(bi, (k, n))?);
        out.extend(matmul(x, y, Threads::Pool, p)?);
    }
    Ok(out)
}

/// Batch elements of a `[.., rows, cols]` f32 storage: their leading dims one after the
/// other, walked by one stride.
pub(crate) struct BatchView<'a> {
    data: &'a [f32],
    off: usize,
    lead: usize,
    strides: (usize, usize),
}

impl<'a> BatchView<'a> {
    pub(crate) fn of(s: &'a CpuStorage, l: &Layout) -> Result<Self> {
        let CpuStorage::F32(v) = s else {
            candle_core::bail!("matmul: fused ops take f32");
        };
        let (d, st) = (l.dims(), l.stride());
        let r = d.len();
        if r < 2 {
            candle_core::bail!("matmul: an operand of shape {d:?}");
        }
        for i in 0..r.saturating_sub(3) {
            if d[i] > 1 && st[i] != st[i + 1] * d[i + 1] {
                candle_core::bail!("matmul: leading dims {d:?} with strides {st:?}");
            }
        }
        Ok(Self {
            data: v,
            off: l.start_offset(),
            lead: if r > 2 { st[r - 3] } else { 0 },
            strides: (st[r - 2], st[r - 1]),
        })
    }

    /// Element `bi` as a `[rows, cols]` view.
    pub(crate) fn at(&self, bi: usize, dims: (usize, usize)) -> Result<MatRef<'a>> {
        MatRef::new(self.data, self.off + bi * self.lead, dims, self.strides)
    }
}

/// `dst[..m·n] = a · b` (row-major `[m, n]`) over an existing buffer (tests: that every
/// element is written).
#[cfg(test)]
pub(crate) fn matmul_over(dst: &mut [f32], a: MatRef, b: MatRef) -> Result<()> {
    let ((m, k), (k2, n)) = (a.dims(), b.dims());
    if k != k2 || dst.len() != m * n {
        candle_core::bail!("matmul: [{m}, {k}] · [{k2}, {n}] into {} values", dst.len());
    }
    // SAFETY: as in `matmul`, with `dst` an exclusive borrow of exactly `m·n` values.
    unsafe { gemm_into(dst.as_mut_ptr(), a, b, Threads::Pool) };
    Ok(())
}

/// # Safety
/// `dst` must be valid for writes of `a.rows · b.cols` f32 values and not overlap `a` or
/// `b`; `a.cols == b.rows`.
unsafe fn gemm_into(dst: *mut f32, a: MatRef, b: MatRef, threads: Threads) {
    let ((m, k), (_, n)) = (a.dims(), b.dims());
    if m == 0 || n == 0 {
        return;
    }
    let parallelism = match (threads, rayon::current_num_threads()) {
        (Threads::Pool, t) if t > 1 => Parallelism::Rayon(t),
        _ => Parallelism::None,
    };
    // An empty view (k = 0) may sit at the end of its slice: gemm reads nothing then.
    let ((da, oa, (ars, acs)), (db, ob, (brs, bcs))) = (a.raw(), b.raw());
    // SAFETY: the caller's contract for `dst`; the operand views are in bounds
    // (`MatRef::new`) and only read.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst,
            1,
            n as isize,
            false,
            da.as_ptr().wrapping_add(oa),
            acs as isize,
            ars as isize,
            db.as_ptr().wrapping_add(ob),
            bcs as isize,
            brs as isize,
            0.0,
            1.0,
            false,
            false,
            false,
            parallelism,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Tensor};

    fn values(n: usize, seed: usize) -> Vec<f32> {
        (0..n)
            .map(|i| (((i + seed) * 7919 % 1009) as f32 / 1009.0) - 0.5)
            .collect()
    }

    /// Products of plain, transposed and row-sliced views equal candle's matmul of the same
    /// tensors, bit for bit (same gemm, same operand strides), for shapes that take gemm's
    /// general, small-matrix and vector paths.
    #[test]
    fn products_match_candle_matmul() {
        for (m, k, n) in [
            (37, 19, 23),
            (1, 64, 9),
            (5, 1, 7),
            (16, 16, 16),
            (130, 70, 3),
        ] {
            let a = values(m * k + 3, 1);
            let b = values(k * n, 2);
            let ta = Tensor::from_slice(&a[3..], (m, k), &Device::Cpu).unwrap();
            let tb = Tensor::from_slice(&b, (n, k), &Device::Cpu).unwrap();
            let want: Vec<f32> = ta
                .matmul(&tb.t().unwrap())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let va = MatRef::new(&a, 3, (m, k), (k, 1)).unwrap();
            let vb = MatRef::new(&b, 0, (n, k), (k, 1)).unwrap().t();
            for threads in [Threads::Pool, Threads::One] {
                assert_eq!(
                    matmul(va, vb, threads, Precision::F32).unwrap(),
                    want,
                    "{m}×{k}×{n}"
                );
            }
            // Rows 1.. of the same product through a row slice.
            if m > 1 {
                let got =
                    matmul(va.rows(1, m - 1).unwrap(), vb, Threads::One, Precision::F32).unwrap();
                assert_eq!(got, want[n..], "rows 1.. of {m}×{k}×{n}");
            }
        }
    }

    /// Every output element is written: a NaN-filled destination comes back finite, and
    /// all zeros for an empty inner dimension.
    #[test]
    fn every_output_element_is_written() {
        for (m, k, n) in [(9, 4, 11), (1, 3, 1), (64, 32, 48), (4, 0, 5)] {
            let (a, b) = (values(m * k, 3), values(k * n, 4));
            let va = MatRef::new(&a, 0, (m, k), (k, 1)).unwrap();
            let vb = MatRef::new(&b, 0, (k, n), (n, 1)).unwrap();
            let mut dst = vec![f32::NAN; m * n];
            matmul_over(&mut dst, va, vb).unwrap();
            assert!(dst.iter().all(|v| v.is_finite()), "{m}×{k}×{n}");
            if k == 0 {
                assert!(dst.iter().all(|&v| v == 0.0));
            }
            assert_eq!(matmul(va, vb, Threads::Pool, Precision::F32).unwrap(), dst);
        }
    }

    /// Views that would reach outside their slice are refused, not read.
    #[test]
    fn views_outside_their_slice_are_refused() {
        let v = vec![0f32; 12];
        assert!(MatRef::new(&v, 0, (3, 4), (4, 1)).is_ok());
        assert!(MatRef::new(&v, 1, (3, 4), (4, 1)).is_err());
        assert!(MatRef::new(&v, 0, (4, 3), (4, 1)).is_err());
        assert!(MatRef::new(&v, 0, (2, 2), (usize::MAX, 1)).is_err());
        assert!(
            MatRef::new(&v, 0, (3, 4), (4, 1))
                .unwrap()
                .rows(2, 2)
                .is_err()
        );
        // Empty views are fine anywhere.
        assert!(MatRef::new(&v, 12, (0, 4), (4, 1)).is_ok());
        let a = MatRef::new(&v, 0, (3, 4), (4, 1)).unwrap();
        assert!(
            matmul(a, a, Threads::One, Precision::F32).is_err(),
            "inner dims differ"
        );
    }
}
