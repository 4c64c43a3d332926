//! The osrt worker: the shell around a generation's [`osrt_trainer::learner::Learner`]
//! (the training loop, which makes no RPC) that registers with the coordinator, asks for
//! plans, carries the step's reduction over the ring all-reduce of `osrt-collective`,
//! sends heartbeats and progress and checkpoint reports ([`run_worker`]).

mod error;
mod generation;
pub mod link;
mod membership;
pub mod reduce;
mod shell;

pub use error::{Result, WorkerError};
pub use shell::{WorkerOptions, run_worker, run_worker_until};
