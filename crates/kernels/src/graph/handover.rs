//! How a node built from tensor ops (the attention, convolution and MLP nodes) puts its
//! result into candle's graph: the forward pass runs on detached tensors before the node
//! is applied, and the node's own forward pass returns a copy of that result (the size
//! of the output), once.

use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, Result, Shape, Tensor};
use std::sync::Mutex;

/// A finished forward pass waiting for its node's forward pass.
pub(crate) struct Handover(Mutex<Option<Tensor>>);

impl Handover {
    /// Holds `t` as one whole contiguous buffer (a storage is copied whole, so a view is
    /// copied out first).
    pub(crate) fn new(t: Tensor) -> Result<Self> {
        let l = t.layout();
        let t = match l.is_contiguous() && l.start_offset() == 0 {
            true => t,
            false => {
                crate::ledger::cast_of(t.elem_count(), t.dtype(), t.dtype());
                t.force_contiguous()?
            }
        };
        Ok(Self(Mutex::new(Some(t))))
    }

    fn take(&self, what: &str) -> Result<Tensor> {
        match self.0.lock().unwrap_or_else(|e| e.into_inner()).take() {
            Some(t) => Ok(t),
            None => candle_core::bail!("{what}: forward pass run twice"),
        }
    }

    /// The result for a node's `cpu_fwd`.
    pub(crate) fn cpu(&self, what: &str) -> Result<(CpuStorage, Shape)> {
        let out = self.take(what)?;
        crate::ledger::cast_of(out.elem_count(), out.dtype(), out.dtype());
        let (storage, layout) = out.storage_and_layout();
        match &*storage {
            candle_core::Storage::Cpu(s) => Ok((s.try_clone(layout)?, out.shape().clone())),
            _ => candle_core::bail!("{what}: output on another device"),
        }
    }

    /// The result for a node's `cuda_fwd`.
    #[cfg(feature = "cuda")]
    pub(crate) fn cuda(&self, what: &str) -> Result<(candle_core::CudaStorage, Shape)> {
        let out = self.take(what)?;
        crate::ledger::cast_of(out.elem_count(), out.dtype(), out.dtype());
        let (storage, layout) = out.storage_and_layout();
        match &*storage {
            candle_core::Storage::Cuda(s) => Ok((s.try_clone(layout)?, out.shape().clone())),
            _ => candle_core::bail!("{what}: output on another device"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// A view (permuted, or narrowed away from its storage's start) is handed over as
    /// its own values in order, not as the storage it views; a second forward pass is
    /// an error.
    #[test]
    fn a_view_is_handed_over_as_its_values() {
        let t = Tensor::arange(0f32, 24.0, &Device::Cpu).unwrap();
        let t = t.reshape((2, 3, 4)).unwrap();
        for view in [
            t.permute((2, 0, 1)).unwrap(),
            t.narrow(0, 1, 1).unwrap(),
            t.clone(),
        ] {
            let want = view.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let h = Handover::new(view.clone()).unwrap();
            let (s, shape) = h.cpu("test").unwrap();
            assert_eq!(shape, *view.shape());
            let CpuStorage::F32(got) = s else {
                panic!("f32 in, f32 out")
            };
            assert_eq!(got, want);
            assert!(h.cpu("test").unwrap_err().to_string().contains("run twice"));
        }
    }
}
