//! Typed errors of the coordinator.

use thiserror::Error;

#[derive(Debug, Error)]
pub enum CoordinatorError {
    /// The run folder: unreadable, unwritable, or holding something else.
    #[error(transparent)]
    Run(#[from] osrt_run::RunError),

    #[error(transparent)]
    Location(#[from] osrt_store::LocationError),

    /// Serving: the listener, TLS.
    #[error("cluster: {0}")]
    Cluster(String),
}
