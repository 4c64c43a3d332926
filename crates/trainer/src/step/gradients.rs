//! The forward and backward passes of a step: its random numbers drawn as one batch draws
//! them, its scenes in micro-batches whose gradients are summed, a device out of memory
//! retried once and then reported with what to change, and the passes timed and their
//! memory measured where asked. Its own file because it is the step's one long pipeline;
//! what it hands on is a flat gradient (`flat`).

use super::flat::HostSum;
use super::{BatchTensors, Gradient, Trainer};
use crate::error::{Result, TrainError};
use candle_core::{Device, Tensor};
use osrt_dataset::Batch;
use osrt_kernels::profile::MemoryMeter;
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

/// Gradients of one (local) batch: by default a host buffer, as the all-reduce sends it.
pub struct StepGradients<G = Vec<f32>> {
    pub loss: f64,
    /// Flat, in [`Params::vars`](osrt_model::Params::vars) order.
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

impl Trainer {
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
        // buffer the step hands on anyway) as their backward passes make them, so no
        // per-parameter sum, and no whole pass's gradients, are held beside it.
        let host_sum = crate::device::is_cpu(&self.device) && !keep && parts.len() > 1;
        let mut sum: Vec<Option<Tensor>> = Vec::new();
        let mut flat_sum =
            host_sum.then(|| HostSum::new(self.params.vars().into_iter().map(|(_, v)| v)));
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
            let (loss, grads, kept) =
                self.micro_step(batch, mb, &mut clock, &probe, flat_sum.as_mut())?;
            loss_value += loss;
            forward_kept_bytes = forward_kept_bytes.max(kept);
            if flat_sum.is_none() {
                sum = accumulate(sum, grads)?;
            }
        }
        let peak_bytes = probe.peak();
        let flat = match flat_sum {
            Some(flat) => Gradient::Host(flat.into_flat()),
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
    /// parameters' gradients in [`Params::vars`](osrt_model::Params::vars) order (`None`
    /// where the loss does not reach one; none where they went into `host_sum`), and the
    /// bytes its forward pass left held.
    fn micro_step(
        &self,
        batch: &Batch,
        mb: MicroBatch,
        clock: &mut Clock,
        probe: &MemoryProbe,
        host_sum: Option<&mut HostSum>,
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
        if let Some(sum) = host_sum {
            cuts.backward_flushing(&mut grads, |g| sum.take(g, false))?;
            sum.take(&mut grads, true)?;
            sum.end_pass();
            drop(grads);
            clock.backward()?;
            return Ok((loss_value, Vec::new(), kept));
        }
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
}
