//! Committing a checkpoint: its files written create-only under names unique to the
//! writer, then the manifest; a checkpoint already committed at the step is adopted if it
//! holds the same bytes, never overwritten.

use super::{
    CheckpointState, MANIFEST, Manifest, ManifestEntry, READ_BUDGET, STATE, read_err, sha256_hex,
    step_dir, store_err, verify_retrying,
};
use crate::error::{Result, is_refusal};
use bytes::Bytes;
use object_store::{ObjectStoreExt, PutMode, PutOptions, PutPayload};
use osrt_retry::RetryPolicy;
use osrt_store::Location;

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
