//! One training step, split the way data parallelism needs it: [`Trainer::gradients`]
//! computes the MSE loss and the gradient as **one flat f32 buffer in the fixed parameter
//! order** (sorted names), and [`Trainer::apply`] takes such a buffer (possibly averaged
//! over workers) and performs the optimiser step. A non-finite loss, gradient or updated
//! weight skips the step: nothing non-finite ever reaches the weights.
//!
//! On the CPU the optimiser runs on the host over `Vec<f32>` buffers; on a GPU its
//! moments stay on the device ([`DeviceAdamW`]) and only the flat gradient crosses to the
//! host for the all-reduce and back. Matrix products run in the job's `precision`
//! (`train.precision`: f32, or bf16 on a GPU), weights and optimiser state in f32.

use crate::config::JobConfig;
use crate::error::Result;
use crate::optim::{AdamW, DeviceAdamW, clip_global_norm};
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
            Self::Device(o) => o.hyper.t,
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
            Self::Host(o) => {
                (o.m, o.v, o.t) = (m, v, t);
            }
            Self::Device(o) => {
                let dev = o.m.device().clone();
                o.m = Tensor::from_vec(m, o.m.dims1()?, &dev)?;
                o.v = Tensor::from_vec(v, o.v.dims1()?, &dev)?;
                o.hyper.t = t;
            }
        }
        Ok(())
    }
}

pub struct Trainer {
    pub cfg: JobConfig,
    pub params: Params,
    pub model: Osrt,
    pub opt: Optimizer,
    num_parameters: usize,
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
        let opt = if crate::device::is_cpu(&device) {
            Optimizer::Host(AdamW::new(n, t.beta1, t.beta2, t.adam_eps, t.weight_decay))
        } else {
            let hyper = AdamW::new(0, t.beta1, t.beta2, t.adam_eps, t.weight_decay);
            Optimizer::Device(DeviceAdamW::new(n, hyper, &device)?)
        };
        Ok(Self {
            cfg,
            params,
            model,
            opt,
            num_parameters: n,
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
        self.num_parameters
    }

    /// Standard-normal slot noise for random slot init (from the caller's seeded RNG).
    pub fn slot_noise(&self, b: usize, rng: &mut impl Rng) -> Result<Option<Tensor>> {
        Ok(self.model.slot_noise(b, rng)?)
    }

    /// MSE on the sampled target rays, and its gradient as one flat buffer.
    pub fn gradients(&self, batch: &Batch, rng: &mut (impl Rng + Send)) -> Result<StepGradients> {
        let (kernels, precision) = (self.cfg.train.kernels, self.cfg.train.precision);
        osrt_kernels::with_kernels(kernels, || {
            osrt_kernels::with_precision(precision, || {
                osrt_kernels::on_device_pool(&self.device, || self.gradients_here(batch, rng))
            })
        })
    }

    fn gradients_here(&self, batch: &Batch, rng: &mut impl Rng) -> Result<StepGradients> {
        let t = BatchTensors::new(batch, &self.device)?;
        let noise = self.slot_noise(batch.batch_size, rng)?;
        // Drawn after the slot noise; nothing is drawn for decoders that do not sample.
        let offsets = self
            .model
            .ray_offsets(batch.batch_size, batch.rays_per_scene, rng)?;
        let slots = self
            .model
            .encode(&t.images, &t.origins, &t.directions, noise.as_ref())?;
        let out = self.model.decode_with(
            &slots.slots,
            &t.target_origins,
            &t.target_directions,
            offsets.as_ref(),
        )?;
        let loss = (&out.rgb - &t.target_rgb)?.sqr()?.mean_all()?;
        let grads = loss.backward()?;
        let flat = if crate::device::is_cpu(&self.device) {
            let mut flat = Vec::with_capacity(self.num_parameters());
            for (_, var) in self.params.vars() {
                match grads.get(var.as_tensor()) {
                    Some(g) => flat.extend(g.flatten_all()?.to_vec1::<f32>()?),
                    // A parameter the loss does not reach (e.g. unused init of another mode).
                    None => flat.extend(std::iter::repeat_n(0.0, var.elem_count())),
                }
            }
            flat
        } else {
            // One flat tensor on the device, then one copy to the host.
            let parts = self
                .params
                .vars()
                .iter()
                .map(|(_, var)| match grads.get(var.as_tensor()) {
                    Some(g) => g.to_dtype(candle_core::DType::F32)?.flatten_all(),
                    None => Tensor::zeros(var.elem_count(), candle_core::DType::F32, &self.device),
                })
                .collect::<candle_core::Result<Vec<_>>>()?;
            Tensor::cat(&parts, 0)?.to_vec1::<f32>()?
        };
        Ok(StepGradients {
            loss: loss.to_scalar::<f32>()? as f64,
            grads: flat,
            samples: batch.batch_size,
        })
    }

    /// Clips (if configured) and applies a flat gradient with AdamW, or skips the step if
    /// the loss, the gradient, the resulting weights or the moments are not finite. Counts the step
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
        match &mut self.opt {
            Optimizer::Host(opt) => {
                let params = self.params.flatten()?;
                let (new, m, v) = opt.propose(&params, &grads, lr);
                if new.iter().any(|p| !p.is_finite()) {
                    return skip(self, "non-finite updated weight");
                }
                // A huge finite gradient squares to ∞ in the second moment while the
                // weights stay finite (m / √∞ = 0): the state must not keep it either.
                if m.iter().chain(&v).any(|x| !x.is_finite()) {
                    return skip(self, "non-finite optimizer moment");
                }
                self.params.load_flat(&new)?;
                opt.commit(m, v);
            }
            Optimizer::Device(opt) => {
                let params = self.params.flatten_tensor()?;
                let grads = Tensor::from_vec(grads, params.dims1()?, &self.device)?;
                let new = opt.propose(&params, &grads, lr)?;
                if !new.finite {
                    return skip(self, "non-finite updated weight or moment");
                }
                self.params.load_flat_tensor(&new.params)?;
                opt.commit(new.m, new.v);
            }
        }
        self.skipped_in_a_row = 0;
        Ok(ApplyOutcome::Applied { grad_norm, lr })
    }
}
