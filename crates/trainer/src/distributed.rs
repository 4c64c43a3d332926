//! One data-parallel step's reduction, less the ring that carries it (`osrt-worker`):
//! every rank's gradient, weighted by its real sample count, summed over the ring
//! together with a few control values, so that every replica derives the same averaged
//! gradient, loss and decisions from the same bytes.
//!
//! Buffer layout (f32): `[g₀·n, g₁·n, …, g_{P−1}·n, n, loss·n, evaluate, stop, horizon,
//! bad, bad_rank + 1]` where `n` is the rank's scene count ([`CONTROL_FLOATS`] after the
//! gradient). `evaluate`, `stop` and `horizon` (0: none) are set by rank 0 only (its
//! clock decides), so after the sum every rank sees rank 0's decision. `bad` is 1 on a rank whose loss or gradient
//! is not finite: the sums say how many and, when one, which. A non-finite value on any
//! rank makes the sum non-finite on every rank, so all replicas skip the step together.

use crate::error::Result;
use crate::lr_schedule::MAX_HORIZON;
use crate::optim::GradSummary;
use crate::step::{Gradient, StepGradients};

/// Floats appended after the gradient.
pub use crate::step::CONTROL_FLOATS;

/// Decisions rank 0 contributes to a step (ignored on other ranks).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Signals {
    pub evaluate: bool,
    pub stop: bool,
    /// The learning rate's decay horizon rank 0 measured (`crate::schedule`): at most
    /// `lr_schedule::MAX_HORIZON`, exact in f32.
    pub horizon: Option<u64>,
}

/// The step every replica takes.
#[derive(Debug, Clone)]
pub struct Reduced {
    /// Sample-weighted mean gradient (where a single worker computed it on a GPU, still
    /// there).
    pub grads: Gradient,
    /// Sample-weighted mean loss.
    pub loss: f64,
    /// Scenes in the global batch.
    pub samples: f64,
    pub signals: Signals,
    /// Ranks whose own loss or gradient was not finite this step.
    pub nonfinite: NonFiniteRanks,
    /// The gradient's summary where the reduction already took it (one worker), so that
    /// the optimiser does not pass over the gradient again.
    pub summary: Option<GradSummary>,
}

/// Which ranks computed a non-finite loss or gradient: their number, and the rank when
/// it is one (sums of small integers are exact in f32, so both survive the all-reduce).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct NonFiniteRanks {
    pub count: u32,
    pub only: Option<usize>,
}

impl std::fmt::Display for NonFiniteRanks {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match (self.count, self.only) {
            (0, _) => write!(f, "none"),
            (_, Some(r)) => write!(f, "rank {r}"),
            (n, None) => write!(f, "{n} ranks"),
        }
    }
}

/// The step of a worker alone: its gradient as it is, where it is, with nothing to weight
/// or sum (and no pass over it but the finiteness check).
pub fn alone(
    rank: usize,
    g: StepGradients<impl Into<Gradient>>,
    signals: Signals,
) -> Result<Reduced> {
    let grads: Gradient = g.grads.into();
    let summary = grads.summary()?;
    let bad = !g.loss.is_finite() || !summary.finite();
    Ok(Reduced {
        summary: Some(summary),
        loss: g.loss,
        samples: g.samples as f64,
        grads,
        signals,
        nonfinite: NonFiniteRanks {
            count: u32::from(bad),
            only: bad.then_some(rank),
        },
    })
}

/// This rank's buffer for the all-reduce (the layout above).
pub fn contribution(
    rank: usize,
    g: StepGradients<impl Into<Gradient>>,
    signals: Signals,
) -> Result<Vec<f32>> {
    let grads: Gradient = g.grads.into();
    let n = g.samples as f32;
    let mut buf = grads.into_host()?;
    let bad = !g.loss.is_finite() || buf.iter().any(|x| !x.is_finite());
    buf.iter_mut().for_each(|x| *x *= n);
    buf.extend(control(rank, g.loss, g.samples, signals, bad));
    Ok(buf)
}

/// This rank's control values (the layout above) for a gradient of `samples` scenes whose
/// loss or gradient is non-finite where `bad`.
pub fn control(
    rank: usize,
    loss: f64,
    samples: usize,
    signals: Signals,
    bad: bool,
) -> [f32; CONTROL_FLOATS] {
    let n = samples as f32;
    let mine = if rank == 0 {
        signals
    } else {
        Signals::default()
    };
    [
        n,
        loss as f32 * n,
        f32::from(u8::from(mine.evaluate)),
        f32::from(u8::from(mine.stop)),
        mine.horizon.map_or(0.0, |h| h.min(MAX_HORIZON) as f32),
        f32::from(u8::from(bad)),
        if bad { (rank + 1) as f32 } else { 0.0 },
    ]
}

/// The step every rank derives from the summed buffers.
pub fn reduced_from(mut buf: Vec<f32>) -> Reduced {
    let p = buf.len() - CONTROL_FLOATS;
    let mut sums = [0.0; CONTROL_FLOATS];
    sums.copy_from_slice(&buf[p..]);
    let total = sums[0];
    buf.truncate(p);
    buf.iter_mut().for_each(|x| *x /= total);
    reduced_with(Gradient::Host(buf), &sums)
}

/// The step every rank derives from the summed control values, with `grads` the summed
/// gradient already divided by the scene count (`sums[0]`).
pub fn reduced_with(grads: Gradient, sums: &[f32; CONTROL_FLOATS]) -> Reduced {
    let [
        total,
        loss_sum,
        evaluate,
        stop,
        horizon,
        bad_count,
        bad_rank_sum,
    ] = *sums;
    let (bad_count, bad_rank_sum) = (bad_count as u32, bad_rank_sum as usize);
    let nonfinite = NonFiniteRanks {
        count: bad_count,
        only: (bad_count == 1).then(|| bad_rank_sum.saturating_sub(1)),
    };
    Reduced {
        summary: None,
        grads,
        loss: (loss_sum / total) as f64,
        samples: total as f64,
        signals: Signals {
            evaluate: evaluate > 0.5,
            stop: stop > 0.5,
            horizon: (horizon >= 1.0).then_some(horizon as u64),
        },
        nonfinite,
    }
}

/// Rank 0's weights for a broadcast as a sum: the other ranks contribute zeros.
pub fn zero_unless_rank0(rank: usize, flat: &mut [f32]) {
    if rank != 0 {
        flat.iter_mut().for_each(|x| *x = 0.0);
    }
}
