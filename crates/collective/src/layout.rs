//! Who is on a ring (`RingConfig`) and how a buffer is cut into buckets, segments and
//! chunks (`Layout`): both ends of a connection compute the same cut from the same numbers.

use osrt_proto::MAX_CHUNK_FLOATS;
use osrt_proto::credentials::Credentials;
use osrt_proto::v1::Phase;
use std::ops::Range;
use std::time::Duration;

/// Who is on the ring and how buffers are cut.
#[derive(Debug, Clone)]
pub struct RingConfig {
    pub job: String,
    pub generation: u64,
    /// The number of the generation's first all-reduce ([`Mailbox::set_generation`]).
    ///
    /// [`Mailbox::set_generation`]: crate::Mailbox::set_generation
    pub first_step: u64,
    pub rank: usize,
    /// `http://host:port` of every rank's collective server, in ring order.
    pub peers: Vec<String>,
    pub bucket_floats: usize,
    pub chunk_floats: usize,
    /// Deadline of every RPC and of every wait for a chunk.
    pub timeout: Duration,
    /// The job's shared token, attached to every chunk sent, and TLS for the connection
    /// to the next rank where set (peers are then `https://`).
    pub credentials: Credentials,
}

impl RingConfig {
    pub fn world(&self) -> usize {
        self.peers.len()
    }
}

/// How a buffer of `len` floats is cut; both sides compute it identically.
#[derive(Debug, Clone, PartialEq)]
pub struct Layout {
    pub world: usize,
    pub buckets: Vec<Range<usize>>,
    pub chunk_floats: usize,
}

impl Layout {
    pub fn new(len: usize, world: usize, bucket_floats: usize, chunk_floats: usize) -> Self {
        // Buckets from the end: the last parameters' gradients are ready first in backward.
        let mut buckets = Vec::new();
        let mut end = len;
        while end > 0 {
            let start = end.saturating_sub(bucket_floats.max(1));
            buckets.push(start..end);
            end = start;
        }
        Self {
            world,
            buckets,
            chunk_floats: chunk_floats.clamp(1, MAX_CHUNK_FLOATS),
        }
    }

    /// Range of segment `s` of bucket `b` (absolute indices in the buffer).
    pub fn segment(&self, b: usize, s: usize) -> Range<usize> {
        let r = &self.buckets[b];
        let n = r.len();
        let (base, extra) = (n / self.world, n % self.world);
        let start = r.start + s * base + s.min(extra);
        let len = base + usize::from(s < extra);
        start..start + len
    }

    /// Chunks of a segment.
    pub fn chunks(&self, seg: Range<usize>) -> Vec<Range<usize>> {
        let mut out = Vec::new();
        let mut s = seg.start;
        while s < seg.end {
            let e = (s + self.chunk_floats).min(seg.end);
            out.push(s..e);
            s = e;
        }
        out
    }

    /// Segment a rank *receives* in `phase`, round `round`.
    pub fn recv_segment(&self, rank: usize, phase: Phase, round: usize) -> usize {
        let w = self.world;
        match phase {
            Phase::ReduceScatter => (rank + 2 * w - round - 1) % w,
            _ => (rank + w - round) % w,
        }
    }

    /// Segment a rank *sends* in `phase`, round `round`.
    pub fn send_segment(&self, rank: usize, phase: Phase, round: usize) -> usize {
        let w = self.world;
        match phase {
            Phase::ReduceScatter => (rank + w - round) % w,
            _ => (rank + 1 + w - round) % w,
        }
    }
}
