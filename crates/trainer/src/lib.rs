//! Training OSRT on one rank, with no RPC: job configuration, the train step (gradients
//! as one flat buffer, AdamW applied from one), evaluation, rendering, data sharding,
//! checkpoints' tensors, the reduction's buffer layout and the learner (one rank's
//! training loop). The worker shell around the learner (membership, heartbeats, the ring
//! all-reduce, reports) is the crate `osrt-worker`; evaluation, rendering, sweeps and
//! `check-device` build without gRPC.

pub mod checkpoint;
mod config;
pub mod device;
pub mod distributed;
mod error;
mod eval;
pub mod feed;
pub mod footprint;
pub mod interop;
pub mod learner;
mod loaded;
pub mod lr_schedule;
pub mod memory;
pub mod optim;
pub mod pictures;
pub mod predict;
pub mod render;
pub mod retry;
pub mod shard;
pub mod staging;
mod step;

pub use config::{JobConfig, TrainConfig, ray_frame};
pub use error::{Result, TrainError};
pub use eval::{EvalOptions, EvalResult, evaluate};
pub use loaded::{LoadedRun, TestTime, eval_options, load_run, load_run_on};
pub use step::{
    ApplyOutcome, BatchTensors, CONTROL_FLOATS, Gradient, Phases, StepGradients, Trainer,
};
