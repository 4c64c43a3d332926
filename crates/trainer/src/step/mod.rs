//! One training step, split the way data parallelism needs it: [`Trainer::gradients`]
//! computes the MSE loss and the gradient as **one flat f32 buffer in the fixed parameter
//! order** (sorted names), and [`Trainer::apply`] takes such a buffer (possibly averaged
//! over workers) and performs the optimiser step. A non-finite loss, gradient or updated
//! weight skips the step: nothing non-finite ever reaches the weights.
//!
//! On the CPU the optimiser updates each parameter's storage in place from flat host
//! moments; on a GPU its moments stay on the device ([`DeviceAdamW`]) and only the flat
//! gradient crosses to the host for the all-reduce and back. Matrix products run in the job's `precision`
//! (`train.precision`: f32, or bf16 on a GPU), weights and optimiser state in f32.
//!
//! The step's parts have files of their own: the forward and backward passes, in
//! micro-batches (`gradients`), the flat gradient (`flat`), the optimiser step (`apply`)
//! and a batch's tensors (`batch`). This file holds the [`Trainer`] they share.

mod apply;
mod batch_tensors;
mod flat;
mod gradients;

pub use apply::{ApplyOutcome, Optimizer};
pub use batch_tensors::BatchTensors;
pub use flat::{CONTROL_FLOATS, Gradient};
pub use gradients::{Phases, StepGradients, micro_batches};

use crate::config::JobConfig;
use crate::error::Result;
use crate::optim::{AdamW, DeviceAdamW, Hyperparams};
use candle_core::{Device, Tensor};
use osrt_model::{Osrt, Params};
use rand::Rng;

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
    /// Where the learning rate's decay ends, once known (`crate::schedule`): the config's
    /// step count, or a budget job's step limit or measured horizon.
    pub horizon: Option<u64>,
    /// Synchronise the device after the forward and the backward pass and report their
    /// times in [`StepGradients::phases`] (benchmarks; costs a synchronisation on a GPU).
    pub time_phases: bool,
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
        let hyper = Hyperparams {
            beta1: t.beta1,
            beta2: t.beta2,
            eps: t.adam_eps,
            weight_decay: t.weight_decay,
        };
        let opt = if crate::device::is_cpu(&device) {
            Optimizer::Host(AdamW::new(n, hyper))
        } else {
            Optimizer::Device(DeviceAdamW::new(n, hyper, &device)?)
        };
        let horizon = cfg.train.schedule().initial_horizon(None, false);
        Ok(Self {
            cfg,
            params,
            model,
            opt,
            num_parameters: n,
            step: 0,
            skipped_total: 0,
            skipped_in_a_row: 0,
            horizon,
            time_phases: false,
            device,
        })
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    pub fn num_parameters(&self) -> usize {
        self.num_parameters
    }

    /// The learning rate of step `step` (0-based) with the horizon now in force.
    pub fn lr_at(&self, step: u64) -> f64 {
        self.cfg.train.schedule().lr_at(step, self.horizon)
    }

    /// Standard-normal slot noise for random slot init (from the caller's seeded RNG).
    pub fn slot_noise(&self, b: usize, rng: &mut impl Rng) -> Result<Option<Tensor>> {
        Ok(self.model.slot_noise(b, rng)?)
    }

    /// The device's total memory, in words.
    fn card_memory(&self) -> String {
        match self.device.location() {
            candle_core::DeviceLocation::Cuda { gpu_id } => crate::device::gpu_memory(gpu_id)
                .map_or("the device's total memory is unknown".into(), |b| {
                    format!("the device has {:.1} GiB", b / (1u64 << 30) as f64)
                }),
            _ => "the device's total memory is unknown".into(),
        }
    }
}
