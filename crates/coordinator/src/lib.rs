//! The osrt coordinator: owns one job's spec and state, decides who trains in which
//! generation, hands out plans, checks that replicas agree, and keeps the run's
//! `metrics.jsonl` and `job.json` in the object store so a restarted coordinator resumes,
//! with the records as TensorBoard events ([`events`]).
//!
//! [`core`] is the state machine (no I/O, unit-tested); `service` is its gRPC face and
//! the loop that times out silent members; beside it, `persist` writes the run folder;
//! [`retention`] deletes old checkpoints and [`timeline`] those of an abandoned timeline.

pub mod core;
mod error;
pub mod events;
mod persist;
pub mod retention;
mod service;
pub mod timeline;

pub use crate::core::{Core, JobSpec, MetricsWrite, Persisted};
pub use error::CoordinatorError;
pub use persist::STORE_RETRY_BUDGET;
pub use service::{Coordinator, OpenOptions, StatusSnapshot};
