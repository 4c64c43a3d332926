//! AdamW over one flat parameter buffer, with its state exposed so it can be checkpointed
//! (candle's `AdamW` keeps its moments private), and global-norm gradient clipping.

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

/// Global L2 norm of a buffer (f64 accumulation).
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

osrt_model::simd_kernel! {
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
