//! AdamW over one flat parameter buffer, with its state exposed so it can be checkpointed
//! (candle's `AdamW` keeps its moments private), and global-norm gradient clipping.

use candle_core::{DType, Device, Tensor};
use serde::{Deserialize, Serialize};

/// Optimiser state: first and second moments per parameter and the step count.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AdamW {
    pub m: Vec<f32>,
    pub v: Vec<f32>,
    /// Number of updates applied (bias correction uses `t`).
    pub t: u64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    pub weight_decay: f64,
}

impl AdamW {
    pub fn new(n: usize, beta1: f64, beta2: f64, eps: f64, weight_decay: f64) -> Self {
        Self {
            m: vec![0.0; n],
            v: vec![0.0; n],
            t: 0,
            beta1,
            beta2,
            eps,
            weight_decay,
        }
    }

    /// The updated parameters, without touching `self` — callers commit with
    /// [`AdamW::commit`] only if the result is finite.
    pub fn propose(
        &self,
        params: &[f32],
        grads: &[f32],
        lr: f64,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        assert_eq!(params.len(), grads.len());
        assert_eq!(params.len(), self.m.len());
        let t = (self.t + 1) as i32;
        let h = Hyper {
            b1: self.beta1,
            b2: self.beta2,
            c1: 1.0 - self.beta1.powi(t),
            c2: 1.0 - self.beta2.powi(t),
            eps: self.eps,
            weight_decay: self.weight_decay,
            lr,
        };
        let n = params.len();
        let (mut p, mut m, mut v) = (vec![0f32; n], vec![0f32; n], vec![0f32; n]);
        adamw_update(&mut p, &mut m, &mut v, params, grads, &self.m, &self.v, &h);
        (p, m, v)
    }

    pub fn commit(&mut self, m: Vec<f32>, v: Vec<f32>) {
        self.m = m;
        self.v = v;
        self.t += 1;
    }
}

/// AdamW with its moments on a device (a GPU): the same update as [`AdamW`], in f64 on
/// the device, over one flat buffer of every parameter in the fixed order, so that the
/// moments never leave the device during training (a checkpoint copies them out).
pub struct DeviceAdamW {
    /// First and second moments, flat f32 on the device.
    pub m: Tensor,
    pub v: Tensor,
    /// The hyperparameters and the step count (its moments are empty).
    pub hyper: AdamW,
}

/// An update proposed on the device: the new weights and moments (flat f32), and whether
/// all of them are finite.
pub struct DeviceProposal {
    pub params: Tensor,
    pub m: Tensor,
    pub v: Tensor,
    pub finite: bool,
}

impl DeviceAdamW {
    pub fn new(n: usize, hyper: AdamW, device: &Device) -> candle_core::Result<Self> {
        Ok(Self {
            m: Tensor::zeros(n, DType::F32, device)?,
            v: Tensor::zeros(n, DType::F32, device)?,
            hyper: AdamW {
                m: Vec::new(),
                v: Vec::new(),
                ..hyper
            },
        })
    }

    /// The update of [`AdamW::propose`] on flat device tensors `params` and `grads`.
    /// The arithmetic is the host loop's, element by element in f64, operation for
    /// operation (tested against it).
    pub fn propose(
        &self,
        params: &Tensor,
        grads: &Tensor,
        lr: f64,
    ) -> candle_core::Result<DeviceProposal> {
        let h = &self.hyper;
        let t = (h.t + 1) as i32;
        let (c1, c2) = (1.0 - h.beta1.powi(t), 1.0 - h.beta2.powi(t));
        let f64_ = |x: &Tensor| x.to_dtype(DType::F64);
        let (p, g, m0, v0) = (f64_(params)?, f64_(grads)?, f64_(&self.m)?, f64_(&self.v)?);
        let m = ((m0 * h.beta1)? + (&g * (1.0 - h.beta1))?)?;
        // Multiplied in the host loop's order, `(1 − β₂)·g·g`, for the same roundings.
        let v = ((v0 * h.beta2)? + ((&g * (1.0 - h.beta2))? * &g)?)?;
        // Divisions as divisions (candle's `tensor / f64` multiplies by the reciprocal).
        let scalar = |x: f64| Tensor::new(x, p.device());
        let denom = (v.broadcast_div(&scalar(c2)?)?.sqrt()? + h.eps)?;
        let update = ((m.broadcast_div(&scalar(c1)?)? / denom)? + (&p * h.weight_decay)?)?;
        let new = (p - (update * lr)?)?;
        let (new, m, v) = (
            new.to_dtype(DType::F32)?,
            m.to_dtype(DType::F32)?,
            v.to_dtype(DType::F32)?,
        );
        // 0·x is 0 for every finite x and NaN otherwise: one reduction (and one
        // synchronisation) tells whether anything overflowed.
        let probe = |x: &Tensor| -> candle_core::Result<Tensor> { (x * 0.0)?.sum_all() };
        let total = ((probe(&new)? + probe(&m)?)? + probe(&v)?)?;
        let finite = total.to_scalar::<f32>()? == 0.0;
        Ok(DeviceProposal {
            params: new,
            m,
            v,
            finite,
        })
    }

    pub fn commit(&mut self, m: Tensor, v: Tensor) {
        self.m = m;
        self.v = v;
        self.hyper.t += 1;
    }
}

/// One step's constants: β's, bias corrections `1 − βᵗ`, ε, decay and learning rate.
pub struct Hyper {
    b1: f64,
    b2: f64,
    c1: f64,
    c2: f64,
    eps: f64,
    weight_decay: f64,
    lr: f64,
}

osrt_kernels::simd_kernel! {
    /// The AdamW update of every element, in f64 (moments and weights are stored in f32);
    /// written as one loop over equal-length slices so that it vectorises.
    #[allow(clippy::too_many_arguments)]
    pub fn adamw_update(
        p: &mut [f32],
        m: &mut [f32],
        v: &mut [f32],
        params: &[f32],
        grads: &[f32],
        m0: &[f32],
        v0: &[f32],
        h: &Hyper,
    ) {
        let n = p.len();
        let (m, v, params, grads, m0, v0) =
            (&mut m[..n], &mut v[..n], &params[..n], &grads[..n], &m0[..n], &v0[..n]);
        for i in 0..n {
            let g = grads[i] as f64;
            let mi = h.b1 * m0[i] as f64 + (1.0 - h.b1) * g;
            let vi = h.b2 * v0[i] as f64 + (1.0 - h.b2) * g * g;
            let update =
                (mi / h.c1) / ((vi / h.c2).sqrt() + h.eps) + h.weight_decay * params[i] as f64;
            m[i] = mi as f32;
            v[i] = vi as f32;
            p[i] = (params[i] as f64 - h.lr * update) as f32;
        }
    }
}

/// Global L2 norm of a buffer (f64 accumulation).
pub fn global_norm(g: &[f32]) -> f64 {
    g.iter()
        .map(|&x| (x as f64) * (x as f64))
        .sum::<f64>()
        .sqrt()
}

/// Scales `g` in place so its global norm is at most `max_norm`; returns the norm before.
pub fn clip_global_norm(g: &mut [f32], max_norm: f64) -> f64 {
    let norm = global_norm(g);
    if norm > max_norm && norm > 0.0 {
        let s = (max_norm / norm) as f32;
        g.iter_mut().for_each(|x| *x *= s);
    }
    norm
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_adam_step_moves_each_weight_by_lr() {
        // With bias correction, step 1 is lr · sign(g) (up to ε).
        let opt = AdamW::new(3, 0.9, 0.999, 1e-12, 0.0);
        let (p, _, _) = opt.propose(&[1.0, 1.0, 1.0], &[0.5, -2.0, 1e-3], 0.1);
        for (x, want) in p.iter().zip([0.9, 1.1, 0.9]) {
            assert!((x - want).abs() < 1e-5, "{p:?}");
        }
    }

    #[test]
    fn weight_decay_is_decoupled() {
        let opt = AdamW::new(1, 0.9, 0.999, 1e-8, 0.5);
        let (p, _, _) = opt.propose(&[2.0], &[0.0], 0.1);
        // Zero gradient: only decay, 2 − 0.1·0.5·2 = 1.9.
        assert!((p[0] - 1.9).abs() < 1e-6);
    }

    /// The device optimiser (run here on CPU tensors) gives the host loop's bits, step
    /// after step, weight decay and bias correction included.
    #[test]
    fn the_device_update_gives_the_host_update_bits() {
        let n = 1000;
        let mut rng = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        };
        let mut host = AdamW::new(n, 0.9, 0.999, 1e-8, 0.01);
        let dev = Device::Cpu;
        let mut device = DeviceAdamW::new(n, host.clone(), &dev).unwrap();
        let mut params: Vec<f32> = (0..n).map(|_| next()).collect();
        let mut p_dev = Tensor::from_slice(&params, n, &dev).unwrap();
        for step in 0..5 {
            let grads: Vec<f32> = (0..n).map(|_| next() * 10f32.powi(step - 2)).collect();
            let lr = 1e-3 * (step + 1) as f64;
            let (p, m, v) = host.propose(&params, &grads, lr);
            host.commit(m, v);
            params = p;
            let g = Tensor::from_slice(&grads, n, &dev).unwrap();
            let prop = device.propose(&p_dev, &g, lr).unwrap();
            assert!(prop.finite);
            device.commit(prop.m, prop.v);
            p_dev = prop.params;
            assert_eq!(p_dev.to_vec1::<f32>().unwrap(), params, "step {step}");
            assert_eq!(device.m.to_vec1::<f32>().unwrap(), host.m, "step {step}");
            assert_eq!(device.v.to_vec1::<f32>().unwrap(), host.v, "step {step}");
        }
        assert_eq!(device.hyper.t, host.t);
    }

    /// An overflowing gradient (its square is past f32's range) or a NaN is reported, so
    /// the step is skipped before anything reaches the weights or the moments.
    #[test]
    fn the_device_update_reports_non_finite_results() {
        let dev = Device::Cpu;
        let opt = DeviceAdamW::new(3, AdamW::new(0, 0.9, 0.999, 1e-8, 0.0), &dev).unwrap();
        let p = Tensor::new(&[1f32, 2.0, 3.0], &dev).unwrap();
        for bad in [f32::NAN, f32::INFINITY, 3e38] {
            let g = Tensor::new(&[0.1f32, bad, 0.2], &dev).unwrap();
            assert!(!opt.propose(&p, &g, 1e-3).unwrap().finite, "{bad}");
        }
        let g = Tensor::new(&[0.1f32, -1e19, 0.2], &dev).unwrap();
        assert!(opt.propose(&p, &g, 1e-3).unwrap().finite);
    }

    #[test]
    fn clipping_bounds_the_norm() {
        let mut g = vec![3.0, 4.0];
        assert_eq!(clip_global_norm(&mut g, 1.0), 5.0);
        assert!((global_norm(&g) - 1.0).abs() < 1e-6);
        let mut small = vec![0.3, 0.4];
        clip_global_norm(&mut small, 1.0);
        assert_eq!(small, vec![0.3, 0.4]);
    }
}
