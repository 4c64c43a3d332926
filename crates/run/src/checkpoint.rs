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

use crate::error::{Result, RunError, is_refusal};
use bytes::Bytes;
use futures::StreamExt;
use object_store::{ObjectStoreExt, PutMode, PutOptions, PutPayload};
use osrt_retry::RetryPolicy;
use osrt_store::Location;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::HashMap;

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

/// `model.safetensors` as written by `writer`: `model.<writer>.safetensors`.
fn object_name(name: &str, writer: &str) -> String {
    match name.rsplit_once('.') {
        Some((stem, ext)) => format!("{stem}.{writer}.{ext}"),
        None => format!("{name}.{writer}"),
    }
}

/// 16 hex digits, fresh for every commit.
fn writer_tag() -> String {
    format!("{:016x}", rand::random::<u64>())
}

fn create() -> PutOptions {
    PutOptions {
        mode: PutMode::Create,
        ..Default::default()
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

/// Writes `files` (name, bytes) of the checkpoint of `state`, then the manifest with `PutMode::Create`. A committed checkpoint
/// at the same step is adopted only if it is this one (a replayed step after a
/// restart produces the same weights and optimizer bytes under the same config);
/// anything else there is an error, never overwritten.
///
/// With `fence` (the writer's generation), the manifest is written only while the run
/// folder's lease names that generation or an older one ([`crate::lease::check_fence`]):
/// a rank of an abandoned generation commits nothing the new timeline would meet.
pub async fn commit(
    run: &Location,
    state: &CheckpointState,
    files: Vec<(&'static str, Bytes)>,
    fence: Option<u64>,
) -> Result<u64> {
    let step = state.step;
    let dir = step_dir(step);
    let manifest_path = format!("{dir}/{MANIFEST}");
    match run.store.head(&run.path(&manifest_path)).await {
        Ok(_) => return adopt(run, state, &files).await,
        Err(object_store::Error::NotFound { .. }) => {}
        // Not knowing whether a committed checkpoint is there must not lead to
        // writing over its files.
        Err(e) => return Err(store_err(run, &manifest_path, e)),
    }
    let writer = writer_tag();
    let mut entries = Vec::new();
    for (name, bytes) in &files {
        let object = object_name(name, &writer);
        let path = format!("{dir}/{object}");
        entries.push(ManifestEntry {
            name: name.to_string(),
            object,
            size: bytes.len() as u64,
            sha256: sha256_hex(bytes),
        });
        put_file(run, &path, bytes).await?;
        torn_checkpoint_fault(step);
    }
    let manifest = Manifest {
        step,
        files: entries,
    };
    if let Some(generation) = fence
        && let Err(e) = crate::lease::check_fence(run, generation).await
    {
        delete_objects(run, &dir, &manifest).await;
        return Err(e);
    }
    let bytes = serde_json::to_vec_pretty(&manifest).expect("serialises");
    match run
        .store
        .put_opts(&run.path(&manifest_path), PutPayload::from(bytes), create())
        .await
    {
        Ok(_) => {}
        // Another writer committed this step meanwhile: its checkpoint stands; ours goes.
        Err(object_store::Error::AlreadyExists { .. }) => {
            return match adopt(run, state, &files).await {
                Ok(step) => {
                    // Another writer's checkpoint stands; unless the "other" is this
                    // commit itself (a put answered `AlreadyExists` after it went through,
                    // its retry finding it), its files go.
                    if !manifest_is(run, &manifest_path, &manifest).await {
                        delete_objects(run, &dir, &manifest).await;
                    }
                    Ok(step)
                }
                Err(e) => {
                    if !manifest_is(run, &manifest_path, &manifest).await {
                        delete_objects(run, &dir, &manifest).await;
                    }
                    Err(e)
                }
            };
        }
        Err(e) => return Err(store_err(run, &manifest_path, e)),
    }
    tracing::info!(step, dir = %run.describe(&run.path(&dir)), "checkpoint committed");
    Ok(step)
}

/// Whether the manifest at `path` is `mine` (it lists my objects). Unknown (unreadable):
/// taken as mine, so that nothing is deleted on a guess.
async fn manifest_is(run: &Location, path: &str, mine: &Manifest) -> bool {
    let Ok(got) = run.store.get(&run.path(path)).await else {
        return true;
    };
    let Ok(bytes) = got.bytes().await else {
        return true;
    };
    serde_json::from_slice::<Manifest>(&bytes).map_or(true, |there| there == *mine)
}

/// Deletes the objects `manifest` lists (a commit that lost or was refused); failures are
/// logged (the objects are unreferenced).
async fn delete_objects(run: &Location, dir: &str, manifest: &Manifest) {
    for e in &manifest.files {
        let path = format!("{dir}/{}", e.object());
        if let Err(err) = run.store.delete(&run.path(&path)).await {
            tracing::warn!(path, error = %err, "could not delete an uncommitted file");
        }
    }
}

/// Writes one data file of a commit create-only under its writer's name.
async fn put_file(run: &Location, path: &str, bytes: &Bytes) -> Result<()> {
    match run
        .store
        .put_opts(
            &run.path(path),
            PutPayload::from_bytes(bytes.clone()),
            create(),
        )
        .await
    {
        Ok(_) => {}
        // The name is this commit's own (a fresh writer tag): an object already there
        // is this put's, found by a retry of a request that went through. Checked by
        // size; the manifest's hash checks the rest at every read.
        Err(object_store::Error::AlreadyExists { .. }) => {
            let object = run.path(path);
            let there = RetryPolicy::backoff(READ_BUDGET)
                .run(
                    "checking a file this commit wrote",
                    |e: &object_store::Error| {
                        !matches!(e, object_store::Error::NotFound { .. }) && !is_refusal(e)
                    },
                    || run.store.head(&object),
                )
                .await
                .map_err(|e| read_err(run, path, e))?;
            if there.size != bytes.len() as u64 {
                return Err(store_err(
                    run,
                    path,
                    format!(
                        "a file of this writer's name is there with {} bytes, not {}",
                        there.size,
                        bytes.len()
                    ),
                ));
            }
        }
        Err(e) => return Err(store_err(run, path, e)),
    }
    Ok(())
}

/// With the `fault-injection` feature, `OSRT_FAULT_TORN_CHECKPOINT=STEP:MARKER` makes the
/// process exit at once (no unwinding, nothing more written: as a crash would) after
/// writing a file of checkpoint STEP, once: MARKER is created first, and a process that
/// finds it goes on. Tests leave a torn checkpoint behind a crash
/// with it (`tests/chaos.rs`).
#[cfg(feature = "fault-injection")]
pub const TORN_CHECKPOINT_ENV: &str = "OSRT_FAULT_TORN_CHECKPOINT";

#[cfg(feature = "fault-injection")]
fn torn_checkpoint_fault(step: u64) {
    let Ok(v) = std::env::var(TORN_CHECKPOINT_ENV) else {
        return;
    };
    let Some((at, marker)) = v.split_once(':') else {
        return;
    };
    if at.parse() != Ok(step) {
        return;
    }
    let first = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(marker)
        .is_ok();
    if first {
        eprintln!("fault injection: exiting in the middle of writing checkpoint {step}");
        std::process::exit(70);
    }
}

#[cfg(not(feature = "fault-injection"))]
fn torn_checkpoint_fault(_step: u64) {}

/// Accepts the checkpoint already committed at this step if it verifies and holds
/// these weights and optimizer state under this config and world size.
async fn adopt(run: &Location, state: &CheckpointState, files: &[(&str, Bytes)]) -> Result<u64> {
    let step = state.step;
    let dir = step_dir(step);
    let there = verify_retrying(run, step).await.map_err(|e| {
        store_err(
            run,
            &dir,
            format!("a manifest exists but does not verify ({e}); delete the folder to re-save"),
        )
    })?;
    let theirs: CheckpointState = there
        .get(STATE)
        .and_then(|b| serde_json::from_slice(b).ok())
        .ok_or_else(|| {
            store_err(
                run,
                &dir,
                "the committed checkpoint has no readable state.json",
            )
        })?;
    let mut differs = Vec::new();
    if theirs.config_hash != state.config_hash {
        differs.push("job config".to_string());
    }
    if theirs.world_size != state.world_size {
        differs.push(format!(
            "world size ({} there, {} here)",
            theirs.world_size, state.world_size
        ));
    }
    for (name, bytes) in files.iter().filter(|(n, _)| *n != STATE) {
        if there.get(*name).is_none_or(|b| b != bytes) {
            differs.push((*name).to_string());
        }
    }
    if !differs.is_empty() {
        return Err(store_err(
            run,
            &dir,
            format!(
                "another checkpoint is committed at step {step}: its {} differ from this job's; \
                 choose a new run folder or delete that checkpoint",
                differs.join(", ")
            ),
        ));
    }
    tracing::info!(step, "checkpoint already committed");
    Ok(step)
}

/// Steps of every checkpoint folder under `run` (verified or not), newest first.
pub async fn list_steps(run: &Location) -> Result<Vec<u64>> {
    let prefix = run.path("checkpoints");
    let listing = run
        .store
        .list_with_delimiter(Some(&prefix))
        .await
        .map_err(|e| read_err(run, "checkpoints", e))?;
    let mut steps: Vec<u64> = listing
        .common_prefixes
        .iter()
        .filter_map(|p| p.filename()?.strip_prefix("step-")?.parse().ok())
        .collect();
    steps.sort_unstable_by(|a, b| b.cmp(a));
    Ok(steps)
}

/// The files of a checkpoint, after checking the manifest and every size and hash.
pub async fn verify(run: &Location, step: u64) -> Result<HashMap<String, Bytes>> {
    let dir = step_dir(step);
    let mpath = format!("{dir}/{MANIFEST}");
    let Some(manifest) = read_manifest(run, step).await? else {
        return Err(store_err(
            run,
            &dir,
            "no MANIFEST.json: the checkpoint was not finished (torn)",
        ));
    };
    if manifest.step != step {
        return Err(store_err(
            run,
            &mpath,
            format!(
                "manifest says step {}, folder is step {step}",
                manifest.step
            ),
        ));
    }
    let mut files = HashMap::new();
    for e in &manifest.files {
        let path = format!("{dir}/{}", e.object());
        let data = run
            .store
            .get(&run.path(&path))
            .await
            .map_err(|err| read_err(run, &path, err))?
            .bytes()
            .await
            .map_err(|err| read_err(run, &path, err))?;
        if data.len() as u64 != e.size {
            return Err(store_err(
                run,
                &path,
                format!("{} bytes, the manifest lists {}", data.len(), e.size),
            ));
        }
        let h = sha256_hex(&data);
        if h != e.sha256 {
            return Err(store_err(
                run,
                &path,
                format!("SHA-256 {h} does not match the manifest's {}", e.sha256),
            ));
        }
        files.insert(e.name.clone(), data);
    }
    for want in [MODEL, OPTIMIZER, STATE] {
        if !files.contains_key(want) {
            return Err(store_err(
                run,
                &mpath,
                format!("manifest does not list {want}"),
            ));
        }
    }
    Ok(files)
}

/// [`verify`], retrying reads that fail for a reason that may pass within
/// [`READ_BUDGET`] (a large file read can meet a store's request timeout).
pub async fn verify_retrying(run: &Location, step: u64) -> Result<HashMap<String, Bytes>> {
    RetryPolicy::backoff(READ_BUDGET)
        .run(
            &format!("reading checkpoint {step}"),
            RunError::is_transient,
            || verify(run, step),
        )
        .await
}

/// The manifest of the checkpoint at `step`, unverified; `None` where there is none.
pub async fn read_manifest(run: &Location, step: u64) -> Result<Option<Manifest>> {
    let mpath = format!("{}/{MANIFEST}", step_dir(step));
    let bytes = match run.store.get(&run.path(&mpath)).await {
        Ok(r) => r.bytes().await.map_err(|e| read_err(run, &mpath, e))?,
        Err(object_store::Error::NotFound { .. }) => return Ok(None),
        Err(e) => return Err(read_err(run, &mpath, e)),
    };
    serde_json::from_slice(&bytes)
        .map(Some)
        .map_err(|e| store_err(run, &mpath, format!("unreadable manifest: {e}")))
}

/// The path under `run` of the object holding file `name` ([`MODEL`], …) of the
/// checkpoint at `step`, as its manifest names it.
pub async fn object_of(run: &Location, step: u64, name: &str) -> Result<String> {
    let dir = step_dir(step);
    let manifest = read_manifest(run, step)
        .await?
        .ok_or_else(|| store_err(run, &dir, "no MANIFEST.json"))?;
    let entry = manifest
        .files
        .iter()
        .find(|e| e.name == name)
        .ok_or_else(|| store_err(run, &dir, format!("the manifest lists no {name}")))?;
    Ok(format!("{dir}/{}", entry.object()))
}

/// The newest checkpoint that verifies, optionally the newest at or below `at_most`.
/// Missing or provably corrupt ones (torn, a size or SHA-256 mismatch) are skipped with
/// a warning; one the store will not hand over is tried again under [`READ_BUDGET`], and
/// if it stays unreadable the error stands: the caller must stop, not start over (an
/// older checkpoint or none would discard the unreadable one and the records after it).
pub async fn latest_verified(run: &Location, at_most: Option<u64>) -> Result<Option<u64>> {
    latest_verified_with(run, at_most, RetryPolicy::backoff(READ_BUDGET)).await
}

/// [`latest_verified`] with its own retry policy (tests).
pub async fn latest_verified_with(
    run: &Location,
    at_most: Option<u64>,
    policy: RetryPolicy,
) -> Result<Option<u64>> {
    let steps = policy
        .run("listing the checkpoints", RunError::is_transient, || {
            list_steps(run)
        })
        .await?;
    for step in steps {
        if at_most.is_some_and(|m| step > m) {
            continue;
        }
        let what = format!("verifying checkpoint {step}");
        match policy
            .run(&what, RunError::is_transient, || check(run, step))
            .await
        {
            Ok(()) => return Ok(Some(step)),
            Err(e @ RunError::Checkpoint { .. }) => {
                tracing::warn!(step, error = %e, "skipping checkpoint")
            }
            Err(e) => return Err(e),
        }
    }
    Ok(None)
}

/// Checks the checkpoint at `step` as [`verify`] does, streaming each file through its
/// hash instead of holding it (the coordinator verifies without a model's memory).
pub async fn check(run: &Location, step: u64) -> Result<()> {
    let dir = step_dir(step);
    let mpath = format!("{dir}/{MANIFEST}");
    let manifest = read_manifest(run, step).await?.ok_or_else(|| {
        store_err(
            run,
            &dir,
            "no MANIFEST.json: the checkpoint was not finished (torn)",
        )
    })?;
    if manifest.step != step {
        return Err(store_err(
            run,
            &mpath,
            format!(
                "manifest says step {}, folder is step {step}",
                manifest.step
            ),
        ));
    }
    for want in [MODEL, OPTIMIZER, STATE] {
        if !manifest.files.iter().any(|e| e.name == want) {
            return Err(store_err(
                run,
                &mpath,
                format!("manifest does not list {want}"),
            ));
        }
    }
    for e in &manifest.files {
        let path = format!("{dir}/{}", e.object());
        let mut stream = run
            .store
            .get(&run.path(&path))
            .await
            .map_err(|err| read_err(run, &path, err))?
            .into_stream();
        let (mut hash, mut len) = (Sha256::new(), 0u64);
        while let Some(chunk) = stream.next().await {
            let chunk = chunk.map_err(|err| read_err(run, &path, err))?;
            len += chunk.len() as u64;
            hash.update(&chunk);
        }
        if len != e.size {
            return Err(store_err(
                run,
                &path,
                format!("{len} bytes, the manifest lists {}", e.size),
            ));
        }
        let h: String = hash.finalize().iter().map(|b| format!("{b:02x}")).collect();
        if h != e.sha256 {
            return Err(store_err(
                run,
                &path,
                format!("SHA-256 {h} does not match the manifest's {}", e.sha256),
            ));
        }
    }
    Ok(())
}

/// Deletes every checkpoint folder (committed or torn) past `step` (`None`: all), the
/// manifest first; returns their steps.
pub async fn discard_after(run: &Location, step: Option<u64>) -> Result<Vec<u64>> {
    let mut discarded = Vec::new();
    for s in list_steps(run).await? {
        if step.is_some_and(|k| s <= k) {
            continue;
        }
        delete_checkpoint(run, s).await?;
        discarded.push(s);
    }
    Ok(discarded)
}

/// Deletes one checkpoint folder, the manifest first (a half-deleted folder is torn),
/// then every object in it (every writer's).
async fn delete_checkpoint(run: &Location, step: u64) -> Result<()> {
    let dir = step_dir(step);
    let mut names = vec![MANIFEST.to_string()];
    let listing = run
        .store
        .list_with_delimiter(Some(&run.path(&dir)))
        .await
        .map_err(|e| store_err(run, &dir, e))?;
    names.extend(
        listing
            .objects
            .iter()
            .filter_map(|o| o.location.filename().map(str::to_string))
            .filter(|n| n != MANIFEST),
    );
    for name in names {
        let path = format!("{dir}/{name}");
        match run.store.delete(&run.path(&path)).await {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
            Err(e) => return Err(store_err(run, &path, e)),
        }
    }
    Ok(())
}

/// The newest step a coordinator continuing the job in this run folder may start from,
/// given the newest step whose record `metrics.jsonl` holds and `job.json`'s
/// `last_checkpoint`: it continues from the newest verified checkpoint at or before it
/// (never past its records, so none goes missing). No record: the job starts over.
pub fn resume_bound(last_record: Option<u64>, last_checkpoint: Option<u64>) -> u64 {
    last_record
        .unwrap_or(0)
        .min(last_checkpoint.unwrap_or(u64::MAX))
}

/// Deletes committed checkpoints beyond the newest `keep_last` (at least 1) and the best
/// by validation FG-ARI (then PSNR), but never the newest committed one at or before
/// `resume_bound` (see [`resume_bound`]) nor any newer: a coordinator restarted now would
/// continue from it. Folders without a manifest are neither counted nor deleted (one may
/// be a checkpoint being written). The manifest goes first, so a half-deleted folder is
/// simply torn.
pub async fn apply_retention(
    run: &Location,
    keep_last: usize,
    resume_bound: u64,
) -> Result<Vec<u64>> {
    let keep_last = keep_last.max(1);
    let mut steps = Vec::new();
    for s in list_steps(run).await? {
        let manifest = format!("{}/{MANIFEST}", step_dir(s));
        match run.store.head(&run.path(&manifest)).await {
            Ok(_) => steps.push(s),
            Err(object_store::Error::NotFound { .. }) => {}
            Err(e) => return Err(read_err(run, &manifest, e)),
        }
    }
    if steps.len() <= keep_last {
        return Ok(Vec::new());
    }
    // The best must be known before anything goes: a state that cannot be read now
    // could be the best's, so the pass stops (and is tried again later) rather than
    // guess.
    let mut best: Option<(u64, (f64, f64))> = None;
    for &s in &steps {
        let path = match object_of(run, s, STATE).await {
            Ok(path) => path,
            Err(e @ RunError::Unreadable { .. }) => return Err(e),
            Err(_) => continue,
        };
        let bytes = match run.store.get(&run.path(&path)).await {
            Ok(r) => r.bytes().await.map_err(|e| read_err(run, &path, e))?,
            Err(object_store::Error::NotFound { .. }) => continue,
            Err(e) => return Err(read_err(run, &path, e)),
        };
        let Ok(st) = serde_json::from_slice::<CheckpointState>(&bytes) else {
            continue;
        };
        let score = (
            st.val_fg_ari.unwrap_or(f64::NEG_INFINITY),
            st.val_psnr.unwrap_or(f64::NEG_INFINITY),
        );
        if st.val_fg_ari.is_some() && best.is_none_or(|(_, b)| score > b) {
            best = Some((s, score));
        }
    }
    // `steps` is newest first.
    let resume = steps.iter().copied().find(|&s| s <= resume_bound);
    let mut deleted = Vec::new();
    for &s in steps.iter().skip(keep_last) {
        if best.is_some_and(|(b, _)| b == s) || resume.is_some_and(|r| s >= r) {
            continue;
        }
        delete_checkpoint(run, s).await?;
        deleted.push(s);
    }
    Ok(deleted)
}
