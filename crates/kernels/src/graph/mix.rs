//! The Slot Mixer's mixing block (paper eq. 5) as one graph node: per ray, weights
//! `w = softmax(scale · (x W_qᵀ)(S W_kᵀ)ᵀ)` over the slots and the mixed slot `wᵀS`.
//!
//! Why: composed it is six nodes — the query and key projections, the batched `q kᵀ`, the
//! scale, the softmax, the batched `w S` — and the query projection and the mixed slot are
//! `[8192, 128]` per step; candle's batched matmuls also zero-fill their outputs and run
//! one small product per batch element. Here it is the attention kernels of
//! `cpu::attention` with one head and the slots as values, the projections inside.
//!
//! The weights are also the decoder's segmentation. They leave the op through a side
//! channel filled by the forward pass, as a tensor without a gradient (the training loss
//! does not use them).

use crate::cpu::attention::{self, AttentionBwd, Dims};
use crate::cpu::gemm;
use crate::cpu::linear::{matmul_xwt, weight_grad};
use crate::cpu::matrix::{MatRef, Threads};
use crate::cpu::{cpu_storage as cpu, f32_slice, rows_layout};
use crate::kept::Kept;
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
        let q = CpuStorage::F32(matmul_xwt(x, x_l, p, &wq, d.precision)?);
        let k = CpuStorage::F32(matmul_xwt(s, s_l, p, &wk, d.precision)?);
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
        crate::ledger::backward("", "slot_mix", || {
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
            let mut dp = weight_grad(&flat, &dq_l, xs, &x_l, d.precision)?;
            dp.extend_from_slice(&weight_grad(&flat, &dk_l, ss, &s_l, d.precision)?);
            let dev = x.device();
            let dx_ = match x.track_op() {
                true => {
                    let v = gemm::matmul(
                        MatRef::of(&flat, &dq_l)?,
                        MatRef::of(ps, &wq)?,
                        Threads::Pool,
                        d.precision,
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
                        d.precision,
                    )?;
                    let dv = f32_slice(&flat, &dv_l, "slot mix")?;
                    v.iter_mut().zip(dv).for_each(|(a, b)| *a += b);
                    Some(Tensor::from_vec(v, slots.shape(), dev)?)
                }
                false => None,
            };
            Ok((dx_, ds_, Some(Tensor::from_vec(dp, p.shape(), dev)?)))
        })
    }
}

/// The mixing block as one node (f32 on the CPU; see [`crate::slot_mix`]), or `None`
/// where the shapes do not fit.
pub(crate) fn slot_mix_node(
    x: &Tensor,
    slots: &Tensor,
    w_q: &Tensor,
    w_k: &Tensor,
    scale: f64,
) -> Result<Option<(Tensor, Tensor)>> {
    let (Ok((b, r, dx)), Ok((bs, k, ds))) = (x.dims3(), slots.dims3()) else {
        return Ok(None);
    };
    let fits = bs == b && w_q.dims() == [ds, dx] && w_k.dims() == [ds, ds] && r > 0 && k > 0;
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
            precision: crate::precision(),
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
