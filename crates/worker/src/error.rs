//! Typed errors of the worker: the learner's, the collective's, and the coordinator's
//! answers.

use osrt_trainer::TrainError;
use thiserror::Error;

pub type Result<T, E = WorkerError> = std::result::Result<T, E>;

#[derive(Debug, Error)]
pub enum WorkerError {
    #[error(transparent)]
    Train(#[from] TrainError),

    #[error(transparent)]
    Collective(#[from] osrt_collective::CollectiveError),

    #[error("cluster: {0}")]
    Cluster(String),

    #[error("{what}: the coordinator answered {code:?}: {message}")]
    Coordinator {
        what: String,
        code: tonic::Code,
        message: String,
    },
}

impl From<osrt_dataset::DatasetError> for WorkerError {
    fn from(e: osrt_dataset::DatasetError) -> Self {
        Self::Train(e.into())
    }
}

impl From<osrt_run::RunError> for WorkerError {
    fn from(e: osrt_run::RunError) -> Self {
        Self::Train(e.into())
    }
}

impl From<candle_core::Error> for WorkerError {
    fn from(e: candle_core::Error) -> Self {
        Self::Train(e.into())
    }
}

impl From<osrt_store::LocationError> for WorkerError {
    fn from(e: osrt_store::LocationError) -> Self {
        Self::Train(e.into())
    }
}
