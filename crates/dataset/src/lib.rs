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

pub mod batch;
pub mod camera;
pub mod codec;
pub mod error;
pub mod generator;
pub mod import;
pub mod inspect;
pub mod manifest;
pub mod math;
pub mod palette;
pub mod rays;
pub mod reader;
pub mod resize;
pub mod scene;
pub mod schema;
pub mod writer;

pub use batch::{
    Batch, BatchConfig, InputSelection, RayFrame, TargetViews, build_batch, build_batch_each,
};
pub use camera::{Camera, Intrinsics};
pub use error::{DatasetError, Result};
pub use generator::{GeneratorConfig, SplitSizes, generate_dataset, generate_scene};
pub use manifest::{MANIFEST_FILE, Manifest, SplitInfo};
pub use reader::{ReadStats, RowGroupRef, SplitReader, load_split};
pub use scene::{ObjectMeta, Scene, View};
pub use schema::{Columns, ImageCodec, SCHEMA_VERSION};
pub use writer::{SplitWriter, WriterOptions};
