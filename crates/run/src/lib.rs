//! The run folder (a path or an object-store URL) and what it holds, shared by the
//! trainer, the coordinator, sweeps and the command line. Nothing here builds a model:
//! the coordinator depends on this crate, not on the trainer.
//!
//! ```text
//! RUN/config.toml     the resolved job config
//! RUN/run.json        dataset location, parameter count, workers
//! RUN/job.json        the coordinator's persisted job state (generation, restarts, …)
//! RUN/metrics.jsonl   one JSON object per line: training and evaluation records (`records`)
//! RUN/lease.json      the coordinator driving the folder, while it runs (`lease`)
//! RUN/tb/events.out.tfevents.*   the records as TensorBoard events (`tensorboard`)
//! RUN/eval/step-NNNNNNNNN/*.png  pictures of each validation (`tensorboard::eval_picture`)
//! RUN/checkpoints/step-NNNNNNNNN/…   see `checkpoint`
//! ```

pub mod checkpoint;
pub mod cluster_config;
mod error;
pub mod lease;
pub mod metrics_log;
mod records;
pub mod tensorboard;

pub use error::{Result, RunError};
use osrt_store::Location;
pub use records::{EvalRecord, MetricsRecord, ObjectCountRecord, TrainRecord, validate_line};

use object_store::ObjectStoreExt;
/// Run folders are object-store locations, like datasets.
use serde::{Deserialize, Serialize};

pub const CONFIG_FILE: &str = "config.toml";
pub const INFO_FILE: &str = "run.json";
pub const METRICS_FILE: &str = "metrics.jsonl";
pub const JOB_FILE: &str = "job.json";

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunInfo {
    pub data: String,
    /// The model's parameter count, written by rank 0 when it first builds the model (the
    /// coordinator never builds one).
    #[serde(default)]
    pub parameters: Option<usize>,
    pub workers: usize,
    /// The learning rate's decay horizon a budget job measured (rank 0, when every rank
    /// has it): `osrt train --horizon N` reruns the job to the bit on any host.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub horizon: Option<u64>,
}

/// Records the model's parameter count in `RUN/run.json` (rank 0, at a generation's
/// start); a no-op when it is there already.
pub async fn record_parameters(run: &Location, parameters: usize) -> Result<()> {
    update_info(run, |info| {
        info.parameters.replace(parameters) != Some(parameters)
    })
    .await
}

/// Records a budget job's measured decay horizon in `RUN/run.json` (rank 0).
pub async fn record_horizon(run: &Location, horizon: u64) -> Result<()> {
    update_info(run, |info| info.horizon.replace(horizon) != Some(horizon)).await
}

/// Reads `RUN/run.json`, lets `change` edit it and writes it back where `change` says it
/// changed anything; a no-op when the file is absent (the coordinator writes it first).
async fn update_info(run: &Location, change: impl FnOnce(&mut RunInfo) -> bool) -> Result<()> {
    let Some(bytes) = read_file(run, INFO_FILE).await? else {
        return Ok(());
    };
    let mut info: RunInfo = serde_json::from_slice(&bytes).map_err(|e| RunError::Run {
        path: run.describe(&run.path(INFO_FILE)),
        reason: format!("unreadable: {e}"),
    })?;
    if !change(&mut info) {
        return Ok(());
    }
    let bytes = serde_json::to_vec_pretty(&info).expect("serialises");
    write_file(run, INFO_FILE, bytes).await
}

/// Seconds since the Unix epoch (0 if the clock is before it).
pub fn unix_now() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// Reads `RUN/name`; `Ok(None)` if it does not exist.
pub async fn read_file(run: &Location, name: &str) -> Result<Option<bytes::Bytes>> {
    let path = run.path(name);
    let err = |e: object_store::Error| RunError::Run {
        path: run.describe(&path),
        reason: e.to_string(),
    };
    match run.store.get(&path).await {
        Ok(r) => Ok(Some(r.bytes().await.map_err(err)?)),
        Err(object_store::Error::NotFound { .. }) => Ok(None),
        Err(e) => Err(err(e)),
    }
}

/// Writes `RUN/name` (one put: atomic on every store).
pub async fn write_file(run: &Location, name: &str, bytes: Vec<u8>) -> Result<()> {
    let path = run.path(name);
    run.store
        .put(&path, bytes.into())
        .await
        .map(|_| ())
        .map_err(|e| RunError::Run {
            path: run.describe(&path),
            reason: e.to_string(),
        })
}
