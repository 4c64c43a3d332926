//! Deleting checkpoints: those of an abandoned timeline, and those retention lets go
//! (beyond the newest few and the best, never the one a restart would continue from).

use super::{
    CheckpointState, MANIFEST, STATE, list_steps, object_of, read_err, step_dir, store_err,
};
use crate::error::{Result, RunError};
use object_store::ObjectStoreExt;
use osrt_store::Location;

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
