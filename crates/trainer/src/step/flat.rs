//! The flat gradient: every parameter's gradient in one f32 buffer in
//! [`Params::vars`](osrt_model::Params::vars) order, on the host or on the device, and
//! how a pass's per-parameter gradients become one. Its own file because the all-reduce,
//! the staging and the optimiser all take this one layout, whatever the passes that made
//! it.

use super::Trainer;
use crate::error::Result;
use crate::optim::GradSummary;
use candle_core::{CpuStorage, Storage, Tensor};

/// A flat f32 gradient in [`Params::vars`](osrt_model::Params::vars) order: in host
/// memory (what the all-reduce sends and the host optimiser reads), or one tensor on the
/// device that computed it (a single worker on a GPU: nothing to sum with anyone, so it
/// never leaves the device).
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

impl Trainer {
    /// The parameters' gradients (in [`Params::vars`](osrt_model::Params::vars) order,
    /// `None` where the loss does not reach one) as one flat gradient: on the host for the
    /// CPU or an all-reduce, on the device where `keep` is set.
    pub(super) fn flatten(&self, param_grads: Vec<Option<Tensor>>, keep: bool) -> Result<Gradient> {
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
    pub(super) fn flatten_host(&self, param_grads: Vec<Option<Tensor>>) -> Result<Vec<f32>> {
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
    pub(super) fn add_into(
        &self,
        flat: &mut [f32],
        param_grads: Vec<Option<Tensor>>,
    ) -> Result<()> {
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
