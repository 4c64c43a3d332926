//! One training step, split the way data parallelism needs it: [`Trainer::gradients`]
//! computes the MSE loss and the gradient as **one flat f32 buffer in the fixed parameter
//! order** (sorted names), and [`Trainer::apply`] takes such a buffer (possibly averaged
//! over workers) and performs the optimiser step. A non-finite loss, gradient or updated
//! weight skips the step: nothing non-finite ever reaches the weights.

use crate::config::JobConfig;
use crate::error::Result;
use crate::optim::{AdamW, clip_global_norm};
use candle_core::{Device, Tensor};
use osrt_dataset::Batch;
use osrt_model::{Osrt, Params};
use rand::Rng;

/// Tensors of a batch.
pub struct BatchTensors {
    pub images: Tensor,
    pub origins: Tensor,
    pub directions: Tensor,
    pub target_origins: Tensor,
    pub target_directions: Tensor,
    pub target_rgb: Tensor,
}

impl BatchTensors {
    pub fn new(b: &Batch, dev: &Device) -> Result<Self> {
        let img = (b.batch_size, b.input_views, b.height, b.width, 3);
        let tgt = (b.batch_size, b.rays_per_scene, 3);
        Ok(Self {
            images: Tensor::from_slice(&b.input_images, img, dev)?,
            origins: Tensor::from_slice(&b.input_origins, img, dev)?,
            directions: Tensor::from_slice(&b.input_directions, img, dev)?,
            target_origins: Tensor::from_slice(&b.target_origins, tgt, dev)?,
            target_directions: Tensor::from_slice(&b.target_directions, tgt, dev)?,
            target_rgb: Tensor::from_slice(&b.target_rgb, tgt, dev)?,
        })
    }
}

/// Gradients of one (local) batch.
pub struct StepGradients {
    pub loss: f64,
    /// Flat, in [`Params::vars`] order.
    pub grads: Vec<f32>,
    /// Scenes this gradient averages over (for weighting across workers).
    pub samples: usize,
}

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

pub struct Trainer {
    pub cfg: JobConfig,
    pub params: Params,
    pub model: Osrt,
    pub opt: AdamW,
    /// Optimiser steps taken (applied or skipped).
    pub step: u64,
    pub skipped_total: u64,
    pub skipped_in_a_row: u64,
    device: Device,
}

impl Trainer {
    /// A freshly initialised model from `cfg.train.seed`.
    pub fn new(cfg: JobConfig, device: Device) -> Result<Self> {
        cfg.validate()?;
        let params = Params::new(cfg.train.seed);
        let model = Osrt::new(&cfg.model, params.var_builder(&device))?;
        let n = params.num_elements();
        let t = &cfg.train;
        let opt = AdamW::new(n, t.beta1, t.beta2, t.adam_eps, t.weight_decay);
        Ok(Self {
            cfg,
            params,
            model,
            opt,
            step: 0,
            skipped_total: 0,
            skipped_in_a_row: 0,
            device,
        })
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    pub fn num_parameters(&self) -> usize {
        self.opt.m.len()
    }

    /// Standard-normal slot noise for random slot init (from the caller's seeded RNG).
    pub fn slot_noise(&self, b: usize, rng: &mut impl Rng) -> Result<Option<Tensor>> {
        Ok(self.model.slot_noise(b, rng)?)
    }

    /// MSE on the sampled target rays, and its gradient as one flat buffer.
    pub fn gradients(&self, batch: &Batch, rng: &mut (impl Rng + Send)) -> Result<StepGradients> {
        osrt_model::fused::on_device_pool(&self.device, || self.gradients_here(batch, rng))
    }

    fn gradients_here(&self, batch: &Batch, rng: &mut impl Rng) -> Result<StepGradients> {
        let t = BatchTensors::new(batch, &self.device)?;
        let noise = self.slot_noise(batch.batch_size, rng)?;
        let slots = self
            .model
            .encode(&t.images, &t.origins, &t.directions, noise.as_ref())?;
        let out = self
            .model
            .decode(&slots.slots, &t.target_origins, &t.target_directions)?;
        let loss = (&out.rgb - &t.target_rgb)?.sqr()?.mean_all()?;
        let grads = loss.backward()?;
        let mut flat = Vec::with_capacity(self.num_parameters());
        for (_, var) in self.params.vars() {
            match grads.get(var.as_tensor()) {
                Some(g) => flat.extend(g.flatten_all()?.to_vec1::<f32>()?),
                // A parameter the loss does not reach (e.g. unused init of another mode).
                None => flat.extend(std::iter::repeat_n(0.0, var.elem_count())),
            }
        }
        Ok(StepGradients {
            loss: loss.to_scalar::<f32>()? as f64,
            grads: flat,
            samples: batch.batch_size,
        })
    }

    /// Clips (if configured) and applies a flat gradient with AdamW, or skips the step if
    /// the loss, the gradient or the resulting weights are not finite. Counts the step
    /// either way.
    pub fn apply(&mut self, loss: f64, mut grads: Vec<f32>) -> Result<ApplyOutcome> {
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
        if grads.iter().any(|g| !g.is_finite()) {
            return skip(self, "non-finite gradient");
        }
        let grad_norm = match self.cfg.train.clip_norm {
            Some(max) => clip_global_norm(&mut grads, max),
            None => crate::optim::global_norm(&grads),
        };
        let lr = self.cfg.train.lr_at(step);
        let params = self.params.flatten()?;
        let (new, m, v) = self.opt.propose(&params, &grads, lr);
        if new.iter().any(|p| !p.is_finite()) {
            return skip(self, "non-finite updated weight");
        }
        self.params.load_flat(&new)?;
        self.opt.commit(m, v);
        self.skipped_in_a_row = 0;
        Ok(ApplyOutcome::Applied { grad_norm, lr })
    }
}
