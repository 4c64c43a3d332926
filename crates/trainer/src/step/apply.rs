//! The optimiser step: where AdamW's state lives (host or device), and [`Trainer::apply`],
//! which clips a flat gradient and applies it, or skips the step where a value is not
//! finite. Its own file because it only reads the flat gradient, wherever it came from
//! (one worker's passes or the all-reduce).

use super::{Gradient, Trainer};
use crate::error::{Result, TrainError};
use crate::optim::{AdamW, DeviceAdamW, GradSummary, clip_scale};
use candle_core::{Tensor, Var};

/// What [`Trainer::apply`] did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ApplyOutcome {
    Applied {
        grad_norm: f64,
        lr: f64,
    },
    /// Skipped: the reason says which value was non-finite.
    Skipped {
        reason: &'static str,
    },
}

/// The optimiser's state where it lives: on the host (CPU training) or on the device.
pub enum Optimizer {
    Host(AdamW),
    Device(DeviceAdamW),
}

impl Optimizer {
    /// Updates applied so far (AdamW's `t`).
    pub fn t(&self) -> u64 {
        match self {
            Self::Host(o) => o.t,
            Self::Device(o) => o.t,
        }
    }

    /// First and second moments, copied to the host (for a checkpoint).
    pub fn moments(&self) -> Result<(Vec<f32>, Vec<f32>)> {
        Ok(match self {
            Self::Host(o) => (o.m.clone(), o.v.clone()),
            Self::Device(o) => (o.m.to_vec1::<f32>()?, o.v.to_vec1::<f32>()?),
        })
    }

    /// Restores moments and step count (from a checkpoint).
    pub fn restore(&mut self, m: Vec<f32>, v: Vec<f32>, t: u64) -> Result<()> {
        match self {
            Self::Host(o) => o.restore(m, v, t),
            Self::Device(o) => o.restore(m, v, t)?,
        }
        Ok(())
    }
}

impl Trainer {
    /// Clips (if configured) and applies a flat gradient with AdamW, or skips the step if
    /// the loss, the gradient, the resulting weights or the moments are not finite. Counts
    /// the step either way.
    pub fn apply(&mut self, loss: f64, grads: impl Into<Gradient>) -> Result<ApplyOutcome> {
        self.apply_summarized(loss, grads.into(), None)
    }

    /// [`Trainer::apply`] with the gradient's summary where it is known already
    /// ([`Gradient::summary`]), saving a pass over the gradient.
    pub fn apply_summarized(
        &mut self,
        loss: f64,
        grads: Gradient,
        summary: Option<GradSummary>,
    ) -> Result<ApplyOutcome> {
        let out = self.apply_here(loss, grads, summary);
        self.final_if_out_of_memory(out)
    }

    /// An optimiser step the device cannot hold ends the job, as a forward and backward
    /// pass that cannot does (`gradients_kept`): a restart from the last checkpoint would
    /// meet the same wall.
    fn final_if_out_of_memory(&self, out: Result<ApplyOutcome>) -> Result<ApplyOutcome> {
        let e = match out {
            Err(TrainError::Model(e)) if crate::device::is_out_of_memory(&e) => e,
            other => return other,
        };
        let n = self.num_parameters as f64;
        // Weights, both moments and the gradient in f32.
        let state_gib = 16.0 * n / (1u64 << 30) as f64;
        Err(TrainError::OutOfMemory(format!(
            "out of memory on {:?} ({e}) in the optimiser step: {} parameters, whose weights, \
             AdamW moments and gradient take {state_gib:.2} GiB before the update's \
             temporaries, did not leave room for it; {}. Lower train.batch_size or \
             train.rays_per_scene (the step's activations share the device), or train a \
             smaller model",
            self.device.location(),
            self.num_parameters,
            self.card_memory(),
        )))
    }

    fn apply_here(
        &mut self,
        loss: f64,
        mut grads: Gradient,
        summary: Option<GradSummary>,
    ) -> Result<ApplyOutcome> {
        let step = self.step;
        self.step += 1;
        let skip = |me: &mut Self, reason| {
            me.skipped_total += 1;
            me.skipped_in_a_row += 1;
            tracing::warn!(
                step,
                reason,
                skipped_total = me.skipped_total,
                "step skipped"
            );
            Ok(ApplyOutcome::Skipped { reason })
        };
        if !loss.is_finite() {
            return skip(self, "non-finite loss");
        }
        let t0 = std::time::Instant::now();
        let mut summary = match summary {
            Some(s) => s,
            None => grads.summary()?,
        };
        tracing::debug!(summary_s = t0.elapsed().as_secs_f64(), "gradient summary");
        if !summary.finite() {
            return skip(self, "non-finite gradient");
        }
        let grad_norm = summary.norm();
        let scale = clip_scale(grad_norm, self.cfg.train.clip_norm);
        // The host optimiser clips a host gradient element by element as it updates
        // (the same f32 products): no pass over the gradient, no second summary.
        let fold = matches!((&self.opt, &grads), (Optimizer::Host(_), Gradient::Host(_)));
        if scale != 1.0 && !fold {
            grads = match grads {
                Gradient::Host(mut g) => {
                    g.iter_mut().for_each(|x| *x *= scale);
                    Gradient::Host(g)
                }
                Gradient::Device(g) => Gradient::Device((g * scale as f64)?),
            };
            summary = grads.summary()?;
        }
        let lr = self.lr_at(step);
        let vars: Vec<Var> = self.params.vars().into_iter().map(|(_, v)| v).collect();
        let version = self.params.version();
        let n = self.num_parameters;
        let applied = match (&mut self.opt, grads) {
            (Optimizer::Host(opt), g) if fold => {
                // Rounding is monotonic: the largest |g·s| is the largest |g| times s.
                let g_max = summary.max_abs * scale;
                opt.step_scaled(&vars, version, &g.into_host()?, scale, g_max, lr)?
            }
            (Optimizer::Host(opt), g) => {
                opt.step(&vars, version, &g.into_host()?, summary.max_abs, lr)?
            }
            (Optimizer::Device(opt), Gradient::Device(g)) => {
                opt.step(&vars, version, &g, summary.max_abs, lr)?
            }
            (Optimizer::Device(opt), Gradient::Host(g)) => {
                let g = Tensor::from_vec(g, n, &self.device)?;
                opt.step(&vars, version, &g, summary.max_abs, lr)?
            }
        };
        if !applied {
            // A huge finite gradient can square to ∞ in the second moment while the
            // weights stay finite (m / √∞ = 0): the state must not keep it either.
            return skip(self, "non-finite updated weight or moment");
        }
        self.skipped_in_a_row = 0;
        Ok(ApplyOutcome::Applied { grad_norm, lr })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::JobConfig;
    use candle_core::Device;

    /// A device out of memory in the optimiser step is final, with the parameter count,
    /// the state's size and what to change; other errors and outcomes pass unchanged.
    #[test]
    fn an_optimiser_step_out_of_memory_ends_the_job() {
        let trainer = Trainer::new(JobConfig::preset("tiny").unwrap(), Device::Cpu).unwrap();
        let oom = |text: &str| Err(TrainError::Model(candle_core::Error::Msg(text.into())));
        for text in [
            "DriverError(CUDA_ERROR_OUT_OF_MEMORY, \"out of memory\")",
            "CublasError(CUBLAS_STATUS_ALLOC_FAILED)",
        ] {
            match trainer.final_if_out_of_memory(oom(text)) {
                Err(TrainError::OutOfMemory(m)) => {
                    for part in [
                        text,
                        "in the optimiser step",
                        &format!("{} parameters", trainer.num_parameters()),
                        "Lower train.batch_size",
                    ] {
                        assert!(m.contains(part), "{part:?} not in {m}");
                    }
                }
                other => panic!("{text}: {other:?}"),
            }
        }
        assert!(matches!(
            trainer.final_if_out_of_memory(oom("CUDA_ERROR_ILLEGAL_ADDRESS")),
            Err(TrainError::Model(_))
        ));
        let applied = Ok(ApplyOutcome::Applied {
            grad_norm: 1.0,
            lr: 1e-4,
        });
        assert!(matches!(
            trainer.final_if_out_of_memory(applied),
            Ok(ApplyOutcome::Applied { .. })
        ));
    }
}
