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

    /// A checkpoint that is missing or provably corrupt (no manifest, a listed file not
    /// found, a size or SHA-256 mismatch, an unparsable manifest).
    #[error("checkpoint {path}: {reason}")]
    Checkpoint { path: String, reason: String },

    /// A checkpoint the store would not hand over (permission, timeout, a 5xx answer, an
    /// I/O error): it may be intact, so nothing may be concluded from it, least of all
    /// that it can be discarded.
    #[error(
        "checkpoint {path}: could not be read ({reason}); nothing was discarded: \
         fix access to the store and run again"
    )]
    Unreadable {
        path: String,
        reason: String,
        /// Whether trying again may succeed (not for a refused permission).
        transient: bool,
    },

    /// The run folder's lease is another holder's now: this process must stop writing.
    #[error("run folder {path}: the run folder was taken over by {holder}")]
    LeaseLost { path: String, holder: String },

    /// A write of a generation the run folder's lease no longer names (a rank of an
    /// abandoned generation, or of a replaced coordinator's job): refused.
    #[error("run folder {path}: refused, the writer is fenced off: {reason}")]
    Fenced { path: String, reason: String },
}

impl RunError {
    /// Whether the same call may succeed if made again (a store that could not be read
    /// for a reason that passes).
    pub fn is_transient(&self) -> bool {
        matches!(
            self,
            RunError::Unreadable {
                transient: true,
                ..
            }
        )
    }
}

/// Whether a store error is a refusal that no retry will change (credentials,
/// permissions), rather than a failure that may pass (a timeout, a 5xx, a reset).
pub fn is_refusal(e: &object_store::Error) -> bool {
    use object_store::Error as E;
    if matches!(e, E::PermissionDenied { .. } | E::Unauthenticated { .. }) {
        return true;
    }
    // A local folder reports EACCES as a generic error with the I/O error inside.
    let mut source = std::error::Error::source(e);
    while let Some(s) = source {
        if let Some(io) = s.downcast_ref::<std::io::Error>()
            && io.kind() == std::io::ErrorKind::PermissionDenied
        {
            return true;
        }
        source = s.source();
    }
    false
}
