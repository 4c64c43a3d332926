//! The worker side of osrt: job configuration, the train step (gradients as one flat
//! buffer, AdamW applied from one), in-memory training data, evaluation, and the
//! single-process training run. The gRPC collective and checkpoints arrive with the
//! cluster.

pub mod bench;
pub mod bench_allreduce;
pub mod collective;
pub mod config;
pub mod data;
pub mod error;
pub mod eval;
pub mod optim;
pub mod run;
pub mod step;

pub use config::{JobConfig, TrainConfig};
pub use error::{Result, TrainError};
pub use eval::{EvalOptions, EvalResult, evaluate};
pub use run::{LoadedRun, TrainOptions, load_run, train};
pub use step::{ApplyOutcome, StepGradients, Trainer};
