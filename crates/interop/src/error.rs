//! Errors of the interop crate: each names the file and, where one is at fault, the
//! tensor or setting.

#[derive(Debug, thiserror::Error)]
pub enum InteropError {
    /// The file cannot be read as what it should be.
    #[error("{path}: {reason}")]
    File { path: String, reason: String },
    /// One tensor of a readable file is unusable.
    #[error("{path}: tensor `{name}`: {reason}")]
    Tensor {
        path: String,
        name: String,
        reason: String,
    },
    /// The checkpoint's tensors are not the model the config describes: every missing,
    /// unexpected and mis-shaped tensor, one per line.
    #[error("{path}: the tensors do not match the model its config describes:\n{report}")]
    Mismatch { path: String, report: String },
    /// A setting of the other tool that osrt's model cannot express.
    #[error("{path}: {setting}: {reason}")]
    Unsupported {
        path: String,
        setting: String,
        reason: String,
    },
    #[error("{path}: {source}")]
    Candle {
        path: String,
        #[source]
        source: candle_core::Error,
    },
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
}

pub type Result<T, E = InteropError> = std::result::Result<T, E>;
