//! Ring all-reduce of the flat gradient buffer over gRPC (the `Collective` service).
//!
//! The buffer is cut into **buckets** from its end (reverse parameter order, at most
//! `bucket_floats` each); each bucket into `world` **segments**; each segment into
//! **chunks** of at most `chunk_floats` (≤ 1 MiB of little-endian f32). Per bucket:
//!
//! - *reduce-scatter*, rounds `r = 0 .. world−2`: rank `i` sends segment `(i − r) mod W`
//!   to rank `i + 1` and adds the segment `(i − r − 1) mod W` it receives from `i − 1`;
//!   afterwards rank `i` holds the complete sum of segment `(i + 1) mod W`.
//! - *all-gather*, rounds `r = 0 .. world−2`: rank `i` sends segment `(i + 1 − r) mod W`
//!   and copies the segment `(i − r) mod W` it receives.
//!
//! Every segment is summed exactly once, in ring order starting at its first sender, and
//! then copied byte for byte: **all replicas end with bit-identical buffers**.
//!
//! Buckets are also the unit of staging ([`Ring::all_reduce_staged`]): a buffer whose
//! floats arrive bucket by bucket (a GPU's gradient copied to the host) is sent as each
//! bucket arrives, and each bucket's sums are handed on as soon as they are final.
//!
//! Every chunk is tagged `(job, generation, step, bucket, phase, round, chunk, from_rank)`;
//! the receiving server refuses another job's chunks, stale generations and steps, a
//! sender that is not its ring predecessor, an unknown bucket and a wrong length. Every RPC
//! and every wait has a deadline, so a dead peer fails the round in seconds.

mod budget;
pub mod chunk_wire;
mod loan;
mod mailbox;
mod stage;

use crate::chunk_wire::PushChunkServer;
use crate::loan::LentBuffer;
use crate::mailbox::Key;
pub use crate::mailbox::Mailbox;
pub use crate::stage::Stage;
use crate::stage::{Fill, Whole};
use bytes::Bytes;
use osrt_proto::auth::{CheckToken, Token};
use osrt_proto::tls::Tls;
use osrt_proto::v1::{ChunkTag, Phase};
use std::collections::BTreeMap;
use std::ops::Range;
use std::sync::Arc;
use std::time::Duration;
use thiserror::Error;
use tokio::time::timeout;
use tonic::Status;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Endpoint};

use budget::Budget;
pub use budget::{MIN_RING_BYTES_PER_S, STRAGGLER_TIMEOUTS, all_reduce_budget};
pub use osrt_proto::{KEEP_ALIVE_INTERVAL, KEEP_ALIVE_TIMEOUT, MAX_CHUNK_FLOATS};

/// HTTP/2 flow-control window of collective connections (several chunks in flight).
const WINDOW_BYTES: u32 = 16 << 20;

/// HTTP/2 frame size both ends advertise: a whole chunk fits one DATA frame instead of 64
/// frames of the default 16 KiB, each with its own header, poll and flow-control update.
const FRAME_BYTES: u32 = (MAX_CHUNK_FLOATS * 4 + 4096) as u32;

#[derive(Debug, Error)]
pub enum CollectiveError {
    #[error("rank {rank}: sending to rank {to} failed: {status}")]
    Send {
        rank: usize,
        to: usize,
        status: Status,
    },
    #[error(
        "rank {rank}: no chunk from rank {from} within {timeout:?} (bucket {bucket}, {phase:?} round {round}): peer dead or slow"
    )]
    Timeout {
        rank: usize,
        from: usize,
        bucket: usize,
        phase: Phase,
        round: usize,
        timeout: Duration,
    },
    #[error(
        "rank {rank}: rank {from} sent {received} of {expected} chunks in {budget:?}, the most an all-reduce of this size may take ({STRAGGLER_TIMEOUTS} timeouts and {MIN_RING_BYTES_PER_S} bytes/s): peer too slow"
    )]
    Straggler {
        rank: usize,
        from: usize,
        received: usize,
        expected: usize,
        budget: Duration,
    },
    #[error("rank {rank}: round failed: {0}", rank = .1)]
    Peer(String, usize),
    #[error(
        "rank {rank}: floats {range:?} were still queued in the transport after {timeout:?}, so they could not be reduced"
    )]
    StillLent {
        rank: usize,
        range: Range<usize>,
        timeout: Duration,
    },
    #[error("rank {rank}: staging bucket {bucket} failed: {reason}")]
    Stage {
        rank: usize,
        bucket: usize,
        reason: String,
    },
    #[error("cannot connect to {addr}: {reason}")]
    Connect { addr: String, reason: String },
    #[error("collective configuration: {0}")]
    Config(String),
}

/// Who is on the ring and how buffers are cut.
#[derive(Debug, Clone)]
pub struct RingConfig {
    pub job: String,
    pub generation: u64,
    /// The number of the generation's first all-reduce ([`Mailbox::set_generation`]).
    pub first_step: u64,
    pub rank: usize,
    /// `http://host:port` of every rank's collective server, in ring order.
    pub peers: Vec<String>,
    pub bucket_floats: usize,
    pub chunk_floats: usize,
    /// Deadline of every RPC and of every wait for a chunk.
    pub timeout: Duration,
    /// The job's shared token, attached to every chunk sent.
    pub token: Token,
    /// TLS for the connection to the next rank (peers are then `https://`).
    pub tls: Option<Tls>,
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

/// One rank's side of the ring.
pub struct Ring {
    cfg: RingConfig,
    mailbox: Arc<Mailbox>,
    /// The connection to the next rank.
    next: Channel,
    /// `authorization` of every chunk sent.
    auth: MetadataValue<Ascii>,
    /// The injected fault (`fault-injection` feature only): rank and all-reduce.
    fault: Option<(usize, u64)>,
    /// How long the predecessor may still be computing when an all-reduce starts
    /// ([`Ring::set_peer_grace`]).
    peer_grace: Duration,
}

/// Adds (`add`) or copies the little-endian floats in `src` into `dst`
/// (`src.len() == 4 · dst.len()`).
fn apply_le(dst: &mut [f32], src: &[u8], add: bool) {
    // tonic hands out payloads at arbitrary byte offsets: read aligned ones as floats
    // directly (the loops vectorise), others byte-wise.
    match bytemuck::try_cast_slice::<u8, f32>(src) {
        Ok(v) if cfg!(target_endian = "little") => {
            if add {
                dst.iter_mut().zip(v).for_each(|(d, x)| *d += x);
            } else {
                dst.copy_from_slice(v);
            }
        }
        _ => {
            let v = src
                .chunks_exact(4)
                .map(|s| f32::from_le_bytes([s[0], s[1], s[2], s[3]]));
            if add {
                dst.iter_mut().zip(v).for_each(|(d, x)| *d += x);
            } else {
                dst.iter_mut().zip(v).for_each(|(d, x)| *d = x);
            }
        }
    }
}

/// Test hook, compiled in only with the `fault-injection` feature (the workspace's tests
/// turn it on; builds of the binary do not): `OSRT_FAULT_MALFORMED_CHUNK=RANK:SEQ` makes
/// rank RANK send a chunk one float short in all-reduce SEQ of generation 1, so tests can
/// prove that a malformed chunk fails the round and the job goes on.
#[cfg(feature = "fault-injection")]
pub const FAULT_ENV: &str = "OSRT_FAULT_MALFORMED_CHUNK";

#[cfg(feature = "fault-injection")]
fn fault_injection() -> Option<(usize, u64)> {
    let v = std::env::var(FAULT_ENV).ok()?;
    let (r, s) = v.split_once(':')?;
    Some((r.parse().ok()?, s.parse().ok()?))
}

#[cfg(not(feature = "fault-injection"))]
fn fault_injection() -> Option<(usize, u64)> {
    None
}

impl Ring {
    /// Connects lazily to the next rank; `mailbox` is this rank's server's.
    pub fn new(cfg: RingConfig, mailbox: Arc<Mailbox>) -> Result<Self, CollectiveError> {
        let w = cfg.world();
        if cfg.rank >= w {
            return Err(CollectiveError::Config(format!(
                "rank {} outside a ring of {w}",
                cfg.rank
            )));
        }
        let addr = cfg.peers[(cfg.rank + 1) % w].clone();
        let connect_err = |e: tonic::transport::Error| CollectiveError::Connect {
            addr: addr.clone(),
            reason: e.to_string(),
        };
        let mut endpoint = Endpoint::from_shared(addr.clone()).map_err(connect_err)?;
        if let Some(tls) = &cfg.tls {
            endpoint = endpoint.tls_config(tls.client()).map_err(connect_err)?;
        }
        let endpoint = endpoint
            .connect_timeout(cfg.timeout)
            // No channel-wide request timeout: a `PushChunks` call lasts as long as its
            // all-reduce, and carries its own deadline (`chunk_wire::open_stream`).
            // HTTP/2's default 64 KiB windows throttle 1 MiB chunks to a crawl.
            .initial_stream_window_size(WINDOW_BYTES)
            .initial_connection_window_size(WINDOW_BYTES)
            .max_frame_size(FRAME_BYTES)
            // A successor whose host vanished without closing the connection (half-open)
            // stops answering pings: the call ends with an error instead of waiting.
            .http2_keep_alive_interval(KEEP_ALIVE_INTERVAL)
            .keep_alive_timeout(KEEP_ALIVE_TIMEOUT)
            .keep_alive_while_idle(true)
            .tcp_nodelay(true);
        mailbox.set_generation(cfg.generation, cfg.rank, cfg.first_step);
        Ok(Self {
            auth: cfg.token.header(),
            cfg,
            mailbox,
            next: endpoint.connect_lazy(),
            fault: fault_injection(),
            peer_grace: Duration::ZERO,
        })
    }

    /// How long the predecessor may still be computing its share when this rank starts
    /// the next all-reduces: the wait for its first chunk is this or the per-chunk
    /// timeout, whichever is longer (a worker sets it from its own step's time). A dead
    /// predecessor is still noticed at once: its connection ends, or the coordinator ends
    /// the generation.
    pub fn set_peer_grace(&mut self, grace: Duration) {
        self.peer_grace = grace;
    }

    pub fn layout(&self, len: usize) -> Layout {
        Layout::new(
            len,
            self.cfg.world(),
            self.cfg.bucket_floats,
            self.cfg.chunk_floats,
        )
    }

    /// Sums `buf` over all ranks in place; every rank ends with identical bytes.
    ///
    /// Chunk by chunk, not round by round: what a rank sends in ring round `r + 1` is
    /// exactly the segment it received (and reduced) in round `r` — across the phase
    /// boundary too — so each received chunk is forwarded as soon as it is applied, while
    /// it is still in cache, and no rank waits for a whole round to drain before the next
    /// one starts. All of one all-reduce's chunks to the successor travel as the messages
    /// of one `PushChunks` call, in the order the successor consumes them (bucket, phase,
    /// round, chunk), at most [`Ring::in_flight`] queued at a time; receives are applied
    /// in that same fixed order, so the arithmetic, and with it every bit, is the same as
    /// a round-by-round ring.
    ///
    /// No float is copied to be sent: the buffer moves into a [`LentBuffer`] for the
    /// all-reduce, reduce-scatter chunks go out as loans of its ranges, and all-gather
    /// chunks are forwarded as the very bytes received. `buf` is taken by `&mut Vec` for
    /// that move; it is back, reduced, when this returns `Ok`. After an error its contents
    /// are unspecified, and if the future is dropped unfinished it is left empty.
    pub async fn all_reduce(
        &mut self,
        step: u64,
        buf: &mut Vec<f32>,
    ) -> Result<(), CollectiveError> {
        if self.cfg.world() == 1 {
            return Ok(());
        }
        self.run(step, buf, None::<&mut Whole>).await
    }

    /// [`Ring::all_reduce`] of a buffer that `stage` fills bucket by bucket as the ring
    /// needs each one (`buf` only has to have the right length), telling `stage` each
    /// bucket's sums as soon as they are final. A rank sends or takes in a bucket's
    /// chunks only once it filled the bucket, so the arithmetic and every bit are those
    /// of [`Ring::all_reduce`] of the filled buffer; what changes is that filling one
    /// bucket overlaps the ring's work on the others.
    pub async fn all_reduce_staged(
        &mut self,
        step: u64,
        buf: &mut Vec<f32>,
        stage: &mut impl Stage,
    ) -> Result<(), CollectiveError> {
        if self.cfg.world() == 1 {
            return stage::alone(self.cfg.rank, &self.layout(buf.len()), buf, stage).await;
        }
        self.run(step, buf, Some(stage)).await
    }

    async fn run(
        &mut self,
        step: u64,
        buf: &mut Vec<f32>,
        stage: Option<&mut impl Stage>,
    ) -> Result<(), CollectiveError> {
        let mut shared = LentBuffer::new(std::mem::take(buf));
        let result = self.ring_all_reduce(step, &mut shared, stage).await;
        // One line per all-reduce: `tests/cluster.rs` counts them per optimiser step.
        tracing::debug!(
            rank = self.cfg.rank,
            seq = step,
            floats = shared.len(),
            ok = result.is_ok(),
            "all-reduce"
        );
        // After success the successor has taken every chunk, so the transport lets go of
        // the loans at once; after a failure they may sit in a dead connection's queue,
        // and a copy now beats waiting for it.
        let wait = if result.is_ok() {
            self.cfg.timeout
        } else {
            Duration::ZERO
        };
        *buf = shared.reclaim(wait).await;
        result
    }

    async fn ring_all_reduce(
        &mut self,
        step: u64,
        shared: &mut LentBuffer,
        stage: Option<&mut impl Stage>,
    ) -> Result<(), CollectiveError> {
        let w = self.cfg.world();
        let layout = self.layout(shared.len());
        let mut fill = Fill::new(stage, &layout, self.cfg.rank, self.cfg.timeout);
        self.mailbox.begin_step(step, layout.clone());
        let rank = self.cfg.rank;
        let send_error = |status| CollectiveError::Send {
            rank,
            to: (rank + 1) % w,
            status,
        };
        let inject = self.fault == Some((rank, step)) && self.cfg.generation == 1;
        let schedule = receive_schedule(&layout, rank);
        // Sends that may go out now, by the order the successor consumes them.
        let mut ready = first_sends(&layout, rank);
        let mut budget = Budget::new(&self.cfg, &schedule, self.peer_grace);
        let (sender, mut call) = self.open_call(schedule.len()).map_err(send_error)?;
        let mut first = true;
        let cfg = &self.cfg;
        let mut send =
            |shared: &LentBuffer, permit: chunk_wire::ChunkPermit, id: ChunkId, out: Outgoing| {
                let mut data = match out {
                    Outgoing::Lend(range) => shared.lend(range),
                    Outgoing::Forward(bytes) => bytes,
                };
                if inject && std::mem::take(&mut first) {
                    data.truncate(data.len().saturating_sub(4));
                }
                permit.send(&id.tag(cfg, step), data);
            };
        let mut received = 0;
        loop {
            // Queue what is ready while there is room, without waiting.
            while let Some(entry) = ready.first_entry() {
                if !fill.has(entry.key().bucket as usize) {
                    break;
                }
                let Some(permit) = sender.try_reserve() else {
                    break;
                };
                let (id, out) = entry.remove_entry();
                send(shared, permit, id, out);
            }
            let hop = schedule.get(received);
            if hop.is_none() && ready.is_empty() {
                break;
            }
            // Wait for whichever comes first: room to queue the next ready chunk (a chunk
            // the ring downstream may be waiting for), or the next chunk to receive. The
            // first failure ends the all-reduce: a refused chunk or a dead successor ends
            // the call, a dead predecessor fails the receive at its deadline, a successor
            // that takes nothing fails the send at its deadline.
            let key = hop.map_or_else(Key::default, |h| h.id.key(self.cfg.generation, step));
            let can_send = ready
                .first_key_value()
                .is_some_and(|(id, _)| fill.has(id.bucket as usize));
            let can_receive = hop.is_some_and(|h| fill.has(h.id.bucket as usize));
            let staging = fill.pending();
            tokio::select! {
                biased;
                status = call.ended() => return Err(send_error(status)),
                // The next bucket as soon as it is there: its first chunks can then go
                // out while this rank waits on the ring.
                staged = fill.staged(), if fill.pending() => fill.fill(staged, shared).await?,
                permit = timeout(self.cfg.timeout, sender.reserve()), if can_send => {
                    let permit = match permit {
                        Ok(Ok(p)) => p,
                        Ok(Err(_)) => {
                            return Err(send_error(call.status_within(self.cfg.timeout).await));
                        }
                        Err(_) => return Err(send_error(stalled(self.cfg.timeout))),
                    };
                    let (id, out) = ready.pop_first().expect("ready is not empty");
                    send(shared, permit, id, out);
                }
                data = budget.take(&self.mailbox, key, staging, received), if can_receive => {
                    let hop = hop.expect("enabled only with a chunk to receive");
                    let data = hop.check(data?, rank, w, self.cfg.timeout)?;
                    let to = (&mut *shared, &mut call, &mut ready);
                    hop.take_in(data, to, (rank, self.cfg.timeout), &send_error).await?;
                    received += 1;
                    // A bucket's last chunk in: all its segments are final on this rank.
                    let b = hop.id.bucket as usize;
                    if schedule.get(received).is_none_or(|h| h.id.bucket as usize != b) {
                        fill.reduced(b, shared)?;
                    }
                }
            }
        }
        // Every chunk is queued and every expected one received; the successor
        // acknowledges the call once it has taken the last one.
        call.finish(sender, self.cfg.timeout)
            .await
            .map_err(send_error)
    }

    /// The all-reduce's one call to the successor, which receives `chunks` chunks from
    /// this rank (as many as this rank receives).
    fn open_call(
        &self,
        chunks: usize,
    ) -> Result<(chunk_wire::ChunkSender, chunk_wire::ChunkCall), Status> {
        // The call's deadline allows each chunk the per-chunk timeout (staging may
        // overlap a long backward pass); a dead peer is noticed much sooner, by the
        // ring's waits, and a slow one by the receiver's budget (`all_reduce_budget`).
        let chunks = u32::try_from(chunks + 1).unwrap_or(u32::MAX);
        let deadline = self.cfg.timeout.saturating_mul(chunks);
        chunk_wire::open_stream(self.next.clone(), &self.auth, deadline, self.in_flight())
    }

    /// Chunks one rank queues for its successor beyond what HTTP/2 flow control lets
    /// through: 8 MiB worth (half the HTTP/2 window), at least 2.
    fn in_flight(&self) -> usize {
        (IN_FLIGHT_BYTES / (self.cfg.chunk_floats.clamp(1, MAX_CHUNK_FLOATS) * 4)).clamp(2, 64)
    }
}

/// The chunks a rank sends first: its round-0 reduce-scatter segment of every bucket.
fn first_sends(layout: &Layout, rank: usize) -> BTreeMap<ChunkId, Outgoing> {
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
enum Outgoing {
    /// A range of the buffer being reduced, lent without a copy.
    Lend(Range<usize>),
    /// Bytes received from the predecessor, passed on as they are.
    Forward(Bytes),
}

/// Why a send waited in vain: the successor took nothing for `timeout`.
fn stalled(timeout: Duration) -> Status {
    Status::deadline_exceeded(format!("the successor took no chunk within {timeout:?}"))
}

/// Bytes of chunks one rank queues at once.
const IN_FLIGHT_BYTES: usize = 8 << 20;

/// A chunk's place in an all-reduce; the derived order (bucket, phase, round, chunk) is
/// the order in which a rank consumes its predecessor's chunks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
struct ChunkId {
    bucket: u32,
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

    fn key(&self, generation: u64, step: u64) -> Key {
        (
            generation,
            step,
            self.bucket,
            self.phase() as i32,
            self.round,
            self.chunk,
        )
    }

    fn tag(&self, cfg: &RingConfig, step: u64) -> ChunkTag {
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
struct Hop {
    id: ChunkId,
    range: Range<usize>,
    forward: Option<ChunkId>,
}

impl Hop {
    /// The chunk the mailbox handed over for this hop (`Err(())`: none within the
    /// deadline), checked for its length.
    fn check(
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
    async fn take_in(
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
fn receive_schedule(layout: &Layout, rank: usize) -> Vec<Hop> {
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

/// The longest a `PushChunks` call may last when its client names no deadline (ours
/// always do: the per-chunk timeout for every chunk of the all-reduce).
pub const CALL_LIMIT: Duration = Duration::from_secs(3600);

/// Serves a collective mailbox on `listener` until `shutdown` resolves, with the standard
/// gRPC health service beside it; every collective call must carry `token`; with `tls`,
/// connections are mutual TLS.
pub async fn serve(
    listener: tokio::net::TcpListener,
    mailbox: Arc<Mailbox>,
    token: Token,
    tls: Option<Tls>,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<(), tonic::transport::Error> {
    let health_service =
        osrt_proto::server::CheckOnly::server(&[osrt_proto::v1::collective_server::SERVICE_NAME]);
    let accept = move |chunk| mailbox.accept(chunk);
    let service = PushChunkServer::new(accept, MAX_CHUNK_FLOATS * 4 + 4096);
    osrt_proto::server::builder(tls.as_ref(), CALL_LIMIT)?
        .initial_stream_window_size(WINDOW_BYTES)
        .initial_connection_window_size(WINDOW_BYTES)
        .max_frame_size(FRAME_BYTES)
        .add_service(health_service)
        .add_service(InterceptedService::new(
            service,
            CheckToken::new(token, "collective"),
        ))
        .serve_with_incoming_shutdown(
            // Our own listener: its sockets need TCP_NODELAY here (the builder's setting
            // applies only to listeners it binds), or Nagle delays the small acks.
            tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true)),
            shutdown,
        )
        .await
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

    /// The wire bytes of a chunk, and applying them at every byte alignment tonic may hand
    /// out, give back the same floats bit for bit (signs, NaN payloads, subnormals, ±∞).
    #[test]
    fn le_bytes_round_trip_at_any_alignment() {
        let v: Vec<f32> = [
            0.0f32,
            -0.0,
            1.5,
            -3.25e-39,
            f32::INFINITY,
            f32::NEG_INFINITY,
        ]
        .into_iter()
        .chain([f32::from_bits(0x7fc0_1234), f32::MAX, f32::MIN_POSITIVE])
        .chain((0..37).map(|i| (i as f32 * 0.37).sin() * 1e3))
        .collect();
        let shared = LentBuffer::new(v.clone());
        let wire = shared.lend(0..v.len());
        assert_eq!(wire.len(), v.len() * 4);
        for (i, x) in v.iter().enumerate() {
            assert_eq!(wire[4 * i..4 * i + 4], x.to_le_bytes());
        }
        for offset in 0..4 {
            let mut padded = vec![0xAAu8; offset];
            padded.extend_from_slice(&wire);
            let src = &padded[offset..];
            let mut copied = vec![7.0f32; v.len()];
            apply_le(&mut copied, src, false);
            let bits = |s: &[f32]| s.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&copied), bits(&v), "copy at offset {offset}");
            let mut summed = vec![1.0f32; v.len()];
            apply_le(&mut summed, src, true);
            let want: Vec<f32> = v.iter().map(|x| 1.0 + x).collect();
            assert_eq!(bits(&summed), bits(&want), "add at offset {offset}");
        }
    }
}
