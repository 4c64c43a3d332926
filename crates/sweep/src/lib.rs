//! Sweeps over the paper's ablations and the reports people look at afterwards.
//!
//! - `grid`: a sweep file (a base job plus axes) and its points in a fixed order.
//! - `results`: one row per finished point, the `results.csv` / `results.md` tables,
//!   and the error-against-run-time curves read from each run's `metrics.jsonl`.
//! - [`plot`]: those curves as SVG and PNG charts (no system fonts needed).
//! - [`seeds`]: points that differ only in their seed as one group: mean and spread of
//!   their curves and test figures, and each seed's time to a target.
//! - [`pictures`]: render frames and slot segmentations as PNG strips and GIFs.
//! - [`html`]: one static page that opens from disk with no server and no network.
//! - [`live`]: where a running job stands, for a page kept current while it runs.
//!
//! Training and evaluating a point needs the local cluster and lives in the binary.

mod grid;
pub mod html;
pub mod live;
pub mod picture_files;
pub mod plot;
mod results;
pub mod seeds;

pub use grid::{Point, SweepFile, Targets};
pub use results::{Curve, PointResult, RESULT_FILE, RunSummary};

use thiserror::Error;

#[derive(Debug, Error)]
pub enum SweepError {
    #[error("sweep file {path}: {reason}")]
    File { path: String, reason: String },
    #[error("sweep point `{point}`: {reason}")]
    Point { point: String, reason: String },
    #[error("{path}: {reason}")]
    Io { path: String, reason: String },
    #[error("drawing {what}: {reason}")]
    Plot { what: String, reason: String },
}

pub type Result<T> = std::result::Result<T, SweepError>;

/// Reads a local file, naming it in the error.
pub(crate) fn read_text(path: &std::path::Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|e| SweepError::Io {
        path: path.display().to_string(),
        reason: e.to_string(),
    })
}

/// Writes a local file whole or not at all (a temporary file renamed over it: a browser
/// or a reader of a page being rewritten never sees half of it), naming it in the error.
pub fn write_bytes(path: &std::path::Path, bytes: &[u8]) -> Result<()> {
    let err = |e: std::io::Error| SweepError::Io {
        path: path.display().to_string(),
        reason: e.to_string(),
    };
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy())
        .unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.{}.tmp", std::process::id()));
    std::fs::write(&tmp, bytes).map_err(err)?;
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        err(e)
    })
}
