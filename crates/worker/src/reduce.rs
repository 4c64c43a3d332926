//! The step's reduction carried over the ring ([`osrt_trainer::distributed`] lays out
//! the buffer and reads the sum).

use crate::error::Result;
use osrt_collective::Ring;
use osrt_trainer::distributed::{self, Reduced, Signals};
use osrt_trainer::step::{Gradient, StepGradients};

/// Sums `g` over the ring (`None` = a single worker) as all-reduce number `seq`.
pub async fn reduce(
    ring: Option<&mut Ring>,
    seq: u64,
    rank: usize,
    g: StepGradients<impl Into<Gradient>>,
    signals: Signals,
) -> Result<Reduced> {
    let Some(ring) = ring else {
        return Ok(distributed::alone(rank, g, signals)?);
    };
    let mut buf = distributed::contribution(rank, g, signals)?;
    ring.all_reduce(seq, &mut buf).await?;
    Ok(distributed::reduced_from(buf))
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
