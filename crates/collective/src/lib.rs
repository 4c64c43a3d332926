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
mod error;
mod layout;
mod loan;
mod mailbox;
mod ring;
mod schedule;
mod server;
mod stage;

pub use budget::{MIN_RING_BYTES_PER_S, STRAGGLER_TIMEOUTS, all_reduce_budget};
pub use error::CollectiveError;
pub use layout::{Layout, RingConfig};
pub use mailbox::Mailbox;
#[cfg(feature = "fault-injection")]
pub use ring::FAULT_ENV;
pub use ring::Ring;
pub use server::{CALL_LIMIT, serve};
pub use stage::Stage;
