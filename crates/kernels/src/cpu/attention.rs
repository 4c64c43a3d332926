//! Multi-head scaled dot-product attention as one graph node with a hand-written
//! backward.
//!
//! Why: composed, the core of an attention layer is ~17 candle nodes — the head split of
//! q, k and v (reshape, transpose, copy), `k.t()`, two matmuls, the scale, the softmax
//! and the head merge — and candle's backward pays a zero tensor and an add for every
//! one of them. In the Slot Mixer's allocation transformer the queries are all of a
//! step's target rays (`[8192, 128]` on the CPU preset), so those accumulations and
//! copies are a visible share of the step (perf: `docs/performance.md`). Here the heads
//! are strided views into the projections: no split or merge copies, one node, and the
//! attention weights are kept for the backward pass instead of recomputed.
//!
//! The arithmetic is the composed version's: the same gemm on the same operands, the
//! scale applied to the logits, then the same row softmax. Tests check values and
//! gradients against it, against finite differences, and on extreme inputs.

use super::gemm::{self, BatchView};
use super::matrix::Threads;
use super::softmax::{softmax_row, softmax_row_grad};
use super::{buffer, f32_slice};
use crate::Precision;
use crate::kept::Kept;
use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp3, D, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// Sizes of one attention call.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Dims {
    /// Batch, queries, keys, heads, head width.
    pub(crate) b: usize,
    pub(crate) n: usize,
    pub(crate) m: usize,
    pub(crate) h: usize,
    pub(crate) dh: usize,
    pub(crate) scale: f32,
    /// The products' precision, forward and backward (the node's when it was made).
    pub(crate) precision: Precision,
}

impl Dims {
    pub(crate) fn inner(&self) -> usize {
        self.h * self.dh
    }

    /// Enters the products of a pass in the ledger, each `(m, n, k, transposed)` per head
    /// of every batch element.
    fn enter(&self, products: &[(usize, usize, usize, [bool; 2])]) {
        let (f, o) = (candle_core::DType::F32, gemm::operand_type(self.precision));
        for &(m, n, k, t) in products {
            let batch = self.b * self.h;
            crate::ledger::product((batch, m, n, k), (o, o, f), t, [false; 2]);
            if o != f {
                crate::ledger::cast_of(batch * k * (m + n), f, o);
            }
        }
    }

    /// Rows `len` of batch element `bi` of a `[b, len, row]` tensor (starting at `off`)
    /// as `[h, len, dh]`: head `j`'s row `i` is at `(bi·len + i)·row + j·dh` (`row` is
    /// `h·dh`, or wider where two tensors are packed side by side).
    fn heads(&self, off: usize, bi: usize, len: usize, row: usize) -> Layout {
        Layout::new(
            Shape::from((self.h, len, self.dh)),
            vec![self.dh, row, 1],
            off + bi * len * row,
        )
    }

    /// Weights-shaped `[h, rows, cols]` (contiguous), transposed when `t`.
    fn square(&self, rows: usize, cols: usize, t: bool) -> Layout {
        match t {
            false => Layout::contiguous((self.h, rows, cols)),
            true => Layout::new(
                Shape::from((self.h, cols, rows)),
                vec![rows * cols, 1, cols],
                0,
            ),
        }
    }
}

/// A `[h, rows, k] · [h, k, cols]` product: in f32 through candle's CPU matmul; on bf16
/// operands head by head through `gemm` (on this task's thread: the callers' tasks are
/// the parallel ones).
fn bmm(
    a: &CpuStorage,
    a_l: &Layout,
    b: &CpuStorage,
    b_l: &Layout,
    (h, rows, cols, k): (usize, usize, usize, usize),
    p: Precision,
) -> Result<Vec<f32>> {
    if gemm::operand_type(p) != candle_core::DType::F32 {
        let (va, vb) = (BatchView::of(a, a_l)?, BatchView::of(b, b_l)?);
        let mut out = Vec::with_capacity(h * rows * cols);
        for j in 0..h {
            let (x, y) = (va.at(j, (rows, k))?, vb.at(j, (k, cols))?);
            out.extend(gemm::matmul(x, y, Threads::One, p)?);
        }
        return Ok(out);
    }
    match a.matmul(b, (h, rows, cols, k), a_l, b_l)? {
        CpuStorage::F32(v) => Ok(v),
        _ => candle_core::bail!("attention: fused ops take f32"),
    }
}

/// `[h, len, dh]` (contiguous) into one batch element's `[len, h·dh]` rows.
fn merge_heads(out: &mut [f32], o: &[f32], d: &Dims, len: usize) {
    for (j, head) in o.chunks(len * d.dh).enumerate() {
        for (i, row) in head.chunks(d.dh).enumerate() {
            let at = i * d.inner() + j * d.dh;
            out[at..at + d.dh].copy_from_slice(row);
        }
    }
}

/// The attention weights of batch element `bi`: `softmax(scale · Q Kᵀ)`, `[h, n, m]`;
/// `k` is `(storage, offset, row stride)` of `[b, m, row]` keys.
fn weights(
    d: &Dims,
    bi: usize,
    (q, q_l): (&CpuStorage, &Layout),
    k: (&CpuStorage, usize, usize),
) -> Result<Vec<f32>> {
    weights_of_rows(d, bi, (0, d.n), (q, q_l), k)
}

/// [`weights`] for query rows `r0 .. r0 + len` of batch element `bi`: `[h, len, m]`.
fn weights_of_rows(
    d: &Dims,
    bi: usize,
    (r0, len): (usize, usize),
    (q, q_l): (&CpuStorage, &Layout),
    (k, k_off, k_row): (&CpuStorage, usize, usize),
) -> Result<Vec<f32>> {
    let q_h = Layout::new(
        Shape::from((d.h, len, d.dh)),
        vec![d.dh, d.inner(), 1],
        q_l.start_offset() + (bi * d.n + r0) * d.inner(),
    );
    let k_t = d.heads(k_off, bi, d.m, k_row).transpose(1, 2)?;
    let mut s = bmm(q, &q_h, k, &k_t, (d.h, len, d.m, d.dh), d.precision)?;
    let mut row = vec![0f32; d.m];
    for r in s.chunks_mut(d.m.max(1)) {
        r.iter_mut().for_each(|v| *v *= d.scale);
        row.copy_from_slice(r);
        softmax_row(r, &row);
    }
    Ok(s)
}

/// Per batch element, the attention weights `[h, n, m]`.
pub(crate) type Saved = Vec<CpuStorage>;

/// Forward: the output `[b, n, h·dh]` and the weights. Keys and values are
/// `(storage, offset, row stride)` of `[b, m, row]` rows, the heads' `h·dh` values at the
/// offset (`row` is wider where k and v sit side by side in one buffer).
pub(crate) fn forward(
    d: &Dims,
    q: (&CpuStorage, &Layout),
    k: (&CpuStorage, usize, usize),
    v: (&CpuStorage, usize, usize),
) -> Result<(Vec<f32>, Saved)> {
    // One task per batch element, or, with few of them (a render decodes one scene), per
    // block of query rows too, so the rows still spread over the threads. The split
    // depends on the shapes only, not on the thread count.
    let rows = if d.b >= FEW_BATCH {
        d.n
    } else {
        QUERY_ROWS_PER_TASK.min(d.n)
    };
    let blocks = d.n.div_ceil(rows.max(1));
    // Q·Kᵀ, then the weights times V.
    d.enter(&[
        (d.n, d.m, d.dh, [false, true]),
        (d.n, d.dh, d.m, [false, false]),
    ]);
    let tasks: Vec<(usize, usize, usize)> = (0..d.b)
        .flat_map(|bi| (0..blocks).map(move |j| (bi, j * rows, rows.min(d.n - j * rows))))
        .collect();
    let per: Vec<(Vec<f32>, Vec<f32>)> = tasks
        .par_iter()
        .map(|&(bi, r0, len)| {
            let p = CpuStorage::F32(weights_of_rows(d, bi, (r0, len), q, k)?);
            let v_h = d.heads(v.1, bi, d.m, v.2);
            let p_l = Layout::contiguous((d.h, len, d.m));
            let o = bmm(&p, &p_l, v.0, &v_h, (d.h, len, d.dh, d.m), d.precision)?;
            let CpuStorage::F32(p) = p else {
                candle_core::bail!("attention: fused ops take f32")
            };
            Ok((o, p))
        })
        .collect::<Result<_>>()?;
    let row = d.n * d.inner();
    if blocks == 1 {
        let out = buffer::par_filled(d.b * row, row, |bi, dst| {
            merge_heads(dst, &per[bi].0, d, d.n)
        });
        return Ok((
            out,
            per.into_iter().map(|(_, p)| CpuStorage::F32(p)).collect(),
        ));
    }
    // Row blocks back into `[b, n, h·dh]` rows and per-element `[h, n, m]` weights.
    let mut out = vec![0f32; d.b * row];
    let mut saved = vec![vec![0f32; d.h * d.n * d.m]; d.b];
    for (&(bi, r0, len), (o, p)) in tasks.iter().zip(&per) {
        let at = (bi * d.n + r0) * d.inner();
        merge_heads(&mut out[at..at + len * d.inner()], o, d, len);
        for j in 0..d.h {
            let to = (j * d.n + r0) * d.m;
            saved[bi][to..to + len * d.m].copy_from_slice(&p[j * len * d.m..(j + 1) * len * d.m]);
        }
    }
    Ok((out, saved.into_iter().map(CpuStorage::F32).collect()))
}

/// Below this many batch elements the forward pass also splits the query rows.
pub(crate) const FEW_BATCH: usize = 8;
/// Query rows per task then.
pub(crate) const QUERY_ROWS_PER_TASK: usize = 128;

struct AttentionOp {
    dims: Dims,
    /// Whether a backward pass can follow: only then are the weights kept.
    keep: bool,
    saved: Kept<Saved>,
}

impl CustomOp3 for AttentionOp {
    fn name(&self) -> &'static str {
        "osrt-attention"
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
        for (s, l, what) in [(s1, l1, "q"), (s2, l2, "k"), (s3, l3, "v")] {
            f32_slice(s, l, what)?;
        }
        let d = &self.dims;
        let inner = d.inner();
        let (y, saved) = forward(
            d,
            (s1, l1),
            (s2, l2.start_offset(), inner),
            (s3, l3.start_offset(), inner),
        )?;
        if self.keep {
            self.saved.put(saved);
        }
        Ok((CpuStorage::F32(y), Shape::from((d.b, d.n, d.inner()))))
    }

    fn bwd(
        &self,
        q: &Tensor,
        k: &Tensor,
        v: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        crate::ledger::backward("", "attention", || {
            // Taken, not cloned: a second backward through the same graph recomputes them.
            let saved = self.saved.take();
            let d = self.dims;
            let bwd = AttentionBwd {
                dims: d,
                saved: Kept::new(saved),
            };
            // Keys and values travel as one tensor: the op takes three inputs.
            let kv = Tensor::cat(&[k, v], D::Minus1)?;
            let flat = q.apply_op3_no_bwd(&kv, &grad.contiguous()?, &bwd)?;
            let (nq, nk) = (d.b * d.n * d.inner(), d.b * d.m * d.inner());
            let part = |t: &Tensor, at: usize, len: usize| -> Result<Option<Tensor>> {
                Ok(match t.track_op() {
                    true => Some(flat.narrow(0, at, len)?.reshape(t.shape())?),
                    false => None,
                })
            };
            Ok((part(q, 0, nq)?, part(k, nq, nk)?, part(v, nq + nk, nk)?))
        })
    }
}

/// The backward pass of [`AttentionOp`] as a no-grad op over `(q, [k | v], grad)`: one
/// flat buffer `[dq | dk | dv]`.
pub(crate) struct AttentionBwd {
    pub(crate) dims: Dims,
    pub(crate) saved: Kept<Saved>,
}

impl CustomOp3 for AttentionBwd {
    fn name(&self) -> &'static str {
        "osrt-attention-bwd"
    }

    fn cpu_fwd(
        &self,
        q: &CpuStorage,
        q_l: &Layout,
        kv: &CpuStorage,
        kv_l: &Layout,
        g: &CpuStorage,
        g_l: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let inner = self.dims.inner();
        for (s, l, what) in [(q, q_l, "q"), (kv, kv_l, "k|v"), (g, g_l, "gradient")] {
            f32_slice(s, l, what)?;
        }
        // `[b, m, 2·h·dh]` as k and v side by side: head views with the wider row.
        let (k_off, row) = (kv_l.start_offset(), 2 * inner);
        let out = self.backward(
            (q, q_l),
            (kv, k_off, row),
            (kv, k_off + inner, row),
            (g, g_l),
        )?;
        let len = out.len();
        Ok((CpuStorage::F32(out), Shape::from(len)))
    }
}

impl AttentionBwd {
    /// `[dq | dk | dv]` for upstream `g: [b, n, h·dh]`; keys and values as in [`forward`].
    pub(crate) fn backward(
        &self,
        (q, q_l): (&CpuStorage, &Layout),
        k: (&CpuStorage, usize, usize),
        v: (&CpuStorage, usize, usize),
        (g, g_l): (&CpuStorage, &Layout),
    ) -> Result<Vec<f32>> {
        let d = &self.dims;
        let inner = d.inner();
        let saved = self.saved.take();
        if saved.is_none() {
            d.enter(&[(d.n, d.m, d.dh, [false, true])]);
        }
        // dV = Pᵀ·dO, dP = dO·Vᵀ, dQ = dS·K, dK = dSᵀ·Q.
        d.enter(&[
            (d.m, d.dh, d.n, [true, false]),
            (d.n, d.m, d.dh, [false, true]),
            (d.n, d.dh, d.m, [false, false]),
            (d.m, d.dh, d.n, [true, false]),
        ]);
        let per: Vec<[Vec<f32>; 3]> = (0..d.b)
            .into_par_iter()
            .map(|bi| {
                let k_h = d.heads(k.1, bi, d.m, k.2);
                let v_h = d.heads(v.1, bi, d.m, v.2);
                let recomputed;
                let p = match &saved {
                    Some(s) => &s[bi],
                    None => {
                        recomputed = CpuStorage::F32(weights(d, bi, (q, q_l), k)?);
                        &recomputed
                    }
                };
                let g_h = d.heads(g_l.start_offset(), bi, d.n, inner);
                let q_h = d.heads(q_l.start_offset(), bi, d.n, inner);
                // dV = Pᵀ · dO: `[h, m, n] · [h, n, dh]`.
                let p_t = d.square(d.n, d.m, true);
                let dv = bmm(p, &p_t, g, &g_h, (d.h, d.m, d.dh, d.n), d.precision)?;
                // dP = dO · Vᵀ: `[h, n, dh] · [h, dh, m]`.
                let v_t = v_h.transpose(1, 2)?;
                let dp = bmm(g, &g_h, v.0, &v_t, (d.h, d.n, d.m, d.dh), d.precision)?;
                let p = f32_slice(p, &d.square(d.n, d.m, false), "attention weights")?;
                // dS = scale · P ⊙ (dP − Σ P ⊙ dP), row by row.
                let mut ds = vec![0f32; p.len()];
                for ((o, y), dy) in ds
                    .chunks_mut(d.m.max(1))
                    .zip(p.chunks(d.m.max(1)))
                    .zip(dp.chunks(d.m.max(1)))
                {
                    softmax_row_grad(o, y, dy);
                    o.iter_mut().for_each(|v| *v *= d.scale);
                }
                let ds = CpuStorage::F32(ds);
                // dQ = dS · K: `[h, n, m] · [h, m, dh]`; dK = dSᵀ · Q: `[h, m, n] · [h, n, dh]`.
                let dq = bmm(
                    &ds,
                    &d.square(d.n, d.m, false),
                    k.0,
                    &k_h,
                    (d.h, d.n, d.dh, d.m),
                    d.precision,
                )?;
                let dk = bmm(
                    &ds,
                    &d.square(d.n, d.m, true),
                    q,
                    &q_h,
                    (d.h, d.m, d.dh, d.n),
                    d.precision,
                )?;
                Ok([dq, dk, dv])
            })
            .collect::<Result<_>>()?;
        let (nq, nk) = (d.b * d.n * inner, d.b * d.m * inner);
        let mut out = vec![0f32; nq + 2 * nk];
        let (dq_all, rest) = out.split_at_mut(nq);
        let (dk_all, dv_all) = rest.split_at_mut(nk);
        for (bi, [dq, dk, dv]) in per.iter().enumerate() {
            let (rq, rk) = (d.n * inner, d.m * inner);
            merge_heads(&mut dq_all[bi * rq..(bi + 1) * rq], dq, d, d.n);
            merge_heads(&mut dk_all[bi * rk..(bi + 1) * rk], dk, d, d.m);
            merge_heads(&mut dv_all[bi * rk..(bi + 1) * rk], dv, d, d.m);
        }
        Ok(out)
    }
}

/// The core of attention over `q: [b, n, h·dh]`, `k, v: [b, m, h·dh]` (`dims`) as one node
/// (f32 on the CPU; shapes checked by the caller) → `[b, n, h·dh]`.
pub(crate) fn attention(q: &Tensor, k: &Tensor, v: &Tensor, dims: Dims) -> Result<Tensor> {
    let op = AttentionOp {
        dims,
        keep: q.track_op() || k.track_op() || v.track_op(),
        saved: Kept::new(None),
    };
    q.contiguous()?
        .apply_op3(&k.contiguous()?, &v.contiguous()?, op)
}
