//! The flat gradient: every parameter's gradient in one f32 buffer in
//! [`Params::vars`](osrt_model::Params::vars) order, on the host or on the device, and
//! how a pass's per-parameter gradients become one. Its own file because the all-reduce,
//! the staging and the optimiser all take this one layout, whatever the passes that made
//! it.

use super::Trainer;
use crate::error::Result;
use crate::optim::GradSummary;
use candle_core::backprop::GradStore;
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
                Some(g) => {
                    let at = flat.len();
                    flat.resize(at + var.elem_count(), 0.0);
                    write_into(&mut flat[at..], &g, false)?;
                }
                // A parameter the loss does not reach (e.g. unused init of another mode).
                None => flat.extend(std::iter::repeat_n(0.0, var.elem_count())),
            }
        }
        Ok(flat)
    }
}

/// The flat host gradient of a step's passes (micro-batches on the CPU), filled while
/// each pass's backward pass runs: a parameter's gradient is taken out of candle's store
/// once the segment that makes it has ended (`osrt_kernels::Cuts::backward_flushing`) and
/// copied (first pass) or added (later passes) into its place, so the store never holds a
/// whole pass's gradients beside the running sum. The sums are those of adding each
/// pass's whole per-parameter gradients, to the bit: a parameter whose gradient the first
/// pass found in more than one segment is taken only at the end of each later pass, its
/// segments' parts summed in the store as before.
pub(super) struct HostSum {
    flat: Vec<f32>,
    /// Each parameter in [`Params::vars`](osrt_model::Params::vars) order, with its offset.
    params: Vec<(candle_core::Var, usize)>,
    /// Whether a pass has written the parameter's place yet (else it holds zeros).
    written: Vec<bool>,
    /// Whether the first pass found its gradient in more than one segment.
    shared: Vec<bool>,
    /// Whether the current pass has taken the parameter's gradient yet.
    taken: Vec<bool>,
    first_pass: bool,
}

impl HostSum {
    /// A sum of zeros over `vars` (the parameters, in their flat order).
    pub(super) fn new(vars: impl IntoIterator<Item = candle_core::Var>) -> Self {
        let mut params = Vec::new();
        let mut at = 0;
        for var in vars {
            let n = var.elem_count();
            params.push((var, at));
            at += n;
        }
        // Room for the all-reduce's control values, as [`Trainer::flatten_host`] leaves.
        let mut flat = Vec::with_capacity(at + CONTROL_FLOATS);
        flat.resize(at, 0.0);
        let n = params.len();
        Self {
            flat,
            params,
            written: vec![false; n],
            shared: vec![false; n],
            taken: vec![false; n],
            first_pass: true,
        }
    }

    /// Takes the finished gradients out of `grads` (after a segment of a pass's backward
    /// pass; `end`: after its last, when every gradient left is finished) into the sum.
    pub(super) fn take(&mut self, grads: &mut GradStore, end: bool) -> candle_core::Result<()> {
        for (i, (var, at)) in self.params.iter().enumerate() {
            if !(self.first_pass || end || !self.shared[i]) {
                continue;
            }
            let Some(g) = grads.remove(var.as_tensor()) else {
                continue;
            };
            if self.first_pass && self.taken[i] {
                self.shared[i] = true;
            }
            self.taken[i] = true;
            let place = &mut self.flat[*at..*at + var.elem_count()];
            write_into(place, &g, self.written[i])?;
            self.written[i] = true;
        }
        Ok(())
    }

    /// Marks a pass as ended (every gradient of it taken).
    pub(super) fn end_pass(&mut self) {
        self.first_pass = false;
        self.taken.fill(false);
    }

    /// The summed flat gradient (zeros where no pass reached a parameter).
    pub(super) fn into_flat(self) -> Vec<f32> {
        self.flat
    }
}

/// Copies (or with `add`, adds) a gradient's values into `place`: straight from a
/// contiguous f32 CPU tensor's storage, through a copy otherwise.
fn write_into(place: &mut [f32], g: &Tensor, add: bool) -> candle_core::Result<()> {
    let write = |place: &mut [f32], values: &[f32]| match add {
        true => place.iter_mut().zip(values).for_each(|(a, b)| *a += b),
        false => place.copy_from_slice(values),
    };
    {
        let (storage, layout) = g.storage_and_layout();
        if let (Storage::Cpu(CpuStorage::F32(data)), Some((a, b))) =
            (&*storage, layout.contiguous_offsets())
        {
            write(place, &data[a..b]);
            return Ok(());
        }
    }
    let values = g
        .flatten_all()?
        .to_dtype(candle_core::DType::F32)?
        .to_vec1::<f32>()?;
    write(place, &values);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    /// A parameter whose gradient the first pass finds in two segments is taken at the
    /// end of each later pass, its parts summed first (the sum of whole per-pass
    /// gradients, to the bit: taking each part as it comes would round `1 + 4e-8 + 4e-8`
    /// down to 1); the others are taken as their segment ends; unreached ones stay zero.
    #[test]
    fn a_parameter_of_two_segments_is_summed_as_whole_passes_sum_it() {
        let var = |v: &[f32]| Var::from_slice(v, v.len(), &Device::Cpu).unwrap();
        let (shared, single, unreached) = (var(&[0.0]), var(&[0.0, 0.0]), var(&[0.0]));
        let t = |v: &[f32]| Tensor::from_slice(v, v.len(), &Device::Cpu).unwrap();
        let mut sum = HostSum::new([shared.clone(), single.clone(), unreached.clone()]);
        // An empty store, as a backward pass leaves one.
        let mut store = t(&[0.0]).sum_all().unwrap().backward().unwrap();
        let passes: [[f32; 2]; 2] = [[0.5, 0.5], [4e-8, 4e-8]];
        for (k, parts) in passes.iter().enumerate() {
            // Segment A: both parameters; segment B adds to the shared one, as candle's
            // store sums what is still in it.
            store.insert(shared.as_tensor(), t(&[parts[0]]));
            store.insert(single.as_tensor(), t(&[1.0, k as f32]));
            sum.take(&mut store, false).unwrap();
            assert!(store.get(single.as_tensor()).is_none(), "taken as it ends");
            let held = store.remove(shared.as_tensor());
            let part = t(&[parts[1]]);
            let both = match held {
                Some(a) => (a + part).unwrap(),
                None => part,
            };
            store.insert(shared.as_tensor(), both);
            sum.take(&mut store, false).unwrap();
            sum.take(&mut store, true).unwrap();
            sum.end_pass();
            assert!(store.get(shared.as_tensor()).is_none());
        }
        let flat = sum.into_flat();
        assert_eq!(flat.len(), 4);
        assert!(flat.capacity() >= 4 + CONTROL_FLOATS);
        let whole = 1.0f32 + (4e-8f32 + 4e-8f32);
        assert_ne!(whole, 1.0);
        assert_eq!(flat[0].to_bits(), whole.to_bits());
        assert_eq!(&flat[1..], &[2.0, 1.0, 0.0]);
    }
}
