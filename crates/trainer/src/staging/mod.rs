//! A device gradient on its way through a ring all-reduce of two or more workers: to the
//! host once and back once per step, one ring bucket at a time, so that copying a bucket
//! overlaps the ring's work on the buckets before it.
//!
//! Per step ([`Staging::begin`] → [`Transfer`] → [`Transfer::finish`]):
//! 1. one device reduction gives the gradient's finiteness (the control values need it
//!    before the first bucket goes out); a thread queues every bucket's copy to the host
//!    on the device's stream, into page-locked memory on a GPU (the copies then run at
//!    the bus's speed and without staging through a driver buffer), and hands each
//!    bucket over as its copy completes, in the ring's order;
//! 2. the ring fills its buffer from each bucket as it needs it, weighting it by this
//!    rank's scene count on the way ([`Transfer::fill`]);
//! 3. as soon as a bucket's sums are final, they are divided by the global scene count
//!    into the same page-locked memory and queued for the device ([`Transfer::reduced`]),
//!    while the ring still works on the next buckets.
//!
//! The arithmetic is [`crate::distributed::contribution`]'s and
//! [`crate::distributed::reduced_from`]'s, float for float: the reduced gradient has the
//! same bits as through the host path. The page-locked memory, the ring's buffer and the
//! host copies of each bucket are kept from step to step.
//!
//! The CUDA side (page-locked pieces, the device buffer the reduced gradient lands in)
//! is in `cuda`.

#[cfg(feature = "cuda")]
#[allow(unsafe_code)]
mod cuda;

use crate::distributed::{self, Reduced, Signals};
use crate::error::{Result, TrainError};
use crate::optim::GradSummary;
use crate::step::{CONTROL_FLOATS, Gradient, StepGradients};
use candle_core::{Device, Tensor};
use std::ops::Range;

/// The host memory of one bucket's gradient: page-locked on a GPU.
enum Piece {
    Plain(Vec<f32>),
    #[cfg(feature = "cuda")]
    Pinned(cuda::Pinned),
}

impl Piece {
    fn new(device: &Device, len: usize) -> Result<Self> {
        match device {
            #[cfg(feature = "cuda")]
            Device::Cuda(d) => Ok(Self::Pinned(cuda::Pinned::new(d, len)?)),
            _ => Ok(Self::Plain(vec![0.0; len])),
        }
    }

    /// The floats, once every copy queued into or out of them has completed.
    fn floats(&self) -> Result<&[f32]> {
        match self {
            Self::Plain(v) => Ok(v),
            #[cfg(feature = "cuda")]
            Self::Pinned(p) => p.floats(),
        }
    }

    fn floats_mut(&mut self) -> Result<&mut [f32]> {
        match self {
            Self::Plain(v) => Ok(v),
            #[cfg(feature = "cuda")]
            Self::Pinned(p) => p.floats_mut(),
        }
    }
}

/// Where the reduced gradient goes: a device buffer of the gradient's length.
enum Target {
    Host(Vec<f32>),
    #[cfg(feature = "cuda")]
    Cuda(cuda::DeviceBuffer),
}

impl Target {
    fn new(device: &Device, len: usize) -> Result<Self> {
        match device {
            #[cfg(feature = "cuda")]
            Device::Cuda(d) => Ok(Self::Cuda(cuda::DeviceBuffer::new(d, len)?)),
            Device::Cpu => Ok(Self::Host(vec![0.0; len])),
            other => Err(TrainError::Device(format!(
                "staging a gradient for the all-reduce: {other:?} is not supported"
            ))),
        }
    }

    /// Queues `piece` into `range` (on a GPU: a copy on the device's stream, which the
    /// optimiser's kernels follow).
    fn upload(&mut self, range: Range<usize>, piece: &Piece) -> Result<()> {
        match (self, piece) {
            (Self::Host(t), p) => t[range].copy_from_slice(p.floats()?),
            #[cfg(feature = "cuda")]
            (Self::Cuda(t), Piece::Pinned(p)) => t.upload(range, p)?,
            #[cfg(feature = "cuda")]
            (Self::Cuda(_), Piece::Plain(_)) => {
                unreachable!("a GPU's pieces are page-locked")
            }
        }
        Ok(())
    }

    /// The reduced gradient: on the GPU a tensor there, on the CPU the host buffer (which
    /// the CPU's optimiser takes without another copy).
    fn into_gradient(self) -> Result<Gradient> {
        match self {
            Self::Host(t) => Ok(Gradient::Host(t)),
            #[cfg(feature = "cuda")]
            Self::Cuda(t) => Ok(Gradient::Device(t.into_tensor()?)),
        }
    }
}

/// One worker's staging memory for a gradient of a fixed length and ring layout, kept
/// from step to step.
pub struct Staging {
    device: Device,
    params: usize,
    /// The ring's buckets over the buffer (`params + CONTROL_FLOATS` floats), in ring
    /// order.
    buckets: Vec<Range<usize>>,
    /// Each bucket's gradient floats (its range less the control values); `None` where
    /// a failed step lost one (it is allocated again).
    pieces: Vec<Option<Piece>>,
    /// The ring's buffer.
    buffer: Vec<f32>,
}

impl Staging {
    /// Staging for a gradient of `params` floats on `device`, all-reduced as a buffer of
    /// `params + CONTROL_FLOATS` floats cut into `buckets` (the ring's layout).
    pub fn new(device: &Device, params: usize, buckets: Vec<Range<usize>>) -> Result<Self> {
        let len = params + CONTROL_FLOATS;
        let mut covered = 0;
        for r in &buckets {
            covered += r.len();
            if r.end > len {
                return Err(TrainError::Device(format!(
                    "staging: bucket {r:?} beyond the buffer's {len} floats"
                )));
            }
        }
        if covered != len {
            return Err(TrainError::Device(format!(
                "staging: the buckets cover {covered} of the buffer's {len} floats"
            )));
        }
        let mut me = Self {
            device: device.clone(),
            params,
            buckets,
            pieces: Vec::new(),
            buffer: vec![0.0; len],
        };
        me.pieces = (0..me.buckets.len()).map(|_| None).collect();
        me.allocate()?;
        Ok(me)
    }

    /// Whether this staging serves a gradient of `params` floats cut into `buckets`.
    pub fn fits(&self, device: &Device, params: usize, buckets: &[Range<usize>]) -> bool {
        self.device.same_device(device) && self.params == params && self.buckets == buckets
    }

    fn grads_of(&self, b: usize) -> Range<usize> {
        let r = &self.buckets[b];
        r.start.min(self.params)..r.end.min(self.params)
    }

    fn allocate(&mut self) -> Result<()> {
        for b in 0..self.buckets.len() {
            if self.pieces[b].is_none() {
                let len = self.grads_of(b).len();
                self.pieces[b] = Some(Piece::new(&self.device, len)?);
            }
        }
        Ok(())
    }

    /// Starts the step's transfer of rank `rank`'s gradient `g` (on the device): its
    /// buckets head for the host in ring order.
    pub fn begin(
        &mut self,
        rank: usize,
        g: StepGradients<Tensor>,
        signals: Signals,
    ) -> Result<Transfer<'_>> {
        if g.grads.dims1()? != self.params {
            return Err(TrainError::Device(format!(
                "staging: a gradient of {} floats for staging of {}",
                g.grads.dims1()?,
                self.params
            )));
        }
        self.allocate()?;
        let summary = match with_cpu_floats(&g.grads, GradSummary::of) {
            Some(s) => s,
            None => GradSummary::of_tensor(&g.grads)?,
        };
        let bad = !g.loss.is_finite() || !summary.finite();
        let control = distributed::control(rank, g.loss, g.samples, signals, bad);
        let target = Target::new(&self.device, self.params)?;
        let jobs: Vec<(usize, Range<usize>, Piece)> = (0..self.buckets.len())
            .map(|b| {
                let piece = self.pieces[b].take().expect("allocated above");
                (b, self.grads_of(b), piece)
            })
            .collect();
        let (tx, arrived) = tokio::sync::mpsc::channel(jobs.len().max(1));
        let grads = g.grads;
        let downloads = std::thread::Builder::new()
            .name("osrt-staging".into())
            .spawn(move || download(&grads, jobs, &tx))
            .map_err(|e| TrainError::Device(format!("staging: cannot start a thread: {e}")))?;
        Ok(Transfer {
            n: g.samples as f32,
            control,
            sums: [f32::NAN; CONTROL_FLOATS],
            arrived,
            downloads: Some(downloads),
            target,
            staging: self,
        })
    }
}

impl Staging {
    /// The staged round trip of a gradient alone (a ring of one): to the host bucket by
    /// bucket and back, weighted and divided by one scene, as each worker of a ring pays
    /// it beside the ring's own time (`osrt bench model`'s `median_gradient_transfer_s`).
    pub fn round_trip(&mut self, g: &Tensor) -> Result<Gradient> {
        let step = StepGradients {
            loss: 0.0,
            grads: g.clone(),
            samples: 1,
            phases: None,
        };
        let mut t = self.begin(0, step, Signals::default())?;
        let mut buf = t.take_buffer();
        let failed = |e: String| TrainError::Device(format!("staging: {e}"));
        // Every bucket down first: the copies run in the stream's order anyway, and
        // joining the copying thread blocks no async runtime (this runs inside one in
        // `osrt bench model`, where a blocking receive would panic).
        t.arrive_all().map_err(failed)?;
        for b in 0..t.staging.buckets.len() {
            let range = t.staging.buckets[b].clone();
            t.fill(b, &mut buf[range.clone()]).map_err(failed)?;
            t.reduced(b, &buf[range]).map_err(failed)?;
        }
        Ok(t.finish(buf)?.grads)
    }
}

/// The ring's cut of a buffer of `len` floats into buckets of at most `bucket_floats`,
/// from its end (`osrt_collective::Layout::new`'s, which a test holds this to).
pub fn ring_buckets(len: usize, bucket_floats: usize) -> Vec<Range<usize>> {
    let mut buckets = Vec::new();
    let mut end = len;
    while end > 0 {
        let start = end.saturating_sub(bucket_floats.max(1));
        buckets.push(start..end);
        end = start;
    }
    buckets
}

/// Copies each bucket's floats of `grads` into its piece and hands each over once its
/// copy has completed, in bucket order; on a GPU all copies are queued first.
fn download(
    grads: &Tensor,
    jobs: Vec<(usize, Range<usize>, Piece)>,
    tx: &tokio::sync::mpsc::Sender<Result<(usize, Piece), String>>,
) {
    let send = |item| {
        // A receiver that is gone is a transfer that ended: nothing left to do.
        let _ = tx.blocking_send(item);
    };
    // Page-locked pieces whose copies are queued on the device's stream.
    #[cfg_attr(not(feature = "cuda"), allow(unused_mut))]
    let mut queued: Vec<(usize, Piece)> = Vec::with_capacity(jobs.len());
    for (b, range, mut piece) in jobs {
        if let Err(e) = copy_out(grads, range, &mut piece) {
            send(Err(format!("copying bucket {b} to the host: {e}")));
            return;
        }
        match piece {
            // Copied already: the ring may start on it while the next one is copied.
            Piece::Plain(_) => send(Ok((b, piece))),
            #[cfg(feature = "cuda")]
            Piece::Pinned(_) => queued.push((b, piece)),
        }
    }
    for (b, piece) in queued {
        match piece.floats() {
            Ok(_) => send(Ok((b, piece))),
            Err(e) => {
                send(Err(format!("copying bucket {b} to the host: {e}")));
                return;
            }
        }
    }
}

/// Queues the copy of `grads[range]` into `piece` (done at once on the CPU).
fn copy_out(grads: &Tensor, range: Range<usize>, piece: &mut Piece) -> Result<()> {
    match piece {
        #[cfg(feature = "cuda")]
        Piece::Pinned(p) => cuda::download(grads, range, p),
        Piece::Plain(v) => {
            if with_cpu_floats(grads, |g| v.copy_from_slice(&g[range.clone()])).is_none() {
                let part = grads.narrow(0, range.start, range.len())?;
                v.copy_from_slice(&part.to_vec1::<f32>()?);
            }
            Ok(())
        }
    }
}

/// `f` of a contiguous f32 CPU tensor's floats, read in place; `None` for another tensor.
fn with_cpu_floats<R>(t: &Tensor, f: impl FnOnce(&[f32]) -> R) -> Option<R> {
    let (storage, layout) = t.storage_and_layout();
    match (&*storage, layout.contiguous_offsets()) {
        (candle_core::Storage::Cpu(candle_core::CpuStorage::F32(data)), Some((a, b))) => {
            Some(f(&data[a..b]))
        }
        _ => None,
    }
}

/// The control values' part of a bucket `range` of the ring's buffer, as indices into
/// the control values (after `params` gradient floats).
fn control_part(range: &Range<usize>, params: usize) -> Range<usize> {
    range.start.max(params) - params..range.end.max(params) - params
}

/// One step's gradient between the device and the ring: the ring's stage
/// (`osrt_collective::Stage` in the worker) and then the reduced step.
pub struct Transfer<'a> {
    staging: &'a mut Staging,
    /// This rank's scene count, the gradient's weight in the sum.
    n: f32,
    control: [f32; CONTROL_FLOATS],
    /// The summed control values, as their buckets are reduced.
    sums: [f32; CONTROL_FLOATS],
    arrived: tokio::sync::mpsc::Receiver<Result<(usize, Piece), String>>,
    downloads: Option<std::thread::JoinHandle<()>>,
    target: Target,
}

impl Transfer<'_> {
    /// The ring's buffer (its contents are the ring's to fill); back with
    /// [`Transfer::finish`].
    pub fn take_buffer(&mut self) -> Vec<f32> {
        std::mem::take(&mut self.staging.buffer)
    }

    /// Resolves once bucket `b` is on the host. Cancel-safe: a bucket that arrives is
    /// kept, whether or not the caller still waits.
    pub async fn staged(&mut self, b: usize) -> Result<(), String> {
        while self.staging.pieces[b].is_none() {
            match self.arrived.recv().await {
                Some(Ok((i, piece))) => self.staging.pieces[i] = Some(piece),
                Some(Err(e)) => return Err(e),
                None => return Err("the copies to the host stopped".into()),
            }
        }
        Ok(())
    }

    /// Waits for every bucket's copy to the host (by joining the copying thread, not by a
    /// blocking receive, so that it may run on an async runtime's thread).
    fn arrive_all(&mut self) -> Result<(), String> {
        if let Some(t) = self.downloads.take() {
            t.join()
                .map_err(|_| "the thread copying to the host panicked")?;
        }
        let mut failure = None;
        while let Ok(item) = self.arrived.try_recv() {
            match item {
                Ok((i, piece)) => self.staging.pieces[i] = Some(piece),
                Err(e) => failure = Some(e),
            }
        }
        match failure {
            Some(e) => Err(e),
            None if self.staging.pieces.iter().any(Option::is_none) => {
                Err("the copies to the host stopped".into())
            }
            None => Ok(()),
        }
    }

    /// Writes bucket `b` of this rank's contribution into `dst` (its range of the ring's
    /// buffer): the gradient weighted by the scene count, and the control values where
    /// the bucket holds them.
    pub fn fill(&mut self, b: usize, dst: &mut [f32]) -> Result<(), String> {
        let s = &*self.staging;
        let (range, grads) = (s.buckets[b].clone(), s.grads_of(b));
        let piece = s.pieces[b]
            .as_ref()
            .ok_or("bucket filled before it arrived")?;
        let src = piece.floats().map_err(|e| e.to_string())?;
        let n = self.n;
        let (g, c) = dst.split_at_mut(grads.len());
        g.iter_mut().zip(src).for_each(|(d, x)| *d = x * n);
        c.copy_from_slice(&self.control[control_part(&range, s.params)]);
        Ok(())
    }

    /// Bucket `b`'s final sums (its range of the ring's buffer): the control values kept,
    /// the gradient divided by the global scene count and queued for the device.
    pub fn reduced(&mut self, b: usize, sums: &[f32]) -> Result<(), String> {
        let s = &mut *self.staging;
        let (range, grads) = (s.buckets[b].clone(), s.grads_of(b));
        let (g, c) = sums.split_at(grads.len());
        self.sums[control_part(&range, s.params)].copy_from_slice(c);
        if grads.is_empty() {
            return Ok(());
        }
        // The ring's order reduces the buffer's end, where the control values are, first.
        let total = self.sums[0];
        let piece = s.pieces[b]
            .as_mut()
            .ok_or("bucket reduced before it arrived")?;
        let dst = piece.floats_mut().map_err(|e| e.to_string())?;
        dst.iter_mut().zip(g).for_each(|(d, x)| *d = x / total);
        self.target
            .upload(grads, piece)
            .map_err(|e| format!("copying bucket {b} to the device: {e}"))
    }

    /// The reduced step, with the gradient on the GPU (on the CPU: in a host buffer);
    /// `buffer` is the ring's, back for the next step.
    pub fn finish(mut self, buffer: Vec<f32>) -> Result<Reduced> {
        self.staging.buffer = buffer;
        self.join();
        if self.staging.pieces.iter().any(Option::is_none) {
            return Err(TrainError::Device(
                "staging: the all-reduce ended before every bucket came back".into(),
            ));
        }
        let target = std::mem::replace(&mut self.target, Target::Host(Vec::new()));
        let grads = target.into_gradient()?;
        Ok(distributed::reduced_with(grads, &self.sums))
    }

    /// Waits for the copying thread, keeping the buckets it still hands over.
    fn join(&mut self) {
        if let Some(t) = self.downloads.take() {
            // Ends once its last bucket is sent (the channel holds them all).
            let _ = t.join();
        }
        while let Ok(Ok((i, piece))) = self.arrived.try_recv() {
            self.staging.pieces[i] = Some(piece);
        }
    }
}

impl Drop for Transfer<'_> {
    fn drop(&mut self) {
        // An all-reduce that failed: the copies still under way finish into memory the
        // next step reuses.
        self.join();
        if self.staging.buffer.is_empty() {
            self.staging.buffer = vec![0.0; self.staging.params + CONTROL_FLOATS];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// A gradient alone (weight 1, one scene) comes back with its own bits, extreme
    /// values included, through buckets of every kind (control values only, control and
    /// gradient, gradient only), step after step with the same staging.
    #[test]
    fn a_round_trip_alone_gives_back_the_gradients_bits() {
        let mut v: Vec<f32> = (0..1001).map(|i| (i as f32 * 0.37).sin() * 1e3).collect();
        v[..8].copy_from_slice(&[
            f32::MAX,
            -f32::MAX,
            f32::MIN_POSITIVE,
            1e-45,
            -0.0,
            f32::INFINITY,
            f32::NEG_INFINITY,
            3.0e38,
        ]);
        let g = Tensor::from_vec(v.clone(), v.len(), &Device::Cpu).unwrap();
        for bucket in [4, 100, 5000] {
            let buckets = ring_buckets(v.len() + CONTROL_FLOATS, bucket);
            let mut staging = Staging::new(&Device::Cpu, v.len(), buckets).unwrap();
            for _ in 0..2 {
                let back = staging.round_trip(&g).unwrap().into_host().unwrap();
                assert_eq!(bits(&back), bits(&v), "buckets of {bucket}");
            }
        }
    }

    /// Buckets that do not cover the buffer exactly once, or a gradient of another
    /// length, are refused with what was expected.
    #[test]
    fn mismatched_buckets_and_gradients_are_refused() {
        let e = Staging::new(&Device::Cpu, 10, vec![5..10, 0..5])
            .err()
            .unwrap();
        assert!(e.to_string().contains("cover 10 of the buffer's 17"), "{e}");
        let e = Staging::new(&Device::Cpu, 10, vec![8..20, 0..8])
            .err()
            .unwrap();
        assert!(e.to_string().contains("beyond the buffer's 17"), "{e}");
        let mut s = Staging::new(&Device::Cpu, 10, ring_buckets(17, 5)).unwrap();
        assert!(s.fits(&Device::Cpu, 10, &ring_buckets(17, 5)));
        assert!(!s.fits(&Device::Cpu, 10, &ring_buckets(17, 4)));
        let g = Tensor::zeros(11, candle_core::DType::F32, &Device::Cpu).unwrap();
        let e = s.round_trip(&g).err().unwrap();
        assert!(
            e.to_string()
                .contains("a gradient of 11 floats for staging of 10"),
            "{e}"
        );
    }
}
