//! How long an all-reduce's transfer may take: a predecessor that sends each chunk just
//! inside the per-chunk timeout (a straggler) would otherwise hold the ring for `timeout`
//! × chunks.

use crate::mailbox::{Key, Mailbox};
use crate::schedule::Hop;
use crate::{CollectiveError, RingConfig};
use bytes::Bytes;
use std::time::{Duration, Instant};

/// The slowest a predecessor may deliver an all-reduce's chunks once it has sent the
/// first and this rank's own are all staged: a peer that sends one chunk just inside every per-chunk timeout would
/// otherwise hold the ring for `timeout` × chunks. Any real link is orders of magnitude
/// faster; the budget is [`STRAGGLER_TIMEOUTS`] per-chunk timeouts plus the bytes at
/// this rate ([`all_reduce_budget`]).
pub const MIN_RING_BYTES_PER_S: u64 = 1 << 20;
pub const STRAGGLER_TIMEOUTS: u32 = 4;

/// The longest an all-reduce moving `bytes` (each way) may take once under way.
pub fn all_reduce_budget(timeout: Duration, bytes: usize) -> Duration {
    timeout.saturating_mul(STRAGGLER_TIMEOUTS)
        + Duration::from_secs_f64(bytes as f64 / MIN_RING_BYTES_PER_S as f64)
}

/// An all-reduce's budget, counted from the first chunk received once this rank's own
/// buffer is staged: before that, a slow backward pass (this rank's or the
/// predecessor's) is not the ring's to judge. The first chunk may take the per-chunk
/// timeout or the predecessor's grace, whichever is longer; each later one the per-chunk
/// timeout.
pub(crate) struct Budget {
    rank: usize,
    world: usize,
    timeout: Duration,
    first: Duration,
    total: Duration,
    chunks: usize,
    deadline: Option<Instant>,
}

impl Budget {
    /// The budget of receiving the chunks of `schedule` on the ring of `cfg`, the
    /// predecessor allowed `grace` to finish computing.
    pub fn new(cfg: &RingConfig, schedule: &[Hop], grace: Duration) -> Self {
        let bytes = schedule.iter().map(|h| h.range.len() * 4).sum();
        Self {
            rank: cfg.rank,
            world: cfg.world(),
            timeout: cfg.timeout,
            first: cfg.timeout.max(grace),
            total: all_reduce_budget(cfg.timeout, bytes),
            chunks: schedule.len(),
            deadline: None,
        }
    }

    /// The mailbox's next chunk under `key` within the per-chunk timeout and what is left
    /// of the budget (`staging`: this rank's buffer is not all staged yet); the straggler
    /// error once the budget is spent, with the chunks `received` so far.
    pub async fn take(
        &mut self,
        mailbox: &Mailbox,
        key: Key,
        staging: bool,
        received: usize,
    ) -> Result<Result<Result<Bytes, String>, ()>, CollectiveError> {
        let (rank, world) = (self.rank, self.world);
        if !staging && received > 0 && self.deadline.is_none() {
            self.deadline = Some(Instant::now() + self.total);
        }
        let per_chunk = if received == 0 {
            self.first
        } else {
            self.timeout
        };
        let wait = self.deadline.map_or(per_chunk, |d| {
            per_chunk.min(d.saturating_duration_since(Instant::now()))
        });
        let data = mailbox.take(key, wait).await;
        match self.deadline {
            Some(d) if data.is_err() && Instant::now() >= d => Err(CollectiveError::Straggler {
                rank,
                from: (rank + world - 1) % world,
                received,
                expected: self.chunks,
                budget: self.total,
            }),
            _ => Ok(data),
        }
    }
}
