//! Where a dataset (or a run) lives: a URL or local path resolved to an object store and
//! a prefix inside it.
//!
//! - a plain path or `file://` URL → [`LocalFileSystem`] with conditional writes
//!   ([`LocalFolder`]; the directory is created);
//! - `memory://NAME/...` → a process-wide [`InMemory`] store per `NAME`, so that every
//!   open of the same URL in one process sees the same objects (tests);
//! - `s3://BUCKET/prefix` → [`AmazonS3Builder::from_env`], configured by the standard
//!   `AWS_*` variables (`AWS_ENDPOINT`, `AWS_ALLOW_HTTP`, `AWS_ACCESS_KEY_ID`, …).

#[cfg(feature = "fault-injection")]
pub mod chaos;
mod local;

pub use local::LocalFolder;
use thiserror::Error;

/// A location that names no store this build opens, or a store that cannot be opened.
#[derive(Debug, Error)]
#[error("invalid location {location:?}: {reason}")]
pub struct LocationError {
    pub location: String,
    pub reason: String,
}

pub type Result<T, E = LocationError> = std::result::Result<T, E>;
use object_store::ObjectStore;
#[cfg(test)]
use object_store::ObjectStoreExt;
use object_store::aws::AmazonS3Builder;
use object_store::local::LocalFileSystem;
use object_store::memory::InMemory;
use object_store::path::Path;
use std::collections::HashMap;
use std::sync::{Arc, LazyLock, Mutex};
use url::Url;

/// An object store and a prefix inside it.
#[derive(Debug, Clone)]
pub struct Location {
    pub store: Arc<dyn ObjectStore>,
    pub prefix: Path,
    /// The string the user gave, for messages.
    pub display: String,
    /// The folder a local store is rooted at (`None` for object stores).
    local_root: Option<std::path::PathBuf>,
}

static MEMORY_STORES: LazyLock<Mutex<HashMap<String, Arc<InMemory>>>> =
    LazyLock::new(|| Mutex::new(HashMap::new()));

impl Location {
    /// Wraps an existing store (tests, embedding).
    pub fn new(store: Arc<dyn ObjectStore>, prefix: impl Into<Path>) -> Self {
        let prefix = prefix.into();
        Self {
            display: format!("{store}/{prefix}"),
            store,
            prefix,
            local_root: None,
        }
    }

    /// Parses a local path or a `file://`, `memory://` or `s3://` URL. In builds with the
    /// `fault-injection` feature, [`chaos::ENV`] wraps the store in a [`chaos::ChaosStore`].
    pub fn parse(location: &str) -> Result<Self> {
        let loc = Self::parse_plain(location)?;
        #[cfg(feature = "fault-injection")]
        if let Ok(spec) = std::env::var(chaos::ENV) {
            let random = chaos::Random::parse(&spec).map_err(|reason| LocationError {
                location: location.to_string(),
                reason,
            })?;
            let store = chaos::ChaosStore::new(loc.store.clone());
            store.faults(|f| f.random = Some(random));
            return Ok(Self {
                store: Arc::new(store),
                ..loc
            });
        }
        Ok(loc)
    }

    fn parse_plain(location: &str) -> Result<Self> {
        let err = |reason: String| LocationError {
            location: location.to_string(),
            reason,
        };
        let looks_like_url = location.contains("://");
        if !looks_like_url {
            return Self::local(std::path::Path::new(location), location);
        }
        let url = Url::parse(location).map_err(|e| err(e.to_string()))?;
        match url.scheme() {
            "file" => {
                let p = url
                    .to_file_path()
                    .map_err(|_| err("not a valid file URL".into()))?;
                Self::local(&p, location)
            }
            "memory" => {
                let name = url.host_str().unwrap_or("default").to_string();
                let store = MEMORY_STORES
                    .lock()
                    .expect("memory store registry poisoned")
                    .entry(name)
                    .or_insert_with(|| Arc::new(InMemory::new()))
                    .clone();
                Ok(Self {
                    store,
                    prefix: url_prefix(&url).map_err(err)?,
                    display: location.to_string(),
                    local_root: None,
                })
            }
            "s3" | "s3a" => {
                let store = AmazonS3Builder::from_env()
                    .with_url(location)
                    .build()
                    .map_err(|e| err(format!("S3 configuration from AWS_* environment: {e}")))?;
                Ok(Self {
                    store: Arc::new(store),
                    prefix: url_prefix(&url).map_err(err)?,
                    display: location.to_string(),
                    local_root: None,
                })
            }
            other => Err(err(format!(
                "unsupported scheme `{other}`: expected a local path, file://, memory:// or s3://"
            ))),
        }
    }

    fn local(dir: &std::path::Path, display: &str) -> Result<Self> {
        let err = |reason: String| LocationError {
            location: display.to_string(),
            reason,
        };
        std::fs::create_dir_all(dir).map_err(|e| err(format!("cannot create directory: {e}")))?;
        // Deleting a folder's last file removes the folder (checkpoint retention), as on
        // object stores where folders are only prefixes.
        // Every write is synced (file and folder) before the put returns: a checkpoint's
        // manifest, written last, can then never reach the disk before its files, and a
        // crash loses no acknowledged write.
        let fs = LocalFileSystem::new_with_prefix(dir)
            .map_err(|e| err(e.to_string()))?
            .with_automatic_cleanup(true)
            .with_fsync(true);
        // Conditional writes (the run folder's lease) as object stores have them.
        let root = dir
            .canonicalize()
            .map_err(|e| err(format!("cannot resolve directory: {e}")))?;
        Ok(Self {
            store: Arc::new(LocalFolder::new(fs, root)),
            prefix: Path::default(),
            display: display.to_string(),
            local_root: Some(dir.to_path_buf()),
        })
    }

    /// The file behind `path` when this is a local folder (for what object stores cannot
    /// do, such as appending in place).
    pub fn local_file(&self, path: &Path) -> Option<std::path::PathBuf> {
        let root = self.local_root.as_ref()?;
        Some(
            path.parts()
                .fold(root.clone(), |p, part| p.join(part.as_ref())),
        )
    }

    /// The location of `child` (a relative path such as `train` or `manifest.json`).
    pub fn join(&self, child: &str) -> Self {
        Self {
            store: self.store.clone(),
            prefix: self.path(child),
            display: format!("{}/{}", self.display.trim_end_matches('/'), child),
            local_root: self.local_root.clone(),
        }
    }

    /// An object path under this prefix.
    pub fn path(&self, child: &str) -> Path {
        child
            .split('/')
            .filter(|p| !p.is_empty())
            .fold(self.prefix.clone(), |p, part| p.join(part))
    }

    /// A path as a user reads it in messages (`DIR/train/part-00000.parquet`).
    pub fn describe(&self, path: &Path) -> String {
        let rel = path
            .as_ref()
            .strip_prefix(self.prefix.as_ref())
            .unwrap_or(path.as_ref())
            .trim_start_matches('/');
        if rel.is_empty() {
            self.display.clone()
        } else {
            format!("{}/{}", self.display.trim_end_matches('/'), rel)
        }
    }
}

fn url_prefix(url: &Url) -> std::result::Result<Path, String> {
    Path::from_url_path(url.path()).map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn memory_urls_share_one_store_per_name() {
        let a = Location::parse("memory://shared-test/data").unwrap();
        a.store
            .put(&a.path("x.txt"), bytes::Bytes::from_static(b"hi").into())
            .await
            .unwrap();
        let b = Location::parse("memory://shared-test/data/").unwrap();
        let got = b
            .store
            .get(&b.path("x.txt"))
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap();
        assert_eq!(&got[..], b"hi");
        assert_eq!(
            b.describe(&b.path("x.txt")),
            "memory://shared-test/data/x.txt"
        );
    }

    #[test]
    fn unknown_schemes_are_rejected() {
        let e = Location::parse("ftp://host/x").unwrap_err().to_string();
        assert!(e.contains("unsupported scheme `ftp`"), "{e}");
    }

    #[test]
    fn local_paths_and_file_urls_resolve_to_the_same_directory() {
        let dir = tempfile::tempdir().unwrap();
        let a = Location::parse(dir.path().to_str().unwrap()).unwrap();
        let url = format!("file://{}", dir.path().display());
        let b = Location::parse(&url).unwrap();
        assert_eq!(a.prefix, b.prefix);
    }

    /// `local_file` names the file a put through the store writes.
    #[tokio::test]
    async fn local_file_is_where_the_store_writes() {
        let dir = tempfile::tempdir().unwrap();
        let run = Location::parse(dir.path().to_str().unwrap())
            .unwrap()
            .join("run");
        let path = run.path("checkpoints/step-1/state.json");
        run.store.put(&path, b"{}".to_vec().into()).await.unwrap();
        let file = run.local_file(&path).unwrap();
        assert_eq!(std::fs::read(&file).unwrap(), b"{}");
        assert!(file.starts_with(dir.path()));
        let mem = Location::parse("memory://local-file-test/run").unwrap();
        assert!(mem.local_file(&mem.path("x")).is_none());
    }
}
