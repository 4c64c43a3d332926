//! Page-locked host memory and the device buffer the reduced gradient lands in: the
//! staging's CUDA side, its one unsafe allocation kept apart from the bucket logic (built
//! with the `cuda` feature only).

use crate::error::Result;
use candle_core::cuda_backend::cudarc::driver::{
    CudaEvent, CudaSlice, CudaStream, PinnedHostSlice,
};
use candle_core::op::BackpropOp;
use candle_core::{CudaDevice, CudaStorage, Storage, Tensor};
use std::ops::Range;

/// Page-locked floats and the event of the last copy queued into or out of them.
///
/// cudarc's own event on a `PinnedHostSlice` is recorded only where it manages
/// several streams with event tracking on; osrt turns tracking off
/// (`device::pool::configure`), so the piece records its copies itself.
pub struct Pinned {
    /// At least one float (an empty piece is allocated with one).
    host: PinnedHostSlice<f32>,
    len: usize,
    device: CudaDevice,
    /// Completes with the last copy queued on the device's stream that reads or
    /// writes `host` (none recorded: complete).
    copied: CudaEvent,
}

impl Drop for Pinned {
    fn drop(&mut self) {
        // The memory is freed after this: no copy may still use it.
        let _ = self.copied.synchronize();
    }
}

impl Pinned {
    pub fn new(device: &CudaDevice, len: usize) -> Result<Self> {
        let ctx = device.cuda_stream().context().clone();
        // Ordinary cached memory (no write-combining): the ring reads it on the host.
        // SAFETY: the floats are unset, and every read waits for the copy that
        // writes them (`floats` synchronises on the slice's event).
        let mut host = unsafe { ctx.alloc_pinned_with_flags::<f32>(len.max(1), 0) }
            .map_err(candle_core::Error::wrap)?;
        host.as_mut_slice()
            .map_err(candle_core::Error::wrap)?
            .fill(0.0);
        let copied = ctx.new_event(None).map_err(candle_core::Error::wrap)?;
        Ok(Self {
            host,
            len,
            device: device.clone(),
            copied,
        })
    }

    /// The floats, once the last copy queued into or out of them has completed.
    pub fn floats(&self) -> Result<&[f32]> {
        self.copied
            .synchronize()
            .map_err(candle_core::Error::wrap)?;
        let len = self.len;
        Ok(&self.host.as_slice().map_err(candle_core::Error::wrap)?[..len])
    }

    /// As [`Pinned::floats`], to write.
    pub fn floats_mut(&mut self) -> Result<&mut [f32]> {
        self.copied
            .synchronize()
            .map_err(candle_core::Error::wrap)?;
        let len = self.len;
        Ok(&mut self.host.as_mut_slice().map_err(candle_core::Error::wrap)?[..len])
    }

    /// Marks the copy just queued on `stream` as the one to wait for.
    fn record(&self, stream: &CudaStream) -> Result<()> {
        self.copied
            .record(stream)
            .map_err(candle_core::Error::wrap)?;
        Ok(())
    }
}

/// Queues the copy of `grads[range]` into `piece` on the device's stream.
pub fn download(grads: &Tensor, range: Range<usize>, piece: &mut Pinned) -> Result<()> {
    let (storage, layout) = grads.storage_and_layout();
    let (Storage::Cuda(s), Some((a, _))) = (&*storage, layout.contiguous_offsets()) else {
        return Err(crate::TrainError::Device(
            "staging: the gradient is not a contiguous CUDA tensor".into(),
        ));
    };
    if range.is_empty() {
        return Ok(());
    }
    let src = s
        .as_cuda_slice::<f32>()?
        .slice(a + range.start..a + range.end);
    let stream = piece.device.cuda_stream();
    stream
        .memcpy_dtoh(&src, &mut piece.host)
        .map_err(candle_core::Error::wrap)?;
    piece.record(&stream)
}

pub struct DeviceBuffer {
    slice: CudaSlice<f32>,
    device: CudaDevice,
}

impl DeviceBuffer {
    pub fn new(device: &CudaDevice, len: usize) -> Result<Self> {
        Ok(Self {
            slice: device.alloc_zeros::<f32>(len)?,
            device: device.clone(),
        })
    }

    /// Queues the copy of `piece` into `range` on the device's stream (the one stream
    /// every kernel runs on, so the optimiser's reads of the buffer follow it).
    pub fn upload(&mut self, range: Range<usize>, piece: &Pinned) -> Result<()> {
        let stream = self.device.cuda_stream();
        let mut dst = self.slice.slice_mut(range);
        stream
            .memcpy_htod(&piece.host, &mut dst)
            .map_err(candle_core::Error::wrap)?;
        // The host must not write the piece again before this copy has read it.
        piece.record(&stream)
    }

    pub fn into_tensor(self) -> Result<Tensor> {
        let n = self.slice.len();
        let storage = CudaStorage::wrap_cuda_slice(self.slice, self.device);
        Ok(Tensor::from_storage(
            Storage::Cuda(storage),
            n,
            BackpropOp::none(),
            false,
        ))
    }
}
