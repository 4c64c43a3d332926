//! Multi-view scenes for OSRT: the Arrow/Parquet scene schema, reading and writing over
//! `object_store`, rays derived from cameras, the batch builder, and the built-in
//! CLEVR-like scene generator.
//!
//! A dataset is a prefix in an object store:
//! ```text
//! DATASET/manifest.json            counts, image size, generator settings (written last)
//! DATASET/{train,val,test}/part-NNNNN.parquet
//! ```
//! One Parquet row is one scene; row groups are the unit the workers shard (each rank reads its own).

mod batch;
mod camera;
pub mod codec;
mod error;
pub mod generator;
pub mod import;
pub mod inspect;
mod manifest;
pub mod math;
pub mod palette;
pub mod rays;
mod reader;
pub mod resize;
mod scene;
mod schema;
mod writer;

pub use batch::{
    Batch, BatchConfig, InputSelection, RayFrame, TargetViews, build_batch, build_batch_each,
};
pub use camera::{Camera, Intrinsics};
pub use error::{DatasetError, Result};
pub use manifest::{GeneratorInfo, MANIFEST_FILE, Manifest, SplitInfo};
pub use reader::{ReadStats, RowGroupRef, SplitReader, load_split};
pub use scene::{ObjectMeta, Scene, View};
pub use schema::{
    CODEC_KEY, Columns, ImageCodec, SCHEMA_VERSION, VERSION_KEY, scenes_to_batch,
    scenes_to_batch_with,
};
pub use writer::{SplitWriter, WriterOptions};
