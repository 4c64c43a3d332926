//! The Slot Mixer's mixing block (paper eq. 5) as one graph node: per ray, weights
//! `w = softmax(scale · (x W_qᵀ)(S W_kᵀ)ᵀ)` over the slots and the mixed slot `wᵀS`.
//!
//! Why: composed it is six nodes — the query and key projections, the batched `q kᵀ`, the
//! scale, the softmax, the batched `w S` — and the query projection and the mixed slot are
//! `[8192, 128]` per step; candle's batched matmuls also zero-fill their outputs and run
//! one small product per batch element. Here it is the attention kernels of
//! `attention.rs` with one head and the slots as values, the projections inside.
//!
//! The weights are also the decoder's segmentation. They leave the op through a side
//! channel filled by the forward pass, as a tensor without a gradient (the training loss
//! does not use them).

use super::attention::{self, AttentionBwd, Dims};
use super::gemm::{self, MatRef, Threads};
use super::{Kept, cpu_storage as cpu, f32_slice, matmul_xwt, rows_layout, usable, weight_grad};
use candle_core::{CpuStorage, CustomOp3, Layout, Result, Shape, Tensor};
use std::sync::{Arc, Mutex};

/// Queries `[R, ds]`, keys `[b·k, ds]`, the weights per batch element.
struct Saved {
    q: CpuStorage,
    k: CpuStorage,
    weights: attention::Saved,
}

struct MixOp {
    dims: Dims,
    /// Query width.
    dx: usize,
    keep: bool,
    saved: Kept<Saved>,
    /// The weights `[b, r, k]`, for the caller.
    weights_out: Arc<Mutex<Option<Vec<f32>>>>,
}

impl MixOp {
    fn ds(&self) -> usize {
        self.dims.dh
    }

    /// `W_q: [ds, dx]` and `W_k: [ds, ds]` in the packed parameters.
    fn weights(&self, p_l: &Layout) -> (Layout, Layout) {
        let (ds, off) = (self.ds(), p_l.start_offset());
        (
            Layout::contiguous_with_offset((ds, self.dx), off),
            Layout::contiguous_with_offset((ds, ds), off + ds * self.dx),
        )
    }

    fn forward(
        &self,
        (x, x_l): (&CpuStorage, &Layout),
        (s, s_l): (&CpuStorage, &Layout),
        (p, p_l): (&CpuStorage, &Layout),
    ) -> Result<(Vec<f32>, Saved)> {
        let d = &self.dims;
        let (wq, wk) = self.weights(p_l);
        let q = CpuStorage::F32(matmul_xwt(x, x_l, p, &wq)?);
        let k = CpuStorage::F32(matmul_xwt(s, s_l, p, &wk)?);
        let q_l = Layout::contiguous((d.b, d.n, self.ds()));
        let (mixed, weights) = attention::forward(
            d,
            (&q, &q_l),
            (&k, 0, self.ds()),
            (s, s_l.start_offset(), self.ds()),
        )?;
        Ok((mixed, Saved { q, k, weights }))
    }
}

impl CustomOp3 for MixOp {
    fn name(&self) -> &'static str {
        "osrt-slot-mix"
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
        let d = &self.dims;
        let (x_l, s_l) = (rows_layout(l1)?, rows_layout(l2)?);
        let ds = self.ds();
        if x_l.dims() != [d.b * d.n, self.dx]
            || s_l.dims() != [d.b * d.m, ds]
            || l3.shape().elem_count() != ds * (self.dx + ds)
        {
            candle_core::bail!("slot mix: queries {:?}, slots {:?}", l1.dims(), l2.dims());
        }
        for (s, l, what) in [(s1, l1, "queries"), (s2, l2, "slots"), (s3, l3, "weights")] {
            f32_slice(s, l, what)?;
        }
        let (mixed, saved) = self.forward((s1, &x_l), (s2, &s_l), (s3, l3))?;
        let weights: Vec<f32> = saved
            .weights
            .iter()
            .map(|w| f32_slice(w, &Layout::contiguous(d.n * d.m), "weights").map(<[f32]>::to_vec))
            .collect::<Result<Vec<_>>>()?
            .concat();
        *self.weights_out.lock().unwrap_or_else(|e| e.into_inner()) = Some(weights);
        if self.keep {
            self.saved.put(saved);
        }
        Ok((CpuStorage::F32(mixed), Shape::from((d.b, d.n, ds))))
    }

    fn bwd(
        &self,
        x: &Tensor,
        slots: &Tensor,
        p: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (d, ds) = (&self.dims, self.ds());
        let grad = grad.contiguous()?;
        let (xs, x_l) = x.storage_and_layout();
        let (ss, s_l) = slots.storage_and_layout();
        let (ps, p_l) = p.storage_and_layout();
        let (gs, g_l) = grad.storage_and_layout();
        let (xs, ss, ps, gs) = (cpu(&xs)?, cpu(&ss)?, cpu(&ps)?, cpu(&gs)?);
        let (x_l, s_l) = (rows_layout(x_l)?, rows_layout(s_l)?);
        // Taken, not cloned: a second backward through the same graph recomputes it.
        let saved = match self.saved.take() {
            Some(s) => s,
            None => self.forward((xs, &x_l), (ss, &s_l), (ps, p_l))?.1,
        };
        let q_l = Layout::contiguous((d.b, d.n, ds));
        let bwd = AttentionBwd {
            dims: *d,
            saved: Kept::new(Some(saved.weights)),
        };
        let g_l = Layout::contiguous_with_offset((d.b, d.n, ds), g_l.start_offset());
        let flat = CpuStorage::F32(bwd.backward(
            (&saved.q, &q_l),
            (&saved.k, 0, ds),
            (ss, s_l.start_offset(), ds),
            (gs, &g_l),
        )?);
        let (rows, krows) = (d.b * d.n, d.b * d.m);
        let dq_l = Layout::contiguous((rows, ds));
        let dk_l = Layout::contiguous_with_offset((krows, ds), rows * ds);
        let dv_l = Layout::contiguous_with_offset((krows, ds), (rows + krows) * ds);
        let (wq, wk) = self.weights(p_l);
        let mut dp = weight_grad(&flat, &dq_l, xs, &x_l)?;
        dp.extend_from_slice(&weight_grad(&flat, &dk_l, ss, &s_l)?);
        let dev = x.device();
        let dx_ = match x.track_op() {
            true => {
                let v = gemm::matmul(
                    MatRef::of(&flat, &dq_l)?,
                    MatRef::of(ps, &wq)?,
                    Threads::Pool,
                )?;
                Some(Tensor::from_vec(v, x.shape(), dev)?)
            }
            false => None,
        };
        let ds_ = match slots.track_op() {
            true => {
                let mut v = gemm::matmul(
                    MatRef::of(&flat, &dk_l)?,
                    MatRef::of(ps, &wk)?,
                    Threads::Pool,
                )?;
                let dv = f32_slice(&flat, &dv_l, "slot mix")?;
                v.iter_mut().zip(dv).for_each(|(a, b)| *a += b);
                Some(Tensor::from_vec(v, slots.shape(), dev)?)
            }
            false => None,
        };
        Ok((dx_, ds_, Some(Tensor::from_vec(dp, p.shape(), dev)?)))
    }
}

/// The mixing block as one node: `x: [b, r, dx]` ray queries, `slots: [b, k, ds]`,
/// `w_q: [ds, dx]`, `w_k: [ds, ds]` → the mixed slots `[b, r, ds]` and the weights
/// `[b, r, k]` (softmax over the slots, without a gradient). `None` where it does not
/// apply (composed kernels, other devices or dtypes, shapes that do not fit): the caller
/// then composes the block from candle's ops (`osrt_model::decoder::slot_mixer`).
pub fn slot_mix(
    x: &Tensor,
    slots: &Tensor,
    w_q: &Tensor,
    w_k: &Tensor,
    scale: f64,
) -> Result<Option<(Tensor, Tensor)>> {
    let Some(rec) = crate::profile::current() else {
        return slot_mix_here(x, slots, w_q, w_k, scale);
    };
    let y = crate::profile::nested(|| slot_mix_here(x, slots, w_q, w_k, scale))?;
    if y.is_some() {
        let rerun = move |t: &[Tensor]| -> Result<Vec<Tensor>> {
            match slot_mix_here(&t[0], &t[1], &t[2], &t[3], scale)? {
                Some((mixed, weights)) => Ok(vec![mixed, weights]),
                None => candle_core::bail!("profile: the recorded slot mix no longer fits"),
            }
        };
        crate::profile::record(&rec, "slot_mix", &[x, slots, w_q, w_k], Arc::new(rerun));
    }
    Ok(y)
}

fn slot_mix_here(
    x: &Tensor,
    slots: &Tensor,
    w_q: &Tensor,
    w_k: &Tensor,
    scale: f64,
) -> Result<Option<(Tensor, Tensor)>> {
    let (Ok((b, r, dx)), Ok((bs, k, ds))) = (x.dims3(), slots.dims3()) else {
        return Ok(None);
    };
    let fits = bs == b
        && w_q.dims() == [ds, dx]
        && w_k.dims() == [ds, ds]
        && r > 0
        && k > 0
        && usable(&[x, slots, w_q, w_k]);
    if !fits {
        return Ok(None);
    }
    let packed = Tensor::cat(&[w_q.flatten_all()?, w_k.flatten_all()?], 0)?;
    let weights_out = Arc::new(Mutex::new(None));
    let op = MixOp {
        dims: Dims {
            b,
            n: r,
            m: k,
            h: 1,
            dh: ds,
            scale: scale as f32,
        },
        dx,
        keep: x.track_op() || slots.track_op() || packed.track_op(),
        saved: Kept::new(None),
        weights_out: weights_out.clone(),
    };
    let mixed = x
        .contiguous()?
        .apply_op3(&slots.contiguous()?, &packed, op)?;
    let Some(w) = weights_out.lock().unwrap_or_else(|e| e.into_inner()).take() else {
        candle_core::bail!("slot mix: the forward pass left no weights");
    };
    Ok(Some((mixed, Tensor::from_vec(w, (b, r, k), x.device())?)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{
        assert_matches_composed, both, finite_difference_check, max_abs, max_diff, randn,
    };
    use crate::with_fused;
    use candle_core::Var;

    /// `[x, slots, W_q, W_k]`: `b` elements, `r` rays of width `dx`, `k` slots of `ds`.
    fn args((b, r, k): (usize, usize, usize), scale: f32, seed: u64) -> Vec<Tensor> {
        let (dx, ds) = (6, 5);
        vec![
            randn(&[b, r, dx], scale, seed),
            randn(&[b, k, ds], 1.0, seed + 1),
            randn(&[ds, dx], 0.5, seed + 2),
            randn(&[ds, ds], 0.5, seed + 3),
        ]
    }

    /// The block from candle's ops (the decoder's composed path): the reference.
    fn composed(t: &[Tensor], scale: f64) -> Result<(Tensor, Tensor)> {
        let q = crate::linear(&t[0], &t[2], None)?; // [b, r, ds]
        let k = crate::linear(&t[1], &t[3], None)?; // [b, k, ds]
        let logits = (crate::matmul(&q, &k.t()?)? * scale)?; // [b, r, k]
        let weights = crate::softmax(&logits, candle_core::D::Minus1)?;
        Ok((crate::matmul(&weights, &t[1])?, weights))
    }

    /// The one node where it applies, else the composed block (as the decoder calls it).
    fn mix(t: &[Tensor]) -> Result<(Tensor, Tensor)> {
        match slot_mix(&t[0], &t[1], &t[2], &t[3], 0.4)? {
            Some(out) => Ok(out),
            None => composed(t, 0.4),
        }
    }

    fn mixed(t: &[Tensor]) -> Result<Tensor> {
        Ok(mix(t)?.0)
    }

    /// The one-node mix against the composed block (projections, batched `q kᵀ`, softmax,
    /// `w S`) and f64 finite differences, for every input; its weights are the composed
    /// weights and carry no gradient.
    #[test]
    fn slot_mix_matches_the_composed_version_and_finite_differences() {
        let a = args((3, 40, 4), 1.0, 1);
        assert_matches_composed(&a, mixed, 1e-5);
        finite_difference_check(&args((2, 3, 3), 1.0, 2), mixed);
        let [wf, wc] = [true, false].map(|on| with_fused(on, || mix(&a).unwrap().1));
        assert_eq!(wf.dims(), [3, 40, 4]);
        assert!(max_diff(&wf, &wc) <= 1e-6);
        let sums = wf.sum(candle_core::D::Minus1).unwrap();
        assert!(max_diff(&sums, &sums.ones_like().unwrap()) <= 1e-5);
        assert!(!wf.track_op(), "the fused weights carry no gradient");
    }

    /// Queries and slots that start inside a larger buffer (contiguous views with an
    /// offset) give the bits of fresh copies, forward and backward.
    #[test]
    fn inputs_with_a_storage_offset_give_the_bits_of_copies() {
        let a = args((2, 6, 3), 1.0, 5);
        let shifted = |t: &Tensor| {
            Tensor::cat(&[&t.narrow(0, 0, 1).unwrap(), t], 0)
                .unwrap()
                .narrow(0, 1, t.dim(0).unwrap())
                .unwrap()
        };
        let offset = vec![shifted(&a[0]), shifted(&a[1]), a[2].clone(), a[3].clone()];
        assert!(offset[1].storage_and_layout().1.start_offset() > 0);
        let run = |t: &[Tensor]| {
            let w = [
                Var::from_tensor(&t[2]).unwrap(),
                Var::from_tensor(&t[3]).unwrap(),
            ];
            let (y, weights) = with_fused(true, || {
                slot_mix(&t[0], &t[1], w[0].as_tensor(), w[1].as_tensor(), 0.4)
            })
            .unwrap()
            .expect("the one-node mix applies");
            let g = y.sum_all().unwrap().backward().unwrap();
            let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let dw: Vec<_> = w
                .iter()
                .map(|v| flat(g.get(v.as_tensor()).unwrap()))
                .collect();
            (flat(&y), flat(&weights), dw)
        };
        assert_eq!(run(&offset), run(&a));
    }

    /// Saturated logits (one slot takes all the weight) stay finite and agree with the
    /// composed version.
    #[test]
    fn slot_mix_is_finite_on_extreme_inputs() {
        let a = args((2, 9, 3), 1e6, 3);
        let [(y, g), (yc, _)] = both(&a, mixed);
        assert!(max_diff(&y, &yc) <= 1e-5 * (1.0 + max_abs(&yc)));
        for t in std::iter::once(&y).chain(&g) {
            assert!(max_abs(t).is_finite());
        }
    }

    /// Shapes that do not fit are left to the composed ops (which report the error), as
    /// is everything when the kernels are switched off.
    #[test]
    fn shapes_that_do_not_fit_and_composed_kernels_are_left_to_the_caller() {
        let a = args((1, 4, 2), 1.0, 4);
        let bad = [a[0].clone(), a[1].clone(), a[3].clone(), a[3].clone()];
        let left = with_fused(true, || slot_mix(&bad[0], &bad[1], &bad[2], &bad[3], 0.4));
        assert!(left.unwrap().is_none());
        assert!(with_fused(true, || mix(&bad)).is_err());
        let off = with_fused(false, || slot_mix(&a[0], &a[1], &a[2], &a[3], 0.4));
        assert!(off.unwrap().is_none());
        assert!(
            with_fused(true, || slot_mix(&a[0], &a[1], &a[2], &a[3], 0.4))
                .unwrap()
                .is_some()
        );
    }
}
