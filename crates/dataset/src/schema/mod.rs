//! The scene schema in Arrow: one row per scene, a variable-length list of views.
//!
//! ```text
//! scene_id  UInt64                                   not null
//! views     List<Struct<                             not null, ≥ 1 view
//!             width, height     UInt32
//!             image             Binary   RGB8, row-major, height·width·3 bytes
//!             mask              Binary?  u8 instance ids, height·width bytes
//!             camera_position   FixedSizeList<Float32, 3>
//!             camera_rotation   FixedSizeList<Float32, 9>   camera-to-world, row-major
//!             intrinsics        FixedSizeList<Float32, 4>   fx, fy, cx, cy (pixels)
//!           >>
//! objects   List<Struct<shape, color, size, material: Utf8,
//!                       position: FixedSizeList<Float32, 3>, yaw: Float32>>?   nullable
//! ```
//! The camera convention is documented in [`crate::camera`]. The schema version lives in
//! the Parquet key-value metadata under [`VERSION_KEY`]; readers refuse versions they do
//! not know. Version 1 stores `image` and `mask` raw; version 2 adds [`CODEC_KEY`]: with
//! `png`, each `image` is a PNG (RGB8) and each `mask` a PNG (8-bit grey) of the view's
//! size. Raw files are still written as version 1, byte for byte as before.
//!
//! This file holds the schema and the checks a file passes before it is read; scenes go
//! into a record batch in `encode` and come back out of one in `decode`.

mod decode;
mod encode;

pub use decode::batch_to_scenes_with;
pub use encode::{scenes_to_batch, scenes_to_batch_with};

use crate::error::{DatasetError, Result};
use arrow::datatypes::{DataType, Field, Fields, Schema, SchemaRef};
use parquet::arrow::ProjectionMask;
use parquet::schema::types::SchemaDescriptor;
use std::sync::{Arc, LazyLock};

/// Newest scene-schema version this build reads and writes (1 and 2 are read).
pub const SCHEMA_VERSION: u32 = 2;
/// Parquet key-value metadata key holding the file's schema version.
pub const VERSION_KEY: &str = "osrt.scene_schema_version";
/// Parquet key-value metadata key holding the file's [`ImageCodec`] (version 2).
pub const CODEC_KEY: &str = "osrt.image_codec";

/// How `image` and `mask` bytes are stored: `raw` pixels, or `png` (lossless; about a
/// third of the raw size for rendered scenes, decoded in parallel on read).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ImageCodec {
    #[default]
    Raw,
    Png,
}

impl ImageCodec {
    /// The schema version files of this codec are written with.
    pub fn schema_version(self) -> u32 {
        match self {
            Self::Raw => 1,
            Self::Png => 2,
        }
    }

    pub fn is_raw(&self) -> bool {
        *self == Self::Raw
    }
}

impl std::fmt::Display for ImageCodec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Raw => "raw",
            Self::Png => "png",
        })
    }
}

impl std::str::FromStr for ImageCodec {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "raw" => Ok(Self::Raw),
            "png" => Ok(Self::Png),
            other => Err(format!(
                "unknown image codec `{other}`: expected raw or png"
            )),
        }
    }
}

/// Which optional column groups a reader decodes. Training needs neither; evaluation
/// needs masks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Columns {
    pub masks: bool,
    pub objects: bool,
}

impl Columns {
    pub const TRAIN: Columns = Columns {
        masks: false,
        objects: false,
    };
    pub const ALL: Columns = Columns {
        masks: true,
        objects: true,
    };
}

fn f32_list(n: i32) -> DataType {
    DataType::FixedSizeList(Arc::new(Field::new("item", DataType::Float32, false)), n)
}

fn view_fields() -> Fields {
    Fields::from(vec![
        Field::new("width", DataType::UInt32, false),
        Field::new("height", DataType::UInt32, false),
        Field::new("image", DataType::Binary, false),
        Field::new("mask", DataType::Binary, true),
        Field::new("camera_position", f32_list(3), false),
        Field::new("camera_rotation", f32_list(9), false),
        Field::new("intrinsics", f32_list(4), false),
    ])
}

fn object_fields() -> Fields {
    Fields::from(vec![
        Field::new("shape", DataType::Utf8, false),
        Field::new("color", DataType::Utf8, false),
        Field::new("size", DataType::Utf8, false),
        Field::new("material", DataType::Utf8, false),
        Field::new("position", f32_list(3), false),
        Field::new("yaw", DataType::Float32, false),
    ])
}

static SCHEMA: LazyLock<SchemaRef> = LazyLock::new(|| {
    Arc::new(Schema::new(vec![
        Field::new("scene_id", DataType::UInt64, false),
        Field::new(
            "views",
            DataType::List(Arc::new(Field::new(
                "element",
                DataType::Struct(view_fields()),
                false,
            ))),
            false,
        ),
        Field::new(
            "objects",
            DataType::List(Arc::new(Field::new(
                "element",
                DataType::Struct(object_fields()),
                false,
            ))),
            true,
        ),
    ]))
});

/// The Arrow schema of a scene file.
pub fn arrow_schema() -> SchemaRef {
    SCHEMA.clone()
}

/// Checks a file's key-value metadata for a schema version this build reads; returns
/// the file's image codec.
pub fn check_version(
    path: &str,
    kv: Option<&Vec<parquet::file::metadata::KeyValue>>,
) -> Result<ImageCodec> {
    let value = |key: &str| {
        kv.into_iter()
            .flatten()
            .find(|kv| kv.key == key)
            .and_then(|kv| kv.value.clone())
    };
    let version = match value(VERSION_KEY) {
        None => {
            return Err(DatasetError::schema(
                path,
                format!("no `{VERSION_KEY}` key in its Parquet key-value metadata"),
            ));
        }
        Some(v) => match v.trim().parse::<u32>() {
            Ok(n @ 1..=SCHEMA_VERSION) => n,
            _ => {
                return Err(DatasetError::SchemaVersion {
                    path: path.to_string(),
                    found: v,
                    expected: SCHEMA_VERSION,
                });
            }
        },
    };
    match (version, value(CODEC_KEY)) {
        (_, None) => Ok(ImageCodec::Raw),
        (1, Some(c)) => Err(DatasetError::schema(
            path,
            format!("schema version 1 has no image codec, the file names `{c}`"),
        )),
        (_, Some(c)) => c
            .parse()
            .map_err(|e: String| DatasetError::schema(path, format!("`{CODEC_KEY}`: {e}"))),
    }
}

/// Checks that a file's Arrow schema has every column we decode, with the right types.
pub fn check_schema(path: &str, schema: &Schema) -> Result<()> {
    let expected = arrow_schema();
    for name in ["scene_id", "views"] {
        let want = expected.field_with_name(name).expect("our own schema");
        let got = schema
            .field_with_name(name)
            .map_err(|_| DatasetError::schema(path, format!("missing column `{name}`")))?;
        if got.data_type() != want.data_type() {
            // Name the first differing view field where we can, so the message is short.
            let detail = match (got.data_type(), want.data_type()) {
                (DataType::List(g), DataType::List(w)) => match (g.data_type(), w.data_type()) {
                    (DataType::Struct(gf), DataType::Struct(wf)) => {
                        wf.iter().find_map(|f| match gf.find(f.name()) {
                            None => Some(format!("missing column `{name}.{}`", f.name())),
                            Some((_, g)) if g.data_type() != f.data_type() => Some(format!(
                                "column `{name}.{}` has type {}, expected {}",
                                f.name(),
                                g.data_type(),
                                f.data_type()
                            )),
                            _ => None,
                        })
                    }
                    _ => None,
                },
                _ => None,
            };
            return Err(DatasetError::schema(
                path,
                detail.unwrap_or_else(|| {
                    format!(
                        "column `{name}` has type {}, expected {}",
                        got.data_type(),
                        want.data_type()
                    )
                }),
            ));
        }
    }
    if let Ok(got) = schema.field_with_name("objects") {
        let want = expected.field_with_name("objects").expect("our own schema");
        if got.data_type() != want.data_type() {
            return Err(DatasetError::schema(
                path,
                format!(
                    "column `objects` has type {}, expected {}",
                    got.data_type(),
                    want.data_type()
                ),
            ));
        }
    }
    Ok(())
}

/// The Parquet leaves to decode for `columns`: masks and object metadata are left out
/// unless asked for, so their pages are never fetched.
pub fn projection(descr: &SchemaDescriptor, columns: Columns) -> ProjectionMask {
    let leaves = descr.columns().iter().enumerate().filter_map(|(i, c)| {
        let parts = c.path().parts();
        let top = parts.first().map(String::as_str);
        let is_mask = top == Some("views") && parts.last().map(String::as_str) == Some("mask");
        let is_object = top == Some("objects");
        let keep = (columns.masks || !is_mask) && (columns.objects || !is_object);
        keep.then_some(i)
    });
    ProjectionMask::leaves(descr, leaves)
}
