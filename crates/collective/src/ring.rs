//! One rank's side of the ring all-reduce (`Ring`): the connection to its successor, the
//! chunk-by-chunk loop that sends, receives and reduces, the little-endian arithmetic of a
//! received chunk (`apply_le`), and the malformed-chunk fault hook.

use crate::budget::Budget;
use crate::chunk_wire;
use crate::error::CollectiveError;
use crate::layout::{Layout, RingConfig};
use crate::loan::LentBuffer;
use crate::mailbox::{Key, Mailbox};
use crate::schedule::{ChunkId, IN_FLIGHT_BYTES, Outgoing, first_sends, receive_schedule};
use crate::server::{FRAME_BYTES, WINDOW_BYTES};
use crate::stage::{self, Fill, Stage, Whole};
use osrt_proto::{KEEP_ALIVE_INTERVAL, KEEP_ALIVE_TIMEOUT, MAX_CHUNK_FLOATS};
use std::sync::Arc;
use std::time::Duration;
use tokio::time::timeout;
use tonic::Status;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::transport::Channel;

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
pub(crate) fn apply_le(dst: &mut [f32], src: &[u8], add: bool) {
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
        let endpoint = cfg.credentials.endpoint(&addr).map_err(connect_err)?;
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
            auth: cfg.credentials.authorization().clone(),
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

/// Why a send waited in vain: the successor took nothing for `timeout`.
fn stalled(timeout: Duration) -> Status {
    Status::deadline_exceeded(format!("the successor took no chunk within {timeout:?}"))
}

#[cfg(test)]
mod tests {
    use super::*;

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
