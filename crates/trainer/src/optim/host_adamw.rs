//! AdamW on the host: flat f32 moments, each parameter updated in its own storage.

use super::{Hyperparams, Maxima, MaximaBits, StepConsts, adamw_element};
use candle_core::{CpuStorage, Layout, Storage, Var};
use rayon::prelude::*;
use std::sync::Mutex;

/// Elements per parallel task of an update.
const TASK: usize = 1 << 15;

/// Optimiser state: first and second moments per parameter, flat in the fixed parameter
/// order, and the step count.
#[derive(Debug, Clone, PartialEq)]
pub struct AdamW {
    pub m: Vec<f32>,
    pub v: Vec<f32>,
    /// Number of updates applied (bias correction uses `t`).
    pub t: u64,
    pub hyper: Hyperparams,
    /// The state's maxima after the last update, and the parameters' version they hold
    /// for (`Params::version`); `None` until an update has run here.
    known: Option<(Maxima, u64)>,
}

impl AdamW {
    pub fn new(n: usize, hyper: Hyperparams) -> Self {
        Self {
            m: vec![0.0; n],
            v: vec![0.0; n],
            t: 0,
            hyper,
            known: None,
        }
    }

    /// Restores moments and step count (from a checkpoint).
    pub fn restore(&mut self, m: Vec<f32>, v: Vec<f32>, t: u64) {
        (self.m, self.v, self.t, self.known) = (m, v, t, None);
    }

    /// Applies one update with learning rate `lr` to `vars` (f32 CPU parameters in the
    /// fixed order, together as long as the moments; `version` identifies their
    /// contents, see `Params::version`) from the flat gradient `grads`, whose largest
    /// magnitude is `g_max`. Returns `false`, changing nothing, where a weight or moment
    /// would not be finite.
    pub fn step(
        &mut self,
        vars: &[Var],
        version: u64,
        grads: &[f32],
        g_max: f32,
        lr: f64,
    ) -> candle_core::Result<bool> {
        self.step_scaled(vars, version, grads, 1.0, g_max, lr)
    }

    /// [`AdamW::step`] on the gradient `grads · scale` (each element multiplied in f32,
    /// as clipping the whole gradient first would, so the bits are the same), without
    /// writing the scaled gradient anywhere; `g_max` is the scaled gradient's largest
    /// magnitude.
    pub fn step_scaled(
        &mut self,
        vars: &[Var],
        version: u64,
        grads: &[f32],
        scale: f32,
        g_max: f32,
        lr: f64,
    ) -> candle_core::Result<bool> {
        let n: usize = vars.iter().map(|v| v.elem_count()).sum();
        if grads.len() != n || self.m.len() != n {
            candle_core::bail!(
                "AdamW over {} moments got {n} parameters and {} gradients",
                self.m.len(),
                grads.len()
            );
        }
        let k = StepConsts::new(&self.hyper, self.t + 1, lr);
        let before = match self.known {
            Some((maxima, v)) if v == version => maxima,
            _ => self.maxima(vars)?,
        };
        if !k.provably_finite(before, g_max) && !self.all_finite(vars, grads, scale, &k)? {
            return Ok(false);
        }
        let mut after = Maxima::default();
        let mut off = 0;
        for var in vars {
            let len = var.elem_count();
            let r = off..off + len;
            let op = Update {
                grads: &grads[r.clone()],
                scale,
                m: Mutex::new(&mut self.m[r.clone()]),
                v: Mutex::new(&mut self.v[r]),
                k,
                after: Mutex::new(Maxima::default()),
            };
            var.as_tensor().inplace_op1(&op)?;
            after = after.max(op.after.into_inner().expect("not poisoned"));
            off += len;
        }
        self.t += 1;
        self.known = Some((after, version));
        Ok(true)
    }

    /// The state's maxima, read from the parameters and the moments.
    fn maxima(&self, vars: &[Var]) -> candle_core::Result<Maxima> {
        let mut out = Maxima::default();
        let mut off = 0;
        for var in vars {
            let len = var.elem_count();
            let (m, v) = (&self.m[off..off + len], &self.v[off..off + len]);
            let part = with_slice(var, |p| {
                p.par_chunks(TASK)
                    .zip(m.par_chunks(TASK))
                    .zip(v.par_chunks(TASK))
                    .map(|((p, m), v)| {
                        p.iter()
                            .zip(m)
                            .zip(v)
                            .fold(Maxima::default(), |a, ((&p, &m), &v)| {
                                a.max(Maxima::of(p, m, v))
                            })
                    })
                    .reduce(Maxima::default, Maxima::max)
            })?;
            out = out.max(part);
            off += len;
        }
        Ok(out)
    }

    /// Whether every element's update is finite, computed without writing anything.
    fn all_finite(
        &self,
        vars: &[Var],
        grads: &[f32],
        scale: f32,
        k: &StepConsts,
    ) -> candle_core::Result<bool> {
        let mut off = 0;
        for var in vars {
            let len = var.elem_count();
            let r = off..off + len;
            let (g, m, v) = (&grads[r.clone()], &self.m[r.clone()], &self.v[r]);
            let finite = with_slice(var, |p| {
                p.par_chunks(TASK)
                    .zip(g.par_chunks(TASK))
                    .zip(m.par_chunks(TASK))
                    .zip(v.par_chunks(TASK))
                    .all(|(((p, g), m), v)| {
                        (0..p.len()).all(|i| {
                            let (p, m, v) = adamw_element(p[i], g[i] * scale, m[i], v[i], k);
                            p.is_finite() && m.is_finite() && v.is_finite()
                        })
                    })
            })?;
            if !finite {
                return Ok(false);
            }
            off += len;
        }
        Ok(true)
    }
}

/// `f` of a contiguous f32 CPU parameter's values.
fn with_slice<T>(var: &Var, f: impl FnOnce(&[f32]) -> T) -> candle_core::Result<T> {
    let (storage, layout) = var.as_tensor().storage_and_layout();
    match (&*storage, layout.contiguous_offsets()) {
        (Storage::Cpu(CpuStorage::F32(data)), Some((a, b))) => Ok(f(&data[a..b])),
        _ => candle_core::bail!("AdamW on the host needs contiguous f32 CPU parameters"),
    }
}

/// One parameter's update, in its storage: the moments' slices and the gradient's go
/// with it; the maxima of the new state come back.
struct Update<'a> {
    grads: &'a [f32],
    /// The clipping factor, applied to each gradient element.
    scale: f32,
    m: Mutex<&'a mut [f32]>,
    v: Mutex<&'a mut [f32]>,
    k: StepConsts,
    after: Mutex<Maxima>,
}

impl candle_core::InplaceOp1 for Update<'_> {
    fn name(&self) -> &'static str {
        "adamw-update"
    }

    fn cpu_fwd(&self, storage: &mut CpuStorage, layout: &Layout) -> candle_core::Result<()> {
        let (CpuStorage::F32(data), Some((a, b))) = (storage, layout.contiguous_offsets()) else {
            candle_core::bail!("AdamW on the host needs contiguous f32 CPU parameters");
        };
        let p = &mut data[a..b];
        let mut m = self.m.lock().expect("not poisoned");
        let mut v = self.v.lock().expect("not poisoned");
        let k = &self.k;
        let after = p
            .par_chunks_mut(TASK)
            .zip(m.par_chunks_mut(TASK))
            .zip(v.par_chunks_mut(TASK))
            .zip(self.grads.par_chunks(TASK))
            .map(|(((p, m), v), g)| {
                let mut out = Maxima::default();
                update_block(p, m, v, g, self.scale, k, &mut out);
                out
            })
            .reduce(Maxima::default, Maxima::max);
        *self.after.lock().expect("not poisoned") = after;
        Ok(())
    }
}

osrt_kernels::simd_kernel! {
    /// [`adamw_element`] over one block, in place, with the new state's maxima. One loop
    /// over equal-length slices, the maxima taken as integer maxima of the values' bits
    /// ([`MaximaBits`]): with no branch and no float reduction in it, the loop vectorises
    /// (f64 division and square root four or eight lanes at a time).
    pub fn update_block(
        p: &mut [f32],
        m: &mut [f32],
        v: &mut [f32],
        g: &[f32],
        scale: f32,
        k: &StepConsts,
        out: &mut Maxima,
    ) {
        let n = p.len();
        let (m, v, g) = (&mut m[..n], &mut v[..n], &g[..n]);
        let mut acc = MaximaBits::default();
        for i in 0..n {
            let (pi, mi, vi) = adamw_element(p[i], g[i] * scale, m[i], v[i], k);
            p[i] = pi;
            m[i] = mi;
            v[i] = vi;
            acc = acc.max(MaximaBits::of(pi, mi, vi));
        }
        *out = acc.decode();
    }
}
