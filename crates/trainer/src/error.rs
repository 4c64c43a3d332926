//! Typed errors of the trainer.

use thiserror::Error;

pub type Result<T, E = TrainError> = std::result::Result<T, E>;

#[derive(Debug, Error)]
pub enum TrainError {
    #[error(transparent)]
    Dataset(#[from] osrt_dataset::DatasetError),

    /// Another tool's file (a PyTorch checkpoint, a peer config, NumPy arrays).
    #[error(transparent)]
    Interop(#[from] osrt_interop::InteropError),

    #[error("model: {0}")]
    Model(#[from] candle_core::Error),

    #[error("config {path}: {reason}")]
    Config { path: String, reason: String },

    /// This process's device cannot run the job (no such GPU, a build without CUDA, a
    /// precision the device does not run): a problem of one worker, not of the job.
    #[error("device: {0}")]
    Device(String),

    #[error("run folder {path}: {reason}")]
    Run { path: String, reason: String },

    #[error("checkpoint {path}: {reason}")]
    Checkpoint { path: String, reason: String },

    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },

    /// The step does not fit in the device's memory: final, for a restart would run
    /// into the same wall. The message names the step's shape, its estimate and the
    /// device's memory, and what to change.
    #[error("{0}")]
    OutOfMemory(String),

    #[error(
        "training stopped: {skipped} steps in a row had a non-finite loss or gradient \
         (limit {limit}); lower the learning rate or enable gradient clipping"
    )]
    TooManySkips { skipped: u64, limit: u64 },
}

/// The run folder's errors keep their kind (and their message) in the trainer's.
impl From<osrt_run::RunError> for TrainError {
    fn from(e: osrt_run::RunError) -> Self {
        use osrt_run::RunError as R;
        match e {
            R::Location(e) => Self::Dataset(e.into()),
            R::Config { path, reason } => Self::Config { path, reason },
            R::Run { path, reason } => Self::Run { path, reason },
            R::Checkpoint { path, reason } => Self::Checkpoint { path, reason },
            R::Unreadable { path, reason, .. } => Self::Checkpoint {
                path,
                reason: format!("could not be read ({reason})"),
            },
            R::Fenced { path, reason } => Self::Run {
                path,
                reason: format!("refused, the writer is fenced off: {reason}"),
            },
            R::LeaseLost { path, holder } => Self::Run {
                path,
                reason: format!("the run folder was taken over by {holder}"),
            },
        }
    }
}

impl TrainError {
    pub(crate) fn io(path: impl std::fmt::Display, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_string(),
            source,
        }
    }
}

impl From<osrt_store::LocationError> for TrainError {
    fn from(e: osrt_store::LocationError) -> Self {
        Self::Dataset(e.into())
    }
}
