//! The chunk schedule of one all-reduce: every chunk's place (`ChunkId`, whose order is
//! the order a rank consumes them), the chunks a rank sends first, and the hops it
//! receives in order, each with what it is forwarded as (`Hop`, `receive_schedule`).

use crate::chunk_wire;
use crate::error::CollectiveError;
use crate::layout::{Layout, RingConfig};
use crate::loan::LentBuffer;
use crate::mailbox::Key;
use crate::ring::apply_le;
use bytes::Bytes;
use osrt_proto::v1::{ChunkTag, Phase};
use std::collections::BTreeMap;
use std::ops::Range;
use std::time::Duration;

/// The chunks a rank sends first: its round-0 reduce-scatter segment of every bucket.
pub(crate) fn first_sends(layout: &Layout, rank: usize) -> BTreeMap<ChunkId, Outgoing> {
    let mut ready = BTreeMap::new();
    for b in 0..layout.buckets.len() {
        let seg = layout.segment(b, layout.send_segment(rank, Phase::ReduceScatter, 0));
        for (c, range) in layout.chunks(seg).into_iter().enumerate() {
            ready.insert(
                ChunkId::new(b, Phase::ReduceScatter, 0, c),
                Outgoing::Lend(range),
            );
        }
    }
    ready
}

/// What goes out as a chunk.
pub(crate) enum Outgoing {
    /// A range of the buffer being reduced, lent without a copy.
    Lend(Range<usize>),
    /// Bytes received from the predecessor, passed on as they are.
    Forward(Bytes),
}

/// Bytes of chunks one rank queues at once.
pub(crate) const IN_FLIGHT_BYTES: usize = 8 << 20;

/// A chunk's place in an all-reduce; the derived order (bucket, phase, round, chunk) is
/// the order in which a rank consumes its predecessor's chunks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) struct ChunkId {
    pub(crate) bucket: u32,
    /// 0 = reduce-scatter, 1 = all-gather.
    phase: u8,
    round: u32,
    chunk: u32,
}

impl ChunkId {
    fn new(bucket: usize, phase: Phase, round: usize, chunk: usize) -> Self {
        Self {
            bucket: bucket as u32,
            phase: u8::from(phase == Phase::AllGather),
            round: round as u32,
            chunk: chunk as u32,
        }
    }

    fn phase(&self) -> Phase {
        if self.phase == 0 {
            Phase::ReduceScatter
        } else {
            Phase::AllGather
        }
    }

    pub(crate) fn key(&self, generation: u64, step: u64) -> Key {
        (
            generation,
            step,
            self.bucket,
            self.phase() as i32,
            self.round,
            self.chunk,
        )
    }

    pub(crate) fn tag(&self, cfg: &RingConfig, step: u64) -> ChunkTag {
        ChunkTag {
            job: cfg.job.clone(),
            generation: cfg.generation,
            step,
            bucket: self.bucket,
            phase: self.phase() as i32,
            round: self.round,
            chunk: self.chunk,
            from_rank: cfg.rank as u32,
        }
    }
}

/// One chunk a rank receives: where it goes, and what it is forwarded as (`None` for the
/// last all-gather round, whose chunks are final everywhere).
#[derive(Debug, Clone)]
pub(crate) struct Hop {
    pub(crate) id: ChunkId,
    pub(crate) range: Range<usize>,
    forward: Option<ChunkId>,
}

impl Hop {
    /// The chunk the mailbox handed over for this hop (`Err(())`: none within the
    /// deadline), checked for its length.
    pub(crate) fn check(
        &self,
        data: Result<Result<Bytes, String>, ()>,
        rank: usize,
        world: usize,
        timeout: Duration,
    ) -> Result<Bytes, CollectiveError> {
        let data = match data {
            Ok(Ok(d)) => d,
            Ok(Err(reason)) => return Err(CollectiveError::Peer(reason, rank)),
            Err(()) => {
                return Err(CollectiveError::Timeout {
                    rank,
                    from: (rank + world - 1) % world,
                    bucket: self.id.bucket as usize,
                    phase: self.id.phase(),
                    round: self.id.round as usize,
                    timeout,
                });
            }
        };
        if data.len() != self.range.len() * 4 {
            return Err(CollectiveError::Peer(
                format!(
                    "chunk {} of bucket {} has {} bytes, expected {}",
                    self.id.chunk,
                    self.id.bucket,
                    data.len(),
                    self.range.len() * 4
                ),
                rank,
            ));
        }
        Ok(data)
    }
}

impl Hop {
    /// Adds (reduce-scatter) or writes (all-gather) a received chunk into its range, and
    /// queues what it lets this rank forward.
    pub(crate) async fn take_in(
        &self,
        data: Bytes,
        (shared, call, ready): (
            &mut LentBuffer,
            &mut chunk_wire::ChunkCall,
            &mut BTreeMap<ChunkId, Outgoing>,
        ),
        (rank, timeout): (usize, Duration),
        send_error: &impl Fn(tonic::Status) -> CollectiveError,
    ) -> Result<(), CollectiveError> {
        let add = self.id.phase() == Phase::ReduceScatter;
        // The range was lent out earlier (sent in reduce-scatter round 0, or forwarded
        // after its sum): the successor has long received it, for this chunk depends on
        // it, but the transport must have dropped the loan before the range is written.
        // Should the call end meanwhile, its status is the better error.
        let write = shared.write(self.range.clone(), timeout, |dst| apply_le(dst, &data, add));
        tokio::select! {
            biased;
            status = call.ended() => return Err(send_error(status)),
            written = write => written.map_err(|e| CollectiveError::StillLent {
                rank,
                range: e.0,
                timeout,
            })?,
        }
        if let Some(id) = self.forward {
            // A sum is lent from the buffer; a final segment is passed on as the bytes
            // that brought it.
            let out = if add {
                Outgoing::Lend(self.range.clone())
            } else {
                Outgoing::Forward(data)
            };
            ready.insert(id, out);
        }
        Ok(())
    }
}

/// Every chunk `rank` receives in one all-reduce, in the order it applies them.
pub(crate) fn receive_schedule(layout: &Layout, rank: usize) -> Vec<Hop> {
    let w = layout.world;
    let mut hops = Vec::new();
    for b in 0..layout.buckets.len() {
        for phase in [Phase::ReduceScatter, Phase::AllGather] {
            for round in 0..w - 1 {
                // Received in round r of a phase = sent in the following round, the first
                // all-gather round following the last reduce-scatter round.
                let forward = match (phase, round + 2 == w) {
                    (Phase::ReduceScatter, false) => Some((Phase::ReduceScatter, round + 1)),
                    (Phase::ReduceScatter, true) => Some((Phase::AllGather, 0)),
                    (_, false) => Some((Phase::AllGather, round + 1)),
                    (_, true) => None,
                };
                let seg = layout.segment(b, layout.recv_segment(rank, phase, round));
                for (c, range) in layout.chunks(seg).into_iter().enumerate() {
                    hops.push(Hop {
                        id: ChunkId::new(b, phase, round, c),
                        range,
                        forward: forward.map(|(p, r)| ChunkId::new(b, p, r, c)),
                    });
                }
            }
        }
    }
    hops
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What a rank sends — its first reduce-scatter segments, then every received chunk
    /// it forwards — is, in order, exactly what its successor expects to receive, for
    /// rings of 2 to 5 ranks; and each forward sends the segment the ring algorithm
    /// prescribes for the next round.
    #[test]
    fn forwarded_chunks_are_what_the_successor_receives() {
        for w in 2..=5 {
            let layout = Layout::new(1003, w, 300, 17);
            for rank in 0..w {
                let mut sent: Vec<(ChunkId, Range<usize>)> = Vec::new();
                for b in 0..layout.buckets.len() {
                    let seg = layout.segment(b, layout.send_segment(rank, Phase::ReduceScatter, 0));
                    for (c, r) in layout.chunks(seg).into_iter().enumerate() {
                        sent.push((ChunkId::new(b, Phase::ReduceScatter, 0, c), r));
                    }
                }
                for hop in receive_schedule(&layout, rank) {
                    if let Some(f) = hop.forward {
                        let seg = layout.segment(
                            f.bucket as usize,
                            layout.send_segment(rank, f.phase(), f.round as usize),
                        );
                        assert_eq!(
                            layout.chunks(seg)[f.chunk as usize],
                            hop.range,
                            "w={w} rank={rank} {f:?}"
                        );
                        sent.push((f, hop.range.clone()));
                    }
                }
                sent.sort_by_key(|(id, _)| *id);
                let successor: Vec<_> = receive_schedule(&layout, (rank + 1) % w)
                    .into_iter()
                    .map(|h| (h.id, h.range))
                    .collect();
                assert_eq!(sent, successor, "w={w} rank={rank}");
            }
        }
    }
}
