//! The worker side of osrt: job configuration, the train step (gradients as one flat
//! buffer, AdamW applied from one), evaluation, data sharding, checkpoints' tensors, the
//! learner (one rank's training loop, no RPC) and the worker shell around it (membership,
//! heartbeats, the ring all-reduce of `osrt-collective`, reports).

pub mod bench;
pub mod bench_allreduce;
/// The ring all-reduce (crate `osrt-collective`), under its former path.
pub use osrt_collective as collective;
pub use osrt_collective::chunk_wire;
pub mod check;
pub mod checkpoint;
pub mod config;
pub mod device;
pub mod distributed;
pub mod error;
pub mod eval;
pub mod learner;
pub mod memory;
pub mod optim;
pub mod pictures;
pub mod render;
pub mod retry;
pub mod run;
pub mod shard;
pub mod step;
pub mod worker;

pub use config::{ClusterConfig, JobConfig, TrainConfig};
pub use device::DeviceSpec;
pub use error::{Result, TrainError};
pub use eval::{EvalOptions, EvalResult, evaluate};
pub use run::{LoadedRun, load_run, load_run_on, load_run_with_slots};
pub use step::{ApplyOutcome, StepGradients, Trainer};
pub use worker::{WorkerOptions, run_worker};
