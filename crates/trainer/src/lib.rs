//! Training OSRT on one rank, with no RPC: job configuration, the train step (gradients
//! as one flat buffer, AdamW applied from one), evaluation, rendering, data sharding,
//! checkpoints' tensors, the reduction's buffer layout and the learner (one rank's
//! training loop). The worker shell around the learner (membership, heartbeats, the ring
//! all-reduce, reports) is the crate `osrt-worker`; evaluation, rendering, sweeps and
//! `check-device` build without gRPC.

pub mod checkpoint;
pub mod config;
pub mod device;
pub mod distributed;
pub mod error;
pub mod eval;
pub mod feed;
pub mod footprint;
pub mod interop;
pub mod learner;
pub mod loaded;
pub mod memory;
pub mod optim;
pub mod pictures;
pub mod predict;
pub mod render;
pub mod retry;
pub mod schedule;
pub mod shard;
pub mod staging;
pub mod step;

pub use config::{JobConfig, TrainConfig};
pub use device::DeviceSpec;
pub use error::{Result, TrainError};
pub use eval::{EvalOptions, EvalResult, evaluate};
pub use loaded::{LoadedRun, load_run, load_run_on, load_run_with_slots};
pub use step::{ApplyOutcome, StepGradients, Trainer};
