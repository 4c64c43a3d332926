//! Typed errors of the dataset crate. Every variant that concerns a file names it, and
//! where the scene is known, the scene id and view index, so a user can find the bad row.

use thiserror::Error;

/// Result alias for the dataset crate.
pub type Result<T, E = DatasetError> = std::result::Result<T, E>;

#[derive(Debug, Error)]
pub enum DatasetError {
    #[error("object store error at {path}: {source}")]
    Store {
        path: String,
        #[source]
        source: object_store::Error,
    },

    #[error("invalid dataset location {location:?}: {reason}")]
    Location { location: String, reason: String },

    #[error("Parquet error in {path}: {source}")]
    Parquet {
        path: String,
        #[source]
        source: parquet::errors::ParquetError,
    },

    #[error("Arrow error in {path}: {source}")]
    Arrow {
        path: String,
        #[source]
        source: arrow::error::ArrowError,
    },

    #[error("{path} is not an osrt scene file: {reason}")]
    Schema { path: String, reason: String },

    #[error("{path} has scene schema version {found}, this build reads versions 1 to {expected}")]
    SchemaVersion {
        path: String,
        found: String,
        expected: u32,
    },

    #[error("{path}: scene {scene_id}, view {view}: {reason}")]
    InvalidView {
        path: String,
        scene_id: u64,
        view: usize,
        reason: String,
    },

    #[error("{path}: scene {scene_id}: {reason}")]
    InvalidScene {
        path: String,
        scene_id: u64,
        reason: String,
    },

    #[error("split {path} is empty: expected at least one scene in *.parquet files")]
    EmptySplit { path: String },

    #[error("manifest {path}: {reason}")]
    Manifest { path: String, reason: String },

    #[error("batch: {0}")]
    Batch(String),

    #[error("generator: {0}")]
    Generator(String),

    #[error("image {path}: {reason}")]
    Image { path: String, reason: String },

    /// A foreign dataset that cannot be imported as it is: which file, what is wrong.
    #[error("import {path}: {reason}")]
    Import { path: String, reason: String },
}

impl DatasetError {
    pub(crate) fn store(path: impl ToString, source: object_store::Error) -> Self {
        Self::Store {
            path: path.to_string(),
            source,
        }
    }

    /// Whether a read that failed with this error may succeed if made again: a store
    /// error that is not a definite answer (missing, refused, unsupported), also when it
    /// reached us through the Parquet reader.
    pub fn is_transient(&self) -> bool {
        fn store(e: &object_store::Error) -> bool {
            matches!(e, object_store::Error::Generic { .. })
        }
        match self {
            Self::Store { source, .. } => store(source),
            Self::Parquet {
                source: parquet::errors::ParquetError::External(e),
                ..
            } => e.downcast_ref::<object_store::Error>().is_some_and(store),
            _ => false,
        }
    }

    pub(crate) fn parquet(path: impl ToString, source: parquet::errors::ParquetError) -> Self {
        Self::Parquet {
            path: path.to_string(),
            source,
        }
    }

    pub(crate) fn schema(path: impl ToString, reason: impl Into<String>) -> Self {
        Self::Schema {
            path: path.to_string(),
            reason: reason.into(),
        }
    }
}

impl From<osrt_store::LocationError> for DatasetError {
    fn from(e: osrt_store::LocationError) -> Self {
        Self::Location {
            location: e.location,
            reason: e.reason,
        }
    }
}
