//! `osrt bench`: the benchmark subcommands (`model`, `allreduce`, `cluster`), each
//! saving the typed figures of the `osrt-bench` crate as JSON and printing them for people.

mod allreduce;
mod cluster;
mod model;

pub use allreduce::{BenchAllReduceArgs, allreduce};
pub use cluster::{BenchClusterArgs, cluster};
pub use model::{BenchModelArgs, run};

use anyhow::{Context, Result};

/// Saves benchmark figures (creating the folder) and returns the text.
pub fn save_json(path: &std::path::Path, value: &serde_json::Value) -> Result<String> {
    let text = serde_json::to_string_pretty(value)?;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(path, &text).with_context(|| format!("writing {}", path.display()))?;
    Ok(text)
}
