//! The store probe: a run folder's store must honour create-only and conditional writes
//! before a job runs on it.

use super::lease_err;
use crate::error::Result;
use object_store::{ObjectStoreExt, PutMode, PutOptions, PutPayload, UpdateVersion};
use osrt_store::Location;

/// Checks that `run`'s store honours create-only and conditional writes, which keep one
/// writer per run folder: a probe object is written create-only twice (the second must
/// be refused), then updated on a version it does not have (must be refused); refused
/// with the store's name and the remedy otherwise.
pub async fn probe_store(run: &Location) -> Result<()> {
    let name = format!(".osrt-probe-{:016x}", rand::random::<u64>());
    let path = run.path(&name);
    let err = |what: &str| {
        lease_err(
            run,
            format!(
                "the store {} {what}: osrt keeps one writer per run folder and every \
                 checkpoint file by create-only and conditional writes. Use a store that \
                 honours If-None-Match and If-Match (AWS S3, MinIO, Cloudflare R2, Google \
                 Cloud Storage) with AWS_CONDITIONAL_PUT=etag (the default)",
                run.store
            ),
        )
    };
    let create = || PutOptions {
        mode: PutMode::Create,
        ..Default::default()
    };
    let io = |e: object_store::Error| lease_err(run, format!("probing the store: {e}"));
    let first = run
        .store
        .put_opts(&path, PutPayload::from_static(b"1"), create())
        .await;
    let outcome = async {
        match first {
            Ok(_) => {}
            Err(object_store::Error::NotImplemented { .. }) => {
                return Err(err("does not offer create-only writes"));
            }
            Err(e) => return Err(io(e)),
        }
        match run
            .store
            .put_opts(&path, PutPayload::from_static(b"2"), create())
            .await
        {
            Err(object_store::Error::AlreadyExists { .. }) => {}
            Ok(_) => return Err(err("overwrote an object written create-only")),
            Err(e) => return Err(io(e)),
        }
        let stale = UpdateVersion {
            e_tag: Some("\"osrt-probe-no-such-version\"".into()),
            version: None,
        };
        let opts = PutOptions {
            mode: PutMode::Update(stale),
            ..Default::default()
        };
        match run
            .store
            .put_opts(&path, PutPayload::from_static(b"3"), opts)
            .await
        {
            Err(object_store::Error::Precondition { .. }) => Ok(()),
            Ok(_) => Err(err(
                "took a conditional write on a version it does not hold",
            )),
            Err(object_store::Error::NotImplemented { .. }) => {
                Err(err("does not offer conditional writes"))
            }
            Err(e) => Err(io(e)),
        }
    }
    .await;
    if let Err(e) = run.store.delete(&path).await {
        tracing::debug!(error = %e, "removing the store probe");
    }
    outcome
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Local folders and memory stores honour create-only and conditional writes.
    #[tokio::test]
    async fn the_stores_osrt_opens_pass_the_probe() {
        let dir = tempfile::tempdir().unwrap();
        let local = Location::parse(dir.path().to_str().unwrap()).unwrap();
        probe_store(&local).await.unwrap();
        probe_store(&Location::parse("memory://lease-probe/run").unwrap())
            .await
            .unwrap();
        assert_eq!(
            std::fs::read_dir(dir.path()).unwrap().count(),
            0,
            "no probe left"
        );
    }
}
