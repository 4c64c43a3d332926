//! The crate's one error type: why an all-reduce, a ring's setup or a connection failed.

use crate::budget::{MIN_RING_BYTES_PER_S, STRAGGLER_TIMEOUTS};
use osrt_proto::v1::Phase;
use std::ops::Range;
use std::time::Duration;
use thiserror::Error;
use tonic::Status;

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
