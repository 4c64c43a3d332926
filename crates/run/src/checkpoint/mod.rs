//! Checkpoints in an object store (local filesystem, `file://`, `memory://`, `s3://`):
//! their layout, commit, verification, listing and retention. Writing tensors and loading
//! them into a model is the trainer's (`osrt_trainer::checkpoint`); nothing here knows a
//! tensor, so the coordinator can list and verify checkpoints without a model.
//!
//! ```text
//! RUN/checkpoints/step-000000120/model.W.safetensors      weights, by parameter name
//! RUN/checkpoints/step-000000120/optimizer.W.safetensors  AdamW moments `m`, `v` (flat)
//! RUN/checkpoints/step-000000120/state.W.json             step, epoch, data cursor, …
//! RUN/checkpoints/step-000000120/MANIFEST.json            written last
//! ```
//!
//! Every object is written create-only (`PutMode::Create`), the data files under names
//! unique to their writer (`W`: 16 hex digits drawn per commit), so two writers at one
//! step (a second job on the folder, a replayed step) never overwrite each other's files,
//! and the first manifest wins; the loser deletes its files and adopts the winner's
//! checkpoint if it holds the same bytes. The manifest names each file by what it is
//! (`model.safetensors`, …) and by the object holding it. A checkpoint exists only if
//! its manifest is present and every file it lists has the listed size and SHA-256: a
//! crash mid-write leaves no manifest, a corrupted file fails its hash, and either is
//! skipped with a warning — never loaded.
//!
//! `write` commits a checkpoint; `verification` lists, reads and verifies them;
//! `retention` deletes those a job no longer needs.

use crate::error::{RunError, is_refusal};
use osrt_store::Location;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

mod retention;
mod verification;
mod write;

pub use retention::{apply_retention, discard_after, resume_bound};
pub use verification::{
    check, latest_verified, latest_verified_with, list_steps, object_of, read_manifest, verify,
    verify_retrying,
};
#[cfg(feature = "fault-injection")]
pub use write::TORN_CHECKPOINT_ENV;
pub use write::commit;

pub const MANIFEST: &str = "MANIFEST.json";
pub const MODEL: &str = "model.safetensors";
pub const OPTIMIZER: &str = "optimizer.safetensors";
pub const STATE: &str = "state.json";

/// Everything besides tensors that an exact resume needs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointState {
    /// Optimiser steps taken (the next step to run).
    pub step: u64,
    /// Data cursor: the epoch in progress and the step it began at (steps within the
    /// epoch index the epoch's shuffled order).
    pub epoch: u64,
    pub epoch_start_step: u64,
    /// Workers of the generation that wrote the checkpoint. The data order and the draws
    /// do not depend on it: a resume with another size continues the epoch.
    pub world_size: usize,
    /// Random state: each scene's RNG in a step is derived from (seed, step, scene id),
    /// so the step number *is* the RNG state; recorded here for people reading the file.
    pub rng: String,
    pub adam_t: u64,
    pub skipped_total: u64,
    /// Wall-clock seconds of the job up to this step, and the part spent in train steps
    /// (summed over generations; replayed steps after a restart count once).
    pub wall_s: f64,
    pub train_s: f64,
    /// SHA-256 of the job config TOML: a resume with another config is refused.
    pub config_hash: String,
    /// Latest validation FG-ARI and PSNR before this step (retention keeps the best).
    pub val_fg_ari: Option<f64>,
    pub val_psnr: Option<f64>,
    /// The learning rate's decay horizon in force (a budget job's, once measured): a
    /// resume keeps it. Absent: none (a fixed schedule, or not measured yet).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub horizon: Option<u64>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ManifestEntry {
    /// What the file is: [`MODEL`], [`OPTIMIZER`] or [`STATE`].
    pub name: String,
    /// The object in the checkpoint's folder that holds it (its writer's name); empty in
    /// manifests written before objects were named per writer, whose object is `name`.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub object: String,
    pub size: u64,
    pub sha256: String,
}

impl ManifestEntry {
    pub fn object(&self) -> &str {
        if self.object.is_empty() {
            &self.name
        } else {
            &self.object
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub step: u64,
    pub files: Vec<ManifestEntry>,
}

pub fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// SHA-256 of the job config, as recorded in checkpoints.
pub fn config_hash(job_toml: &str) -> String {
    sha256_hex(job_toml.as_bytes())
}

/// Hash of a replica's parameters (first 16 hex digits of the SHA-256 of their bytes).
pub fn param_hash(flat: &[f32]) -> String {
    let mut h = Sha256::new();
    for x in flat {
        h.update(x.to_le_bytes());
    }
    h.finalize()[..8]
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

pub fn step_dir(step: u64) -> String {
    format!("checkpoints/step-{step:09}")
}

/// A checkpoint error naming the file or folder under `loc`.
pub fn store_err(loc: &Location, path: &str, e: impl std::fmt::Display) -> RunError {
    RunError::Checkpoint {
        path: loc.describe(&loc.path(path)),
        reason: e.to_string(),
    }
}

/// A store error met while reading `path` of a checkpoint: an object that is not there
/// is a missing part (the checkpoint is provably incomplete); anything else means the
/// checkpoint could not be read, which says nothing about whether it is intact.
fn read_err(loc: &Location, path: &str, e: object_store::Error) -> RunError {
    match e {
        object_store::Error::NotFound { .. } => store_err(loc, path, "missing"),
        e => RunError::Unreadable {
            path: loc.describe(&loc.path(path)),
            transient: !is_refusal(&e),
            reason: e.to_string(),
        },
    }
}

/// How long reads of a checkpoint may keep failing for a reason that may pass before a
/// resume stops with the error (object stores' outages last seconds; a read of a large
/// optimizer file can meet the client's own request timeout).
pub const READ_BUDGET: std::time::Duration = std::time::Duration::from_secs(60);
