//! The step's reduction carried over the ring ([`osrt_trainer::distributed`] lays out
//! the buffer and reads the sum; [`osrt_trainer::staging`] moves a device gradient to the
//! host and back bucket by bucket while the ring runs).

use crate::error::Result;
use osrt_collective::{Ring, Stage};
use osrt_trainer::distributed::{self, Reduced, Signals};
use osrt_trainer::staging::{Staging, Transfer};
use osrt_trainer::{CONTROL_FLOATS, Gradient, StepGradients};

/// Sums `g` over the ring (`None` = a single worker) as all-reduce number `seq`. A
/// gradient on a GPU goes through `staging` (made on first use, kept for the next steps).
pub async fn reduce(
    ring: Option<&mut Ring>,
    staging: &mut Option<Staging>,
    seq: u64,
    rank: usize,
    g: StepGradients<impl Into<Gradient>>,
    signals: Signals,
) -> Result<Reduced> {
    let Some(ring) = ring else {
        return Ok(distributed::alone(rank, g, signals)?);
    };
    let g = StepGradients {
        grads: g.grads.into(),
        loss: g.loss,
        samples: g.samples,
        phases: g.phases,
    };
    let Gradient::Device(grads) = g.grads else {
        let mut buf = distributed::contribution(rank, g, signals)?;
        ring.all_reduce(seq, &mut buf).await?;
        return Ok(distributed::reduced_from(buf));
    };
    let params = grads.dims1().map_err(osrt_trainer::TrainError::from)?;
    let buckets = ring.layout(params + CONTROL_FLOATS).buckets;
    let device = grads.device().clone();
    if !staging
        .as_ref()
        .is_some_and(|s| s.fits(&device, params, &buckets))
    {
        // The old one goes first: its page-locked memory is the size of the gradient.
        *staging = None;
        let n = buckets.len();
        *staging = Some(Staging::new(&device, params, buckets)?);
        tracing::info!(
            params,
            buckets = n,
            device = ?device.location(),
            "the gradient crosses to the ring and back bucket by bucket"
        );
    }
    let staging = staging.as_mut().expect("made above");
    let g = StepGradients {
        grads,
        loss: g.loss,
        samples: g.samples,
        phases: g.phases,
    };
    let mut transfer = staging.begin(rank, g, signals)?;
    let mut buf = transfer.take_buffer();
    ring.all_reduce_staged(seq, &mut buf, &mut Staged(&mut transfer))
        .await?;
    Ok(transfer.finish(buf)?)
}

/// The ring's view of a step's [`Transfer`].
struct Staged<'a, 'b>(&'a mut Transfer<'b>);

impl Stage for Staged<'_, '_> {
    async fn staged(&mut self, bucket: usize) -> Result<(), String> {
        self.0.staged(bucket).await
    }
    fn fill(&mut self, bucket: usize, dst: &mut [f32]) -> Result<(), String> {
        self.0.fill(bucket, dst)
    }
    fn reduced(&mut self, bucket: usize, sums: &[f32]) -> Result<(), String> {
        self.0.reduced(bucket, sums)
    }
}

/// Makes every rank's `flat` equal to rank 0's (the initial weights come from one rank,
/// never from independent seeds): the other ranks contribute zeros to a sum.
pub async fn broadcast_from_rank0(
    ring: Option<&mut Ring>,
    seq: u64,
    rank: usize,
    flat: &mut Vec<f32>,
) -> Result<()> {
    let Some(ring) = ring else { return Ok(()) };
    distributed::zero_unless_rank0(rank, flat);
    ring.all_reduce(seq, flat).await?;
    Ok(())
}
