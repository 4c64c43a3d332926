//! Chunks received by this rank's Collective server, checked and held until the local
//! all-reduce takes them.

use crate::Layout;
use bytes::Bytes;
use osrt_proto::MAX_CHUNK_FLOATS;
use osrt_proto::v1::{Chunk, ChunkTag, Phase};
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::Notify;
use tonic::Status;

/// `(generation, step, bucket, phase, round, chunk)`
pub(crate) type Key = (u64, u64, u32, i32, u32, u32);

/// What is wrong with a chunk addressed to `rank` at step `min_step`, if anything.
fn validate(
    layout: &Layout,
    rank: usize,
    min_step: u64,
    tag: &ChunkTag,
    phase: Phase,
    bytes: usize,
) -> Option<String> {
    let w = layout.world;
    let expected_from = (rank + w - 1) % w;
    if tag.from_rank as usize != expected_from {
        return Some(format!(
            "chunk from rank {}, expected the ring predecessor {expected_from}",
            tag.from_rank
        ));
    }
    if tag.round as usize + 1 >= w.max(2)
        || (tag.step == min_step && tag.bucket as usize >= layout.buckets.len())
    {
        return Some(format!(
            "unknown bucket {} or round {}",
            tag.bucket, tag.round
        ));
    }
    if tag.step == min_step {
        let seg = layout.segment(
            tag.bucket as usize,
            layout.recv_segment(rank, phase, tag.round as usize),
        );
        let want = layout
            .chunks(seg)
            .get(tag.chunk as usize)
            .map(|c| c.len() * 4);
        if want != Some(bytes) {
            return Some(format!(
                "malformed chunk {} of bucket {}: {bytes} bytes, expected {}",
                tag.chunk,
                tag.bucket,
                want.map_or("no such chunk".to_string(), |w| w.to_string())
            ));
        }
    }
    None
}

#[derive(Default)]
struct MailboxState {
    job: String,
    generation: u64,
    rank: usize,
    min_step: u64,
    layout: Option<Layout>,
    chunks: HashMap<Key, Bytes>,
    /// A malformed chunk aimed at this rank fails the round that waits for it.
    failure: Option<String>,
    /// Set by the worker when the coordinator moved on: every wait of this generation
    /// fails at once instead of running into its deadline.
    aborted: Option<String>,
    /// Bytes of the chunks kept before they could be checked (a peer already in the next
    /// generation, or in this one before this rank's first step, or one step ahead). A
    /// payload holds at most twice its length (`chunk_wire` copies one that is a small
    /// slice of its HTTP/2 frame), so the memory they hold is at most twice this.
    early_bytes: usize,
    /// Bytes of the last gradient this mailbox saw reduced, and the most chunks of it
    /// this rank receives in one all-reduce (together they bound `early_bytes`).
    gradient_bytes: usize,
    gradient_chunks: usize,
}

/// Bound of unchecked early chunks before any gradient size is known: the round-0 share
/// of a 2-worker ring at 67 M parameters (the `paper` preset's is 41 M floats).
const EARLY_BYTES_DEFAULT: usize = 256 << 20;

/// What an early chunk costs beside its payload (its key, its `Bytes` handle, its slot in
/// the map), counted against the bound: chunks of a few bytes, or none, cannot pile up
/// past it in numbers.
const EARLY_ENTRY_COST: usize = 128;

impl MailboxState {
    fn early_limit(&self) -> usize {
        if self.gradient_bytes == 0 {
            EARLY_BYTES_DEFAULT
        } else {
            // A peer sends at most its share of one step before it needs this rank's.
            self.gradient_bytes
                + (MAX_CHUNK_FLOATS * 4)
                + EARLY_ENTRY_COST * (self.gradient_chunks + 1)
        }
    }

    /// Whether a kept chunk could not be checked on arrival.
    fn is_early(&self, k: &Key) -> bool {
        k.0 > self.generation || self.layout.is_none() || k.1 > self.min_step
    }

    /// Recounts the early chunks after the generation or step moved.
    fn recount_early(&mut self) {
        let early: Vec<(&Key, &Bytes)> = self
            .chunks
            .iter()
            .filter(|(k, _)| self.is_early(k))
            .collect();
        self.early_bytes = early.iter().map(|(_, b)| b.len() + EARLY_ENTRY_COST).sum();
    }
}

/// Chunks received by this rank's server, waiting for the local all-reduce.
#[derive(Default)]
pub struct Mailbox {
    state: Mutex<MailboxState>,
    notify: Notify,
}

impl Mailbox {
    pub fn new(job: &str) -> Arc<Self> {
        let m = Arc::new(Self::default());
        m.state.lock().expect("mailbox").job = job.to_string();
        m
    }

    /// The job this mailbox accepts chunks of (learnt at registration).
    pub fn set_job(&self, job: &str) {
        self.state.lock().expect("mailbox").job = job.to_string();
    }

    /// Starts a new generation (membership changed): older traffic becomes stale.
    ///
    /// `first_step` is the number of the generation's first all-reduce (0 for the
    /// weights' broadcast of a fresh job, `s + 1` for the gradient of a job resumed at
    /// step `s`): before this rank reaches it, a peer can only have sent chunks of it or
    /// of the one after, so anything else kept for this generation is dropped.
    pub fn set_generation(&self, generation: u64, rank: usize, first_step: u64) {
        let mut s = self.state.lock().expect("mailbox");
        s.generation = generation;
        s.rank = rank;
        // Keep chunks a faster peer already sent for this generation.
        let first = first_step..=first_step.saturating_add(1);
        s.chunks
            .retain(|k, _| k.0 > generation || (k.0 == generation && first.contains(&k.1)));
        s.failure = None;
        s.aborted = None;
        // A new generation restarts from a checkpoint: its steps may be lower than the
        // last generation's.
        s.min_step = first_step;
        s.layout = None;
        s.recount_early();
    }

    /// Fails the current and every later wait of this generation with `reason`.
    pub fn abort(&self, reason: &str) {
        self.state.lock().expect("mailbox").aborted = Some(reason.to_string());
        self.notify.notify_waiters();
    }

    pub(crate) fn begin_step(&self, step: u64, layout: Layout) {
        let mut s = self.state.lock().expect("mailbox");
        s.min_step = step;
        s.gradient_bytes = layout.buckets.iter().map(|b| b.len() * 4).sum();
        // Per bucket, 2 (W − 1) rounds of one segment, each in chunks of `chunk_floats`.
        let (w, per) = (layout.world.max(1), layout.chunk_floats.max(1));
        s.gradient_chunks = layout
            .buckets
            .iter()
            .map(|b| 2 * (w - 1) * (b.len().div_ceil(w * per) + 1))
            .sum();
        s.layout = Some(layout);
        let generation = s.generation;
        s.chunks.retain(|k, _| k.0 > generation || k.1 >= step);
        s.failure = None;
        s.recount_early();
    }

    /// Keeps a chunk that cannot be checked yet, within the bounds of what a live peer
    /// sends ahead of this rank. Chunks of several steps may wait at once: a live peer
    /// sends those of one only, but which one is not known before this rank gets there
    /// (a chunk of the next generation names a step nobody can check yet), and refusing
    /// the others would let one bogus chunk shut the real ones out.
    fn keep_early(s: &mut MailboxState, key: Key, data: Bytes) -> Result<(), Status> {
        let limit = s.early_limit();
        let cost = data.len() + EARLY_ENTRY_COST;
        if s.early_bytes + cost > limit {
            return Err(Status::resource_exhausted(format!(
                "{} bytes of early chunks would exceed {limit}",
                s.early_bytes + cost
            )));
        }
        s.early_bytes += cost;
        if let Some(old) = s.chunks.insert(key, data) {
            s.early_bytes -= old.len() + EARLY_ENTRY_COST;
        }
        Ok(())
    }

    pub(crate) fn accept(&self, chunk: Chunk) -> Result<(), Status> {
        let tag = chunk
            .tag
            .ok_or_else(|| Status::invalid_argument("chunk without a tag"))?;
        let mut s = self.state.lock().expect("mailbox");
        if tag.job != s.job {
            return Err(Status::permission_denied(format!(
                "chunk of job `{}`, this is job `{}`",
                tag.job, s.job
            )));
        }
        if tag.generation < s.generation {
            return Err(Status::failed_precondition(format!(
                "stale chunk: generation {}, current generation {}",
                tag.generation, s.generation
            )));
        }
        let key = (
            tag.generation,
            tag.step,
            tag.bucket,
            tag.phase,
            tag.round,
            tag.chunk,
        );
        if tag.generation > s.generation + 1 {
            return Err(Status::failed_precondition(format!(
                "chunk of generation {}, this rank is in generation {}: a peer is at most one ahead",
                tag.generation, s.generation
            )));
        }
        if tag.generation > s.generation {
            // A peer that joined the next generation first: keep it, bounded; the length
            // is checked when the chunk is used.
            Self::keep_early(&mut s, key, chunk.data)?;
            self.notify.notify_waiters();
            return Ok(());
        }
        if tag.step < s.min_step {
            return Err(Status::failed_precondition(format!(
                "stale chunk: step {}, current step {}",
                tag.step, s.min_step
            )));
        }
        let phase = Phase::try_from(tag.phase)
            .map_err(|_| Status::invalid_argument(format!("unknown phase {}", tag.phase)))?;
        if phase == Phase::Unspecified {
            return Err(Status::invalid_argument("chunk phase unspecified"));
        }
        if tag.step > s.min_step.saturating_add(1) {
            // Refused, without failing the round that waits: one chunk from too far
            // ahead must not shut the real ones out.
            return Err(Status::failed_precondition(format!(
                "chunk of step {}, this rank is at step {}: a peer is at most one step ahead",
                tag.step, s.min_step
            )));
        }
        let Some(layout) = s.layout.clone() else {
            // The local worker has not reached its first step of the generation: keep
            // it, bounded; validate on use.
            Self::keep_early(&mut s, key, chunk.data)?;
            self.notify.notify_waiters();
            return Ok(());
        };
        let (rank, min_step) = (s.rank, s.min_step);
        if let Some(msg) = validate(&layout, rank, min_step, &tag, phase, chunk.data.len()) {
            s.failure = Some(msg.clone());
            self.notify.notify_waiters();
            return Err(Status::invalid_argument(msg));
        }
        if tag.step > min_step {
            // The next all-reduce may have another length (the weights' broadcast comes
            // before the first gradient's): its chunks are checked when used, and bounded.
            Self::keep_early(&mut s, key, chunk.data)?;
        } else {
            s.chunks.insert(key, chunk.data);
        }
        self.notify.notify_waiters();
        Ok(())
    }

    pub(crate) async fn take(
        &self,
        key: Key,
        timeout: Duration,
    ) -> Result<Result<Bytes, String>, ()> {
        let deadline = crate::loan::deadline(timeout);
        loop {
            // Register as a waiter *before* looking, or a notification that lands between
            // the look and the wait is lost (notify_waiters only wakes registered waiters).
            let notified = self.notify.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            {
                let mut s = self.state.lock().expect("mailbox");
                if let Some(a) = &s.aborted {
                    return Ok(Err(a.clone()));
                }
                if let Some(f) = s.failure.take() {
                    return Ok(Err(f));
                }
                if let Some(b) = s.chunks.remove(&key) {
                    return Ok(Ok(b));
                }
            }
            if tokio::time::timeout_at(deadline, notified).await.is_err() {
                return Err(());
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// What can happen to a mailbox: the worker's own moves and chunks from anyone.
    #[derive(Debug, Clone)]
    enum Event {
        Generation {
            generation: u64,
            rank: usize,
            first: u64,
        },
        Step {
            step: u64,
            len: usize,
        },
        Chunk {
            tag: ChunkTag,
            bytes: usize,
        },
    }

    fn event() -> impl Strategy<Value = Event> {
        let small = || prop_oneof![0u64..4, Just(u64::MAX), any::<u64>()];
        prop_oneof![
            (0u64..4, 0usize..3, small()).prop_map(|(generation, rank, first)| {
                Event::Generation {
                    generation,
                    rank,
                    first,
                }
            }),
            (small(), 1usize..5000).prop_map(|(step, len)| Event::Step { step, len }),
            (
                (0u64..5, small(), 0u32..3, -1i32..4),
                (
                    0u32..3,
                    0u32..6,
                    0u32..4,
                    prop_oneof![Just("job"), Just("other")]
                ),
                prop_oneof![0usize..64, Just(4000), Just(300_000)],
            )
                .prop_map(
                    |((generation, step, bucket, phase), (round, chunk, from_rank, job), bytes)| {
                        Event::Chunk {
                            tag: ChunkTag {
                                job: job.into(),
                                generation,
                                step,
                                bucket,
                                phase,
                                round,
                                chunk,
                                from_rank,
                            },
                            bytes,
                        }
                    }
                ),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig { failure_persistence: None, ..ProptestConfig::default() })]

        /// Any sequence of generations, steps and chunks (of any tag, from anyone): no
        /// panic, the bytes counted as early are exactly the early chunks', and no
        /// accepted chunk takes them past the bound.
        #[test]
        fn any_traffic_keeps_the_early_bound(events in prop::collection::vec(event(), 1..40)) {
            let mailbox = Mailbox::new("job");
            for e in events {
                match e {
                    Event::Generation { generation, rank, first } => {
                        mailbox.set_generation(generation, rank, first);
                    }
                    Event::Step { step, len } => mailbox.begin_step(step, Layout::new(len, 3, 1000, 256)),
                    Event::Chunk { tag, bytes } => {
                        let before = mailbox.state.lock().unwrap().early_bytes;
                        let data = Bytes::from(vec![0u8; bytes]);
                        let kept = mailbox.accept(Chunk { tag: Some(tag), data }).is_ok();
                        let s = mailbox.state.lock().unwrap();
                        // What an accepted chunk adds stays within the bound (a later,
                        // smaller gradient may lower the bound below what is held).
                        if kept && s.early_bytes > before {
                            prop_assert!(
                                s.early_bytes <= s.early_limit(),
                                "{} > {}",
                                s.early_bytes,
                                s.early_limit()
                            );
                        }
                    }
                }
                let mut s = mailbox.state.lock().unwrap();
                let counted = s.early_bytes;
                s.recount_early();
                prop_assert_eq!(counted, s.early_bytes);
            }
        }
    }
}
