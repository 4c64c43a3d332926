//! A local folder with the conditional writes object stores have: `PutMode::Update`
//! (replace an object only if it is still the version the writer read), which
//! `object_store`'s `LocalFileSystem` does not offer. The run folder's lease renews with
//! it, so that a late renewal can never overwrite a newcomer's lease.
//!
//! An update holds an exclusive `flock` on the object's folder while it compares the
//! object's ETag with the expected one and replaces the object (written to a temporary
//! file and renamed, as every put is). Every conditional writer of the folder takes the
//! same lock, whichever process or PID namespace it runs in, on one machine or over a
//! network filesystem that passes locks on; create-only writes need no lock (the rename
//! itself refuses an existing object).

use async_trait::async_trait;
use futures::stream::BoxStream;
use object_store::local::LocalFileSystem;
use object_store::path::Path;
use object_store::{
    CopyOptions, GetOptions, GetResult, ListResult, MultipartUpload, ObjectMeta, ObjectStore,
    PutMode, PutMultipartOptions, PutOptions, PutPayload, PutResult, UpdateVersion,
};
use std::path::PathBuf;

const STORE: &str = "LocalFileSystem";

/// [`LocalFileSystem`] rooted at `root`, with `PutMode::Update`.
#[derive(Debug)]
pub struct LocalFolder {
    inner: LocalFileSystem,
    root: PathBuf,
}

impl LocalFolder {
    pub fn new(inner: LocalFileSystem, root: PathBuf) -> Self {
        Self { inner, root }
    }

    /// Replaces `location` with `payload` if its ETag is still `expected`'s.
    async fn update(
        &self,
        location: &Path,
        payload: PutPayload,
        expected: UpdateVersion,
        opts: PutOptions,
    ) -> object_store::Result<PutResult> {
        let Some(want) = expected.e_tag else {
            return Err(object_store::Error::Generic {
                store: STORE,
                source: "an ETag is required for a conditional write".into(),
            });
        };
        let folder = location
            .parts()
            .fold(self.root.clone(), |p, part| p.join(part.as_ref()))
            .parent()
            .map(PathBuf::from)
            .unwrap_or_else(|| self.root.clone());
        let precondition = |why: String| object_store::Error::Precondition {
            path: location.to_string(),
            source: why.into(),
        };
        // The lock lives as long as `_lock`: it is released when the file closes.
        let _lock = match tokio::task::spawn_blocking(move || {
            let f = std::fs::File::open(&folder)?;
            f.lock()?;
            Ok::<_, std::io::Error>(f)
        })
        .await
        {
            Ok(Ok(f)) => f,
            Ok(Err(e)) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(precondition("the object does not exist".into()));
            }
            Ok(Err(e)) => {
                return Err(object_store::Error::Generic {
                    store: STORE,
                    source: Box::new(e),
                });
            }
            Err(e) => {
                return Err(object_store::Error::Generic {
                    store: STORE,
                    source: Box::new(e),
                });
            }
        };
        let head = match self.inner.head(location).await {
            Ok(meta) => meta,
            Err(object_store::Error::NotFound { .. }) => {
                return Err(precondition("the object does not exist".into()));
            }
            Err(e) => return Err(e),
        };
        if head.e_tag.as_deref() != Some(want.as_str()) {
            return Err(precondition(format!(
                "ETag {:?} is not the expected {want:?}",
                head.e_tag
            )));
        }
        let opts = PutOptions {
            mode: PutMode::Overwrite,
            ..opts
        };
        self.inner.put_opts(location, payload, opts).await
    }
}

impl std::fmt::Display for LocalFolder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.inner)
    }
}

use object_store::ObjectStoreExt as _;

#[async_trait]
impl ObjectStore for LocalFolder {
    async fn put_opts(
        &self,
        location: &Path,
        payload: PutPayload,
        opts: PutOptions,
    ) -> object_store::Result<PutResult> {
        match opts.mode.clone() {
            PutMode::Update(v) => self.update(location, payload, v, opts).await,
            _ => self.inner.put_opts(location, payload, opts).await,
        }
    }

    async fn put_multipart_opts(
        &self,
        location: &Path,
        opts: PutMultipartOptions,
    ) -> object_store::Result<Box<dyn MultipartUpload>> {
        self.inner.put_multipart_opts(location, opts).await
    }

    async fn get_opts(
        &self,
        location: &Path,
        options: GetOptions,
    ) -> object_store::Result<GetResult> {
        self.inner.get_opts(location, options).await
    }

    fn delete_stream(
        &self,
        locations: BoxStream<'static, object_store::Result<Path>>,
    ) -> BoxStream<'static, object_store::Result<Path>> {
        self.inner.delete_stream(locations)
    }

    fn list(&self, prefix: Option<&Path>) -> BoxStream<'static, object_store::Result<ObjectMeta>> {
        self.inner.list(prefix)
    }

    fn list_with_offset(
        &self,
        prefix: Option<&Path>,
        offset: &Path,
    ) -> BoxStream<'static, object_store::Result<ObjectMeta>> {
        self.inner.list_with_offset(prefix, offset)
    }

    async fn list_with_delimiter(&self, prefix: Option<&Path>) -> object_store::Result<ListResult> {
        self.inner.list_with_delimiter(prefix).await
    }

    async fn copy_opts(
        &self,
        from: &Path,
        to: &Path,
        options: CopyOptions,
    ) -> object_store::Result<()> {
        self.inner.copy_opts(from, to, options).await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An update on the version read replaces the object; one on any other version, or
    /// on a missing object, is refused as a failed precondition and changes nothing.
    #[tokio::test]
    async fn updates_replace_only_the_version_they_read() {
        let dir = tempfile::tempdir().unwrap();
        let fs = LocalFileSystem::new_with_prefix(dir.path()).unwrap();
        let store = LocalFolder::new(fs, dir.path().to_path_buf());
        let path = Path::from("run/lease.json");
        let first = store
            .put(&path, PutPayload::from_static(b"a"))
            .await
            .unwrap();
        let update = |v: PutResult| PutOptions {
            mode: PutMode::Update(UpdateVersion {
                e_tag: v.e_tag,
                version: v.version,
            }),
            ..Default::default()
        };
        let second = store
            .put_opts(&path, PutPayload::from_static(b"b"), update(first.clone()))
            .await
            .unwrap();
        let stale = store
            .put_opts(&path, PutPayload::from_static(b"c"), update(first))
            .await;
        assert!(
            matches!(stale, Err(object_store::Error::Precondition { .. })),
            "{stale:?}"
        );
        let got = store.get(&path).await.unwrap().bytes().await.unwrap();
        assert_eq!(&got[..], b"b");
        let missing = store
            .put_opts(
                &Path::from("run/none.json"),
                PutPayload::from_static(b"d"),
                update(second),
            )
            .await;
        assert!(
            matches!(missing, Err(object_store::Error::Precondition { .. })),
            "{missing:?}"
        );
    }
}
