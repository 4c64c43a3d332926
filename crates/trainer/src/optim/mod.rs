//! AdamW over the model's parameters, updated in place, with its state exposed so it can
//! be checkpointed (candle's `AdamW` keeps its moments private), and global-norm
//! gradient clipping.
//!
//! One arithmetic serves both sides: [`adamw_element`] in f64 on the host
//! ([`AdamW`], over the flat moments and each parameter's own storage), and the same
//! operations in the same order as candle ops on a device ([`DeviceAdamW`]); the two give
//! the same bits (tested).
//!
//! **Nothing non-finite is written.** An update is applied in place only once it is known
//! to be finite everywhere. Usually that is proven without a pass over the data: from
//! the largest `|g|` (taken with the gradient's norm) and the largest `|p|`, `|m|` and
//! `v` of the state (taken by the previous update), [`StepConsts::provably_finite`]
//! bounds every result below `f32::MAX`. Where the bound cannot be shown (a huge gradient,
//! a state restored with non-finite values), every element's result is computed and
//! checked first, and the step is applied or skipped on that.

mod device_adamw;
mod host_adamw;

pub use device_adamw::DeviceAdamW;
pub use host_adamw::AdamW;

/// AdamW's hyperparameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hyperparams {
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    pub weight_decay: f64,
}

/// One update's constants: β's, bias corrections `1 − βᵗ`, ε, decay and learning rate.
#[derive(Debug, Clone, Copy)]
pub struct StepConsts {
    pub b1: f64,
    pub b2: f64,
    pub c1: f64,
    pub c2: f64,
    /// `1 / c₁` and `1 / √c₂`: the bias corrections as products, so that an element's
    /// update costs one division and one square root.
    pub inv_c1: f64,
    pub inv_sqrt_c2: f64,
    pub eps: f64,
    pub weight_decay: f64,
    pub lr: f64,
}

impl StepConsts {
    /// The constants of update number `t` (1 for the first).
    pub fn new(h: &Hyperparams, t: u64, lr: f64) -> Self {
        let t = t.min(i32::MAX as u64) as i32;
        let (c1, c2) = (1.0 - h.beta1.powi(t), 1.0 - h.beta2.powi(t));
        Self {
            b1: h.beta1,
            b2: h.beta2,
            c1,
            c2,
            inv_c1: 1.0 / c1,
            inv_sqrt_c2: 1.0 / c2.sqrt(),
            eps: h.eps,
            weight_decay: h.weight_decay,
            lr,
        }
    }

    /// Whether every element's update is finite, shown from bounds alone: with `|m₀| ≤
    /// M`, `0 ≤ v₀ ≤ V`, `|p| ≤ P` (`before`) and `|g| ≤ G`, the new moments are at most
    /// `|β₁|M + |1−β₁|G` and `|β₂|V + |1−β₂|G²`, and since `√v̂ + ε ≥ ε` the new weight is
    /// at most `P + lr·(M'/(c₁ε) + |λ|P)`. Each bound carries a relative slack far above
    /// f64's rounding, and must stay below `f32::MAX`, so no cast to f32 overflows.
    /// `false` only means "not shown": the caller then checks element by element.
    pub fn provably_finite(&self, before: Maxima, g_max: f32) -> bool {
        const SLACK: f64 = 1.0 + 1e-9;
        if !(self.eps > 0.0
            && self.c1 > 0.0
            && self.c2 > 0.0
            && self.inv_c1.is_finite()
            && self.lr >= 0.0)
        {
            return false;
        }
        let (p, m, v, g) = (
            before.p as f64,
            before.m as f64,
            before.v as f64,
            g_max as f64,
        );
        let m_new = (self.b1.abs() * m.max(0.0) + (1.0 - self.b1).abs() * g) * SLACK;
        let v_new = (self.b2.abs() * v + (1.0 - self.b2).abs() * g * g) * SLACK;
        let step = m_new * self.inv_c1 / self.eps + self.weight_decay.abs() * p;
        let p_new = (p + self.lr * step) * SLACK;
        // Written so that a NaN anywhere fails the test.
        [m_new, v_new, p_new].iter().all(|&x| x <= f32::MAX as f64)
            && self.b2 >= 0.0
            && self.b2 <= 1.0
    }
}

/// AdamW for one element, in f64 (moments and weights are stored in f32): the new weight,
/// first and second moment. [`DeviceAdamW`] does these operations in this order.
#[inline(always)]
pub fn adamw_element(p: f32, g: f32, m0: f32, v0: f32, k: &StepConsts) -> (f32, f32, f32) {
    let g = g as f64;
    let m = k.b1 * m0 as f64 + (1.0 - k.b1) * g;
    let v = k.b2 * v0 as f64 + (1.0 - k.b2) * g * g;
    // √v̂ = √v / √c₂ and m̂ = m / c₁, each as a product (PyTorch's AdamW divides √v by
    // √c₂ the same way): the element's one division is m̂ by the denominator.
    let denom = v.sqrt() * k.inv_sqrt_c2 + k.eps;
    let update = (m * k.inv_c1) / denom + k.weight_decay * p as f64;
    ((p as f64 - k.lr * update) as f32, m as f32, v as f32)
}

/// Largest `|p|`, `|m|` and `v` of a state, where a NaN (or a negative `v`, which no
/// update produces, and −0.0 with them) counts as `+∞`, so that
/// [`StepConsts::provably_finite`] refuses it.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Maxima {
    pub p: f32,
    pub m: f32,
    pub v: f32,
}

impl Maxima {
    #[inline(always)]
    pub fn of(p: f32, m: f32, v: f32) -> Self {
        MaximaBits::of(p, m, v).decode()
    }

    #[inline(always)]
    pub fn max(self, o: Self) -> Self {
        Self {
            p: self.p.max(o.p),
            m: self.m.max(o.m),
            v: self.v.max(o.v),
        }
    }
}

/// [`Maxima`] as the largest bit patterns: `|p|` and `|m|` with the sign bit cleared,
/// `v` as it is, so that a NaN (whose pattern is above +∞'s) or a negative `v` (sign bit
/// set) is above every finite value and decodes to +∞. Integer maxima need no branch:
/// the update loop that takes them vectorises.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MaximaBits {
    p: u32,
    m: u32,
    v: u32,
}

impl MaximaBits {
    const ABS: u32 = 0x7fff_ffff;

    #[inline(always)]
    pub fn of(p: f32, m: f32, v: f32) -> Self {
        Self {
            p: p.to_bits() & Self::ABS,
            m: m.to_bits() & Self::ABS,
            v: v.to_bits(),
        }
    }

    #[inline(always)]
    pub fn max(self, o: Self) -> Self {
        Self {
            p: self.p.max(o.p),
            m: self.m.max(o.m),
            v: self.v.max(o.v),
        }
    }

    pub fn decode(self) -> Maxima {
        let value = |b: u32| {
            if b > f32::INFINITY.to_bits() {
                f32::INFINITY
            } else {
                f32::from_bits(b)
            }
        };
        Maxima {
            p: value(self.p),
            m: value(self.m),
            v: value(self.v),
        }
    }
}

/// A gradient's sum of squares (f64) and largest magnitude, in one pass. The sum is
/// finite exactly when every element is (squares of finite f32 values cannot overflow
/// f64), and it is the same bits for any thread count: fixed blocks, each summed over
/// eight lanes, the blocks added in order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GradSummary {
    pub sum_sq: f64,
    pub max_abs: f32,
}

impl GradSummary {
    /// Elements per block of the sum.
    const BLOCK: usize = 1 << 16;

    pub fn of(g: &[f32]) -> Self {
        use rayon::prelude::*;
        let blocks: Vec<Self> = g.par_chunks(Self::BLOCK).map(Self::of_block).collect();
        blocks.into_iter().fold(
            Self {
                sum_sq: 0.0,
                max_abs: 0.0,
            },
            |a, b| Self {
                sum_sq: a.sum_sq + b.sum_sq,
                max_abs: a.max_abs.max(b.max_abs),
            },
        )
    }

    /// The summary of a flat f32 gradient on a device: squares summed in f64, in
    /// buckets so that the f64 copy is one bucket's size; one synchronisation. The same
    /// bits for the same gradient on the same device; not the host's bits (another
    /// summation order).
    pub fn of_tensor(g: &candle_core::Tensor) -> candle_core::Result<Self> {
        use candle_core::{DType, Tensor};
        let n = g.dims1()?;
        if n == 0 {
            return Ok(Self {
                sum_sq: 0.0,
                max_abs: 0.0,
            });
        }
        let (mut sums, mut maxima) = (Vec::new(), Vec::new());
        for off in (0..n).step_by(device_adamw::BUCKET) {
            let part = g.narrow(0, off, device_adamw::BUCKET.min(n - off))?;
            sums.push(device_adamw::wide_sum(&part.to_dtype(DType::F64)?.sqr()?)?);
            maxima.push(device_adamw::wide_max(&part.abs()?)?);
        }
        let both = Tensor::cat(
            &[
                Tensor::stack(&sums, 0)?.sum_all()?.unsqueeze(0)?,
                Tensor::stack(&maxima, 0)?
                    .max(0)?
                    .to_dtype(DType::F64)?
                    .unsqueeze(0)?,
            ],
            0,
        )?
        .to_vec1::<f64>()?;
        // A NaN makes the sum NaN (the maximum may skip it): `finite` reads the sum.
        Ok(Self {
            sum_sq: both[0],
            max_abs: both[1] as f32,
        })
    }

    fn of_block(g: &[f32]) -> Self {
        let mut out = Self {
            sum_sq: 0.0,
            max_abs: 0.0,
        };
        summarize_block(g, &mut out);
        out
    }

    pub fn finite(&self) -> bool {
        self.sum_sq.is_finite()
    }

    pub fn norm(&self) -> f64 {
        self.sum_sq.sqrt()
    }
}

osrt_kernels::simd_kernel! {
    /// Eight f64 lanes of squares and of maxima over one block (so that it vectorises).
    pub fn summarize_block(g: &[f32], out: &mut GradSummary) {
        let mut sq = [0f64; 8];
        let mut mx = [0f32; 8];
        let chunks = g.chunks_exact(8);
        let rest = chunks.remainder();
        for c in chunks {
            for l in 0..8 {
                sq[l] += c[l] as f64 * c[l] as f64;
                mx[l] = mx[l].max(c[l].abs());
            }
        }
        for (l, &x) in rest.iter().enumerate() {
            sq[l] += x as f64 * x as f64;
            mx[l] = mx[l].max(x.abs());
        }
        out.sum_sq = ((sq[0] + sq[1]) + (sq[2] + sq[3])) + ((sq[4] + sq[5]) + (sq[6] + sq[7]));
        out.max_abs = mx.iter().fold(0f32, |a, &b| a.max(b));
    }
}

/// Global L2 norm of a buffer ([`GradSummary`]'s sum).
pub fn global_norm(g: &[f32]) -> f64 {
    GradSummary::of(g).norm()
}

/// The factor that brings a gradient of norm `norm` to at most `max_norm` (1 when it is
/// already within; applied as an f32 product).
pub fn clip_scale(norm: f64, max_norm: Option<f64>) -> f32 {
    match max_norm {
        Some(max) if norm > max && norm > 0.0 => (max / norm) as f32,
        _ => 1.0,
    }
}

#[cfg(test)]
mod tests;
