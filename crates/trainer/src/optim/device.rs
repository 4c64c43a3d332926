//! AdamW on a device (a GPU): flat f32 moments that never leave it during training (a
//! checkpoint copies them out), updated bucket by bucket so that the f64 temporaries are
//! the size of one bucket, not of the model.

use super::{Hyperparams, Maxima, StepConsts};
use candle_core::{DType, Device, Tensor, Var};

/// Elements per bucket: the f64 temporaries of one bucket take about 80 bytes each
/// (≈ 335 MB), against ≈ 6.6 GB for the 83 M parameters of the `paper` preset at once.
const BUCKET: usize = 1 << 22;

pub struct DeviceAdamW {
    /// First and second moments, flat f32 on the device in the fixed parameter order.
    pub m: Tensor,
    pub v: Tensor,
    /// Number of updates applied.
    pub t: u64,
    pub hyper: Hyperparams,
    /// After an update: per bucket, the new state's `[max |p|, max |m|, max v]`, left on
    /// the device until the next step reads them; with the parameters' version.
    known: Option<(Tensor, u64)>,
}

/// A run of whole parameters updated together: `vars[first..end]`, flat `offset..offset+len`.
struct Bucket {
    first: usize,
    end: usize,
    offset: usize,
    len: usize,
}

fn buckets(vars: &[Var]) -> Vec<Bucket> {
    let mut out: Vec<Bucket> = Vec::new();
    let mut offset = 0;
    for (i, var) in vars.iter().enumerate() {
        let n = var.elem_count();
        match out.last_mut() {
            Some(b) if b.len + n <= BUCKET => {
                b.end = i + 1;
                b.len += n;
            }
            _ => out.push(Bucket {
                first: i,
                end: i + 1,
                offset,
                len: n,
            }),
        }
        offset += n;
    }
    out
}

impl DeviceAdamW {
    pub fn new(n: usize, hyper: Hyperparams, device: &Device) -> candle_core::Result<Self> {
        Ok(Self {
            m: Tensor::zeros(n, DType::F32, device)?,
            v: Tensor::zeros(n, DType::F32, device)?,
            t: 0,
            hyper,
            known: None,
        })
    }

    /// Restores moments and step count (from a checkpoint).
    pub fn restore(&mut self, m: Vec<f32>, v: Vec<f32>, t: u64) -> candle_core::Result<()> {
        let dev = self.m.device().clone();
        self.m = Tensor::from_vec(m, self.m.dims1()?, &dev)?;
        self.v = Tensor::from_vec(v, self.v.dims1()?, &dev)?;
        (self.t, self.known) = (t, None);
        Ok(())
    }

    /// [`super::AdamW::step`] on the device: `vars` in the fixed order, `grads` one flat
    /// f32 tensor on the device. Returns `false`, changing nothing, where a weight or
    /// moment would not be finite.
    pub fn step(
        &mut self,
        vars: &[Var],
        version: u64,
        grads: &Tensor,
        g_max: f32,
        lr: f64,
    ) -> candle_core::Result<bool> {
        let n = self.m.dims1()?;
        if grads.dims1()? != n || vars.iter().map(|v| v.elem_count()).sum::<usize>() != n {
            candle_core::bail!("AdamW over {n} moments got other parameter or gradient counts");
        }
        let k = StepConsts::new(&self.hyper, self.t + 1, lr);
        let buckets = buckets(vars);
        let before = match &self.known {
            Some((maxima, v)) if *v == version => fold_maxima(maxima)?,
            _ => self.maxima(vars, &buckets)?,
        };
        if !k.provably_finite(before, g_max) && !self.all_finite(vars, &buckets, grads, &k)? {
            return Ok(false);
        }
        let mut after = Vec::with_capacity(buckets.len());
        for b in &buckets {
            let (p, m, v) = self.propose(vars, b, grads, &k)?;
            for (var, off) in vars[b.first..b.end].iter().zip(offsets(vars, b)) {
                let part = p.narrow(0, off, var.elem_count())?.reshape(var.shape())?;
                var.set(&part)?;
            }
            self.m.slice_set(&m, 0, b.offset)?;
            self.v.slice_set(&v, 0, b.offset)?;
            after.push(Tensor::stack(
                &[p.abs()?.max(0)?, m.abs()?.max(0)?, v.max(0)?],
                0,
            )?);
        }
        self.t += 1;
        self.known = Some((Tensor::stack(&after, 0)?, version));
        Ok(true)
    }

    /// The bucket's parameters as one flat f32 tensor.
    fn params(vars: &[Var], b: &Bucket) -> candle_core::Result<Tensor> {
        let parts = vars[b.first..b.end]
            .iter()
            .map(|v| v.as_tensor().flatten_all())
            .collect::<candle_core::Result<Vec<_>>>()?;
        Tensor::cat(&parts, 0)
    }

    /// One bucket's new weights and moments (flat f32): the operations of
    /// [`super::adamw_element`], in its order, element by element in f64.
    fn propose(
        &self,
        vars: &[Var],
        b: &Bucket,
        grads: &Tensor,
        k: &StepConsts,
    ) -> candle_core::Result<(Tensor, Tensor, Tensor)> {
        let f64_ = |x: &Tensor| x.to_dtype(DType::F64);
        let p = f64_(&Self::params(vars, b)?)?;
        let g = f64_(&grads.narrow(0, b.offset, b.len)?)?;
        let m0 = f64_(&self.m.narrow(0, b.offset, b.len)?)?;
        let v0 = f64_(&self.v.narrow(0, b.offset, b.len)?)?;
        let m = ((m0 * k.b1)? + (&g * (1.0 - k.b1))?)?;
        // Multiplied in the host's order, `(1 − β₂)·g·g`, for the same roundings.
        let v = ((v0 * k.b2)? + ((&g * (1.0 - k.b2))? * &g)?)?;
        // Divisions as divisions (candle's `tensor / f64` multiplies by the reciprocal).
        let scalar = |x: f64| Tensor::new(x, p.device());
        let denom = (v.broadcast_div(&scalar(k.c2)?)?.sqrt()? + k.eps)?;
        let update = ((m.broadcast_div(&scalar(k.c1)?)? / denom)? + (&p * k.weight_decay)?)?;
        let new = (p - (update * k.lr)?)?;
        Ok((
            new.to_dtype(DType::F32)?,
            m.to_dtype(DType::F32)?,
            v.to_dtype(DType::F32)?,
        ))
    }

    /// The state's maxima, read from the parameters and the moments (one synchronisation).
    fn maxima(&self, vars: &[Var], buckets: &[Bucket]) -> candle_core::Result<Maxima> {
        let mut parts = Vec::with_capacity(buckets.len());
        for b in buckets {
            let p = Self::params(vars, b)?;
            let m = self.m.narrow(0, b.offset, b.len)?;
            let v = self.v.narrow(0, b.offset, b.len)?;
            // A non-finite value anywhere makes its maximum NaN (0·x is NaN exactly for
            // non-finite x); a negative v makes the third entry NaN too.
            let poison = |x: &Tensor| (x * 0.0)?.sum(0);
            let v_neg = v.min(0)?.ge(0f32)?.to_dtype(DType::F32)?.log()?.neg()?;
            parts.push(Tensor::stack(
                &[
                    (p.abs()?.max(0)? + poison(&p)?)?,
                    (m.abs()?.max(0)? + poison(&m)?)?,
                    ((v.max(0)? + poison(&v)?)? + v_neg)?,
                ],
                0,
            )?);
        }
        fold_maxima(&Tensor::stack(&parts, 0)?)
    }

    /// Whether every element's update is finite, computed without writing anything (one
    /// synchronisation).
    fn all_finite(
        &self,
        vars: &[Var],
        buckets: &[Bucket],
        grads: &Tensor,
        k: &StepConsts,
    ) -> candle_core::Result<bool> {
        let mut total = Tensor::zeros((), DType::F32, grads.device())?;
        for b in buckets {
            let (p, m, v) = self.propose(vars, b, grads, k)?;
            // 0·x is 0 for every finite x and NaN otherwise.
            for x in [p, m, v] {
                total = (total + (x * 0.0)?.sum_all()?)?;
            }
        }
        Ok(total.to_scalar::<f32>()? == 0.0)
    }
}

/// Offsets of the bucket's parameters within the bucket.
fn offsets(vars: &[Var], b: &Bucket) -> Vec<usize> {
    let mut off = 0;
    vars[b.first..b.end]
        .iter()
        .map(|v| {
            let o = off;
            off += v.elem_count();
            o
        })
        .collect()
}

/// `[buckets, 3]` maxima on the device → one [`Maxima`] (NaN counts as +∞).
fn fold_maxima(t: &Tensor) -> candle_core::Result<Maxima> {
    let rows = t.to_vec2::<f32>()?;
    let nan_inf = |x: f32| if x.is_nan() { f32::INFINITY } else { x };
    Ok(rows.iter().fold(Maxima::default(), |a, r| {
        a.max(Maxima {
            p: nan_inf(r[0]),
            m: nan_inf(r[1]),
            v: nan_inf(r[2]),
        })
    }))
}
