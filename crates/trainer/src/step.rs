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

use crate::config::JobConfig;
use crate::error::{Result, TrainError};
use crate::optim::{AdamW, DeviceAdamW, GradSummary, Hyperparams, clip_scale};
use candle_core::{CpuStorage, Device, Storage, Tensor, Var};
use osrt_dataset::Batch;
use osrt_kernels::profile::MemoryMeter;
use osrt_model::{Osrt, Params};
use rand::Rng;

/// The scenes of a step's share that one forward and backward pass takes, with their
/// rows of the share's random numbers, and the weight of its mean in the share's (`None`:
/// the whole share in one pass, unweighted).
struct MicroBatch {
    scenes: std::ops::Range<usize>,
    noise: Option<Tensor>,
    offsets: Option<Tensor>,
    weight: Option<f64>,
}

/// A share of `n` scenes cut into consecutive micro-batches of at most `size` (`None`:
/// one pass); the last may be smaller.
pub fn micro_batches(n: usize, size: Option<usize>) -> Vec<std::ops::Range<usize>> {
    let size = size.filter(|&m| m > 0).unwrap_or(n).max(1);
    (0..n.div_ceil(size))
        .map(|i| i * size..((i + 1) * size).min(n))
        .collect()
}

/// `sum + grads`, parameter by parameter (the first micro-batch's gradients are the sum).
fn accumulate(sum: Vec<Option<Tensor>>, grads: Vec<Option<Tensor>>) -> Result<Vec<Option<Tensor>>> {
    if sum.is_empty() {
        return Ok(grads);
    }
    sum.into_iter()
        .zip(grads)
        .map(|pair| {
            Ok(match pair {
                (Some(a), Some(g)) => Some((a + g)?),
                (a, g) => a.or(g),
            })
        })
        .collect()
}

/// The passes' seconds, each lap ending synchronised with the device where timed.
struct Clock {
    timing: bool,
    device: Device,
    at: std::time::Instant,
    forward_s: f64,
    backward_s: f64,
}

impl Clock {
    fn new(timing: bool, device: &Device) -> Self {
        Self {
            timing,
            device: device.clone(),
            at: std::time::Instant::now(),
            forward_s: 0.0,
            backward_s: 0.0,
        }
    }

    fn lap(&mut self) -> Result<f64> {
        if self.timing {
            self.device.synchronize()?;
        }
        let s = self.at.elapsed().as_secs_f64();
        self.at = std::time::Instant::now();
        Ok(s)
    }

    fn forward(&mut self) -> Result<()> {
        self.forward_s += self.lap()?;
        Ok(())
    }

    fn backward(&mut self) -> Result<()> {
        self.backward_s += self.lap()?;
        Ok(())
    }
}

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
        Self::scenes(b, 0..b.batch_size, dev)
    }

    /// The tensors of the batch's scenes `scenes` only (a micro-batch: nothing of the
    /// other scenes reaches the device).
    pub fn scenes(b: &Batch, scenes: std::ops::Range<usize>, dev: &Device) -> Result<Self> {
        let n = scenes.len();
        let per_image = b.input_views * b.height * b.width * 3;
        let per_target = b.rays_per_scene * 3;
        let img = (n, b.input_views, b.height, b.width, 3);
        let tgt = (n, b.rays_per_scene, 3);
        let image = |v: &[f32]| {
            Tensor::from_slice(
                &v[scenes.start * per_image..scenes.end * per_image],
                img,
                dev,
            )
        };
        let target = |v: &[f32]| {
            Tensor::from_slice(
                &v[scenes.start * per_target..scenes.end * per_target],
                tgt,
                dev,
            )
        };
        Ok(Self {
            images: image(&b.input_images)?,
            origins: image(&b.input_origins)?,
            directions: image(&b.input_directions)?,
            target_origins: target(&b.target_origins)?,
            target_directions: target(&b.target_directions)?,
            target_rgb: target(&b.target_rgb)?,
        })
    }
}

/// Gradients of one (local) batch: by default a host buffer, as the all-reduce sends it.
pub struct StepGradients<G = Vec<f32>> {
    pub loss: f64,
    /// Flat, in [`Params::vars`] order.
    pub grads: G,
    /// Scenes this gradient averages over (for weighting across workers).
    pub samples: usize,
    /// The forward and backward passes' seconds, synchronised, where the trainer times
    /// its phases ([`Trainer::time_phases`] or debug logging).
    pub phases: Option<Phases>,
}

/// With the phases timed, the memory the forward pass leaves held (its graph) and the
/// passes' peak, above what was held when the probe started (before the batch came in).
struct MemoryProbe {
    meter: crate::device::Meter,
    before: Option<u64>,
}

impl MemoryProbe {
    fn start(on: bool, device: &Device) -> Self {
        let meter = crate::device::Meter(device.clone());
        let before = if on { meter.live() } else { None };
        if before.is_some() {
            meter.reset_peak();
        }
        Self { meter, before }
    }

    /// Bytes held now beyond the start (`None` when off: nothing is read or synchronised).
    fn held(&self) -> Option<u64> {
        let before = self.before?;
        Some(self.meter.live()?.saturating_sub(before))
    }

    /// Bytes held when the probe started (`None` when off).
    fn held_before(&self) -> Option<u64> {
        self.before
    }

    /// The most bytes held at once since the start, beyond it (`None` when off).
    fn peak(&self) -> Option<u64> {
        let before = self.before?;
        Some(self.meter.peak()?.saturating_sub(before))
    }
}

/// Seconds of a step's passes, each ending synchronised with the device, and its memory
/// (heap on the CPU where the binary counts it, the memory pool on a GPU).
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct Phases {
    pub forward_s: f64,
    pub backward_s: f64,
    /// Bytes held after the forward pass (the batch and the whole graph) beyond what was
    /// held before the batch came in.
    pub forward_kept_bytes: Option<u64>,
    /// The most bytes held at once through the forward and backward passes, beyond the
    /// same starting point.
    pub peak_bytes: Option<u64>,
}

/// A flat f32 gradient in [`Params::vars`] order: in host memory (what the all-reduce
/// sends and the host optimiser reads), or one tensor on the device that computed it (a
/// single worker on a GPU: nothing to sum with anyone, so it never leaves the device).
#[derive(Debug, Clone)]
pub enum Gradient {
    Host(Vec<f32>),
    Device(Tensor),
}

impl From<Vec<f32>> for Gradient {
    fn from(g: Vec<f32>) -> Self {
        Self::Host(g)
    }
}

impl From<Tensor> for Gradient {
    fn from(g: Tensor) -> Self {
        Self::Device(g)
    }
}

impl Gradient {
    /// The host buffer, copied from the device where the gradient lives there.
    pub fn into_host(self) -> Result<Vec<f32>> {
        Ok(match self {
            Self::Host(g) => g,
            Self::Device(g) => g.to_vec1::<f32>()?,
        })
    }

    /// The host buffer, where the gradient is on the host.
    pub fn host(&self) -> Option<&[f32]> {
        match self {
            Self::Host(g) => Some(g),
            Self::Device(_) => None,
        }
    }

    /// Its sum of squares and largest magnitude (on the device where it lives there).
    pub fn summary(&self) -> Result<GradSummary> {
        Ok(match self {
            Self::Host(g) => GradSummary::of(g),
            Self::Device(g) => GradSummary::of_tensor(g)?,
        })
    }
}

/// Floats the reduction appends after a flat gradient (`crate::distributed`'s control
/// values): a flat gradient is allocated with room for them, so appending does not move it.
pub const CONTROL_FLOATS: usize = 7;

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

    /// MSE on the sampled target rays, and its gradient as one flat host buffer.
    pub fn gradients<R: Rng + Send + Clone>(
        &self,
        batch: &Batch,
        rng: &mut R,
    ) -> Result<StepGradients> {
        let g = self.gradients_kept(batch, rng, false)?;
        Ok(StepGradients {
            loss: g.loss,
            grads: g.grads.into_host()?,
            samples: g.samples,
            phases: g.phases,
        })
    }

    /// [`Trainer::gradients`], with the flat gradient left a tensor on the model's device
    /// where `keep` is set ([`Gradient::Device`], also on the CPU): a single worker on a
    /// GPU has no all-reduce to feed, and a ring stages a device gradient bucket by bucket
    /// (`crate::staging`).
    pub fn gradients_kept<R: Rng + Send + Clone>(
        &self,
        batch: &Batch,
        rng: &mut R,
        keep: bool,
    ) -> Result<StepGradients<Gradient>> {
        self.gradients_each(batch, std::slice::from_mut(rng), keep)
    }

    /// [`Trainer::gradients_kept`] with one RNG per scene of the batch (`rngs[i]` draws
    /// scene `i`'s slot noise and ray offsets, after its rays: the batch was built from
    /// the same RNGs), or a single RNG for all.
    pub fn gradients_each<R: Rng + Send + Clone>(
        &self,
        batch: &Batch,
        rngs: &mut [R],
        keep: bool,
    ) -> Result<StepGradients<Gradient>> {
        if rngs.len() != 1 && rngs.len() != batch.batch_size {
            return Err(TrainError::Config {
                path: "train step".into(),
                reason: format!(
                    "{} random streams for a batch of {} scenes: one, or one per scene",
                    rngs.len(),
                    batch.batch_size
                ),
            });
        }
        let (kernels, precision) = (self.cfg.train.kernels, self.cfg.train.precision);
        let run = |rngs: &mut [R]| {
            osrt_kernels::with_kernels(kernels, || {
                osrt_kernels::with_precision(precision, || {
                    osrt_kernels::on_device_pool(&self.device, || {
                        self.gradients_here(batch, rngs, keep)
                    })
                })
            })
        };
        // The device's pool keeps freed memory for reuse; where a step's allocation fails,
        // the free blocks go back to the driver and the step runs once more from the same
        // RNG state (so the retried step draws what the first try drew). Failing again,
        // it is final.
        let mut again = rngs.to_vec();
        let out = match run(rngs) {
            Err(TrainError::Model(e))
                if crate::device::is_out_of_memory(&e)
                    && crate::device::release_cached(&self.device) =>
            {
                tracing::warn!(
                    "out of device memory: the pool's free blocks released, step retried"
                );
                let out = run(&mut again);
                rngs.clone_from_slice(&again);
                out
            }
            other => other,
        };
        match out {
            Err(TrainError::Model(e)) if crate::device::is_out_of_memory(&e) => {
                Err(self.out_of_memory(batch, &e))
            }
            other => other,
        }
    }

    /// The final error of a step the device cannot hold: what the step is, its estimated
    /// peak against the device's memory, and what to change.
    fn out_of_memory(&self, batch: &Batch, e: &candle_core::Error) -> TrainError {
        let t = &self.cfg.train;
        let world = t.batch_size.div_ceil(batch.batch_size.max(1));
        let estimate = crate::footprint::estimate(
            &self.cfg,
            [batch.width as u32, batch.height as u32],
            world,
            1,
        )
        .map_or("no estimate for this decoder".to_string(), |m| m.describe());
        let card = self.card_memory();
        TrainError::OutOfMemory(format!(
            "out of memory on {:?} ({e}): the step of {} scene(s), {} input view(s) at {}×{} px and {} target rays each, in {:?} with {:?} kernels, did not fit; {estimate}; {card}. {}{}Lower train.batch_size or train.rays_per_scene, use more workers, or train in bf16 on a GPU",
            self.device.location(),
            batch.batch_size,
            batch.input_views,
            batch.width,
            batch.height,
            batch.rays_per_scene,
            t.precision,
            t.kernels,
            match t.micro_batch_size.unwrap_or(batch.batch_size) {
                1 => String::new(),
                m => format!(
                    "Set train.micro_batch_size below {m} (--micro-batch-size: the same step, its scenes in smaller passes). "
                ),
            },
            match t.recompute {
                true => "",
                false =>
                    "Set train.recompute = true (--recompute: activations made again in the backward pass, the same gradients). ",
            },
        ))
    }

    fn gradients_here(
        &self,
        batch: &Batch,
        rngs: &mut [impl Rng],
        keep: bool,
    ) -> Result<StepGradients<Gradient>> {
        #[cfg(feature = "fault-injection")]
        if std::env::var_os("OSRT_FAULT_DEVICE_OOM").is_some() {
            // The device's own error text, so the real classification runs.
            return Err(TrainError::Model(candle_core::Error::Msg(
                "CUDA_ERROR_OUT_OF_MEMORY (injected by OSRT_FAULT_DEVICE_OOM)".into(),
            )));
        }
        // With debug logging, the phases' times (synchronised on a GPU).
        let timing = self.time_phases || tracing::enabled!(tracing::Level::DEBUG);
        let mut clock = Clock::new(timing, &self.device);
        let probe = MemoryProbe::start(timing, &self.device);
        let n = batch.batch_size;
        // The whole share's random numbers, drawn as one batch draws them: each micro-batch
        // takes its scenes' rows, so the numbers do not depend on how the share is cut.
        // Offsets are drawn after the slot noise; nothing is drawn for decoders that do
        // not sample.
        let (noise, offsets) = match rngs {
            [rng] => (
                self.slot_noise(n, rng)?,
                self.model.ray_offsets(n, batch.rays_per_scene, rng)?,
            ),
            each => {
                let noise = self.model.slot_noise_each(each)?;
                (
                    noise,
                    self.model.ray_offsets_each(batch.rays_per_scene, each)?,
                )
            }
        };
        let parts = micro_batches(n, self.cfg.train.micro_batch_size);
        // Passes on the CPU add their gradients straight into the flat host gradient (the
        // buffer the step hands on anyway), so no per-parameter sum is held beside it.
        let host_sum = crate::device::is_cpu(&self.device) && !keep && parts.len() > 1;
        let mut sum: Vec<Option<Tensor>> = Vec::new();
        let mut flat_sum: Option<Vec<f32>> = None;
        let (mut loss_value, mut forward_kept_bytes) = (0.0, None);
        for scenes in &parts {
            let rows = |t: &Option<Tensor>| -> Result<Option<Tensor>> {
                Ok(match t {
                    Some(t) if parts.len() > 1 => Some(t.narrow(0, scenes.start, scenes.len())?),
                    other => other.clone(),
                })
            };
            // The global batch's mean: each micro-batch's mean weighted by its scenes.
            let weight = (parts.len() > 1).then(|| scenes.len() as f64 / n as f64);
            let mb = MicroBatch {
                scenes: scenes.clone(),
                noise: rows(&noise)?,
                offsets: rows(&offsets)?,
                weight,
            };
            let (loss, grads, kept) = self.micro_step(batch, mb, &mut clock, &probe)?;
            loss_value += loss;
            forward_kept_bytes = forward_kept_bytes.max(kept);
            match (host_sum, &mut flat_sum) {
                (true, None) => flat_sum = Some(self.flatten_host(grads)?),
                (true, Some(flat)) => self.add_into(flat, grads)?,
                (false, _) => sum = accumulate(sum, grads)?,
            }
        }
        let peak_bytes = probe.peak();
        let flat = match flat_sum {
            Some(flat) => Gradient::Host(flat),
            None => self.flatten(sum, keep)?,
        };
        let flatten_s = clock.lap()?;
        // The memory where the meter reads it: what was held before the batch came in, what
        // the forward pass added, the passes' peak above the start and what the flat
        // gradient's making added to it (GiB; where a step's peak lies).
        let gib = |b: Option<u64>| b.map_or(f64::NAN, |b| b as f64 / (1u64 << 30) as f64);
        tracing::debug!(
            forward_s = clock.forward_s,
            backward_s = clock.backward_s,
            flatten_s,
            micro_batches = parts.len(),
            start_gib = gib(probe.held_before()),
            forward_held_gib = gib(forward_kept_bytes),
            passes_peak_gib = gib(peak_bytes),
            with_flatten_peak_gib = gib(probe.peak()),
            "train step gradients"
        );
        Ok(StepGradients {
            loss: loss_value,
            grads: flat,
            samples: n,
            phases: timing.then_some(Phases {
                forward_s: clock.forward_s,
                backward_s: clock.backward_s,
                forward_kept_bytes,
                peak_bytes,
            }),
        })
    }

    /// The forward and backward pass of one micro-batch: its loss (weighted), the
    /// parameters' gradients in [`Params::vars`] order (`None` where the loss does not
    /// reach one), and the bytes its forward pass left held.
    fn micro_step(
        &self,
        batch: &Batch,
        mb: MicroBatch,
        clock: &mut Clock,
        probe: &MemoryProbe,
    ) -> Result<(f64, Vec<Option<Tensor>>, Option<u64>)> {
        let t = BatchTensors::scenes(batch, mb.scenes.clone(), &self.device)?;
        // The forward pass in segments (`osrt_kernels::cut`: encoder, slot attention,
        // decoder), whose backward passes run one after the other, each segment's
        // activations freed before the next: the step's peak is then not every activation
        // beside every gradient at the end of the backward pass. The gradients are the
        // uncut graph's, to the bit.
        let (forward, cuts) = osrt_kernels::with_cuts(self.cfg.train.recompute, || -> Result<_> {
            let slots =
                self.model
                    .encode(&t.images, &t.origins, &t.directions, mb.noise.as_ref())?;
            let out = self.model.decode_with(
                &slots.slots,
                &t.target_origins,
                &t.target_directions,
                mb.offsets.as_ref(),
            )?;
            let mut loss = (&out.rgb - &t.target_rgb)?.sqr()?.mean_all()?;
            if let Some(w) = mb.weight {
                loss = (loss * w)?;
            }
            Ok((slots, out, loss))
        });
        let (slots, out, loss) = forward?;
        clock.forward()?;
        let kept = probe.held();
        let mut grads = loss.backward()?;
        let loss_value = loss.to_scalar::<f32>()? as f64;
        // The last segment's graph (the outputs hold it) goes before the earlier
        // segments' backward passes; the batch goes with it.
        drop((loss, out, slots, t));
        cuts.backward(&mut grads)?;
        // The parameters' gradients, in order, out of candle's store and detached; the rest
        // of it goes: candle also writes gradients for constants (the data, a product's
        // other factor), and a gradient computed from a tracked operand holds that
        // operand's graph.
        let param_grads: Vec<Option<Tensor>> = self
            .params
            .vars()
            .into_iter()
            .map(|(_, var)| grads.remove(var.as_tensor()).map(|g| g.detach()))
            .collect();
        drop(grads);
        clock.backward()?;
        Ok((loss_value, param_grads, kept))
    }

    /// The parameters' gradients (in [`Params::vars`] order, `None` where the loss does
    /// not reach one) as one flat gradient: on the host for the CPU or an all-reduce, on
    /// the device where `keep` is set.
    fn flatten(&self, param_grads: Vec<Option<Tensor>>, keep: bool) -> Result<Gradient> {
        Ok(if crate::device::is_cpu(&self.device) && !keep {
            Gradient::Host(self.flatten_host(param_grads)?)
        } else {
            // One flat tensor on the device; copied to the host only for an all-reduce.
            let mut parts = Vec::new();
            for ((_, var), g) in self.params.vars().into_iter().zip(param_grads) {
                parts.push(match g {
                    Some(g) => g.to_dtype(candle_core::DType::F32)?.flatten_all()?,
                    None => Tensor::zeros(var.elem_count(), candle_core::DType::F32, &self.device)?,
                });
            }
            let flat = Tensor::cat(&parts, 0)?;
            drop(parts);
            if keep {
                Gradient::Device(flat)
            } else {
                Gradient::Host(flat.to_vec1::<f32>()?)
            }
        })
    }

    /// The parameters' gradients as one flat host buffer, each gradient freed once copied.
    fn flatten_host(&self, param_grads: Vec<Option<Tensor>>) -> Result<Vec<f32>> {
        // Room for the all-reduce's control values, so that appending them does not move
        // the buffer.
        let cap = self.num_parameters() + CONTROL_FLOATS;
        let mut flat = Vec::with_capacity(cap);
        for ((_, var), g) in self.params.vars().into_iter().zip(param_grads) {
            match g {
                Some(g) => extend_with(&mut flat, &g)?,
                // A parameter the loss does not reach (e.g. unused init of another mode).
                None => flat.extend(std::iter::repeat_n(0.0, var.elem_count())),
            }
        }
        Ok(flat)
    }

    /// Adds a pass's gradients into a flat host gradient ([`Trainer::flatten_host`]'s
    /// layout), each freed once added: the same sums, in the same order, as adding the
    /// per-parameter tensors.
    fn add_into(&self, flat: &mut [f32], param_grads: Vec<Option<Tensor>>) -> Result<()> {
        let mut at = 0;
        for ((_, var), g) in self.params.vars().into_iter().zip(param_grads) {
            let n = var.elem_count();
            if let Some(g) = g {
                let mut part = Vec::with_capacity(n);
                extend_with(&mut part, &g)?;
                drop(g);
                for (a, b) in flat[at..at + n].iter_mut().zip(part) {
                    *a += b;
                }
            }
            at += n;
        }
        Ok(())
    }

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
            "out of memory on {:?} ({e}) in the optimiser step: {} parameters, whose weights,              AdamW moments and gradient take {state_gib:.2} GiB before the update's              temporaries, did not leave room for it; {}. Lower train.batch_size or              train.rays_per_scene (the step's activations share the device), or train a              smaller model",
            self.device.location(),
            self.num_parameters,
            self.card_memory(),
        )))
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

/// Appends a gradient's values to `flat`: straight from a contiguous f32 CPU tensor's
/// storage, through a copy otherwise.
fn extend_with(flat: &mut Vec<f32>, g: &Tensor) -> candle_core::Result<()> {
    {
        let (storage, layout) = g.storage_and_layout();
        if let (Storage::Cpu(CpuStorage::F32(data)), Some((a, b))) =
            (&*storage, layout.contiguous_offsets())
        {
            flat.extend_from_slice(&data[a..b]);
            return Ok(());
        }
    }
    flat.extend(
        g.flatten_all()?
            .to_dtype(candle_core::DType::F32)?
            .to_vec1::<f32>()?,
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

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
