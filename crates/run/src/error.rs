//! Typed errors of the run folder.

use thiserror::Error;

pub type Result<T, E = RunError> = std::result::Result<T, E>;

#[derive(Debug, Error)]
pub enum RunError {
    #[error(transparent)]
    Location(#[from] osrt_store::LocationError),

    #[error("config {path}: {reason}")]
    Config { path: String, reason: String },

    #[error("run folder {path}: {reason}")]
    Run { path: String, reason: String },

    #[error("checkpoint {path}: {reason}")]
    Checkpoint { path: String, reason: String },

    /// The run folder's lease is another holder's now: this process must stop writing.
    #[error("run folder {path}: the run folder was taken over by {holder}")]
    LeaseLost { path: String, holder: String },
}
