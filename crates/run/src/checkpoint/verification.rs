//! Listing, reading and verifying checkpoints: a checkpoint exists only if its manifest
//! is there and every file it lists has the listed size and SHA-256.

use super::{
    MANIFEST, MODEL, Manifest, OPTIMIZER, READ_BUDGET, STATE, read_err, sha256_hex, step_dir,
    store_err,
};
use crate::error::{Result, RunError};
use bytes::Bytes;
use futures::StreamExt;
use object_store::ObjectStoreExt;
use osrt_retry::RetryPolicy;
use osrt_store::Location;
use sha2::{Digest, Sha256};
use std::collections::HashMap;

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
