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

use crate::camera::{Camera, Intrinsics};
use crate::error::{DatasetError, Result};
use crate::scene::{ObjectMeta, Scene, View};
use arrow::array::{
    Array, ArrayRef, AsArray, BinaryArray, FixedSizeListArray, Float32Array, ListArray,
    RecordBatch, StringArray, StructArray, UInt32Array, UInt64Array,
};
use arrow::buffer::{NullBuffer, OffsetBuffer};
use arrow::datatypes::{DataType, Field, Fields, Float32Type, Schema, SchemaRef, UInt32Type};
use parquet::arrow::ProjectionMask;
use parquet::schema::types::SchemaDescriptor;
use rayon::prelude::*;
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

fn fixed_list(values: Vec<f32>, n: i32) -> ArrayRef {
    let item = Arc::new(Field::new("item", DataType::Float32, false));
    Arc::new(FixedSizeListArray::new(
        item,
        n,
        Arc::new(Float32Array::from(values)),
        None,
    ))
}

/// Encodes scenes as one record batch, images and masks raw. No validation here: the
/// writer validates first, and tests use this directly to produce deliberately bad files.
pub fn scenes_to_batch(scenes: &[Scene]) -> Result<RecordBatch> {
    scenes_to_batch_with(scenes, ImageCodec::Raw)
}

/// [`scenes_to_batch`] with images and masks stored in `codec` (PNGs encoded in
/// parallel).
pub fn scenes_to_batch_with(scenes: &[Scene], codec: ImageCodec) -> Result<RecordBatch> {
    let ids = UInt64Array::from_iter_values(scenes.iter().map(|s| s.id));

    let all_views: Vec<&View> = scenes.iter().flat_map(|s| &s.views).collect();
    let coded: Vec<(Vec<u8>, Option<Vec<u8>>)> = match codec {
        ImageCodec::Raw => Vec::new(),
        ImageCodec::Png => all_views
            .par_iter()
            .map(|v| crate::codec::encode_view(v))
            .collect::<Result<_>>()?,
    };
    let image_bytes = |i: usize| -> &[u8] {
        match codec {
            ImageCodec::Raw => &all_views[i].image,
            ImageCodec::Png => &coded[i].0,
        }
    };
    let mask_bytes = |i: usize| -> Option<&[u8]> {
        match codec {
            ImageCodec::Raw => all_views[i].mask.as_deref(),
            ImageCodec::Png => coded[i].1.as_deref(),
        }
    };
    let mut pos = Vec::with_capacity(all_views.len() * 3);
    let mut rot = Vec::with_capacity(all_views.len() * 9);
    let mut intr = Vec::with_capacity(all_views.len() * 4);
    for v in &all_views {
        pos.extend_from_slice(&v.camera.position);
        rot.extend(v.camera.rotation.iter().flatten());
        intr.extend_from_slice(&v.camera.intrinsics.to_array());
    }
    let view_columns: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from_iter_values(
            all_views.iter().map(|v| v.width),
        )),
        Arc::new(UInt32Array::from_iter_values(
            all_views.iter().map(|v| v.height),
        )),
        Arc::new(BinaryArray::from_iter_values(
            (0..all_views.len()).map(image_bytes),
        )),
        Arc::new(BinaryArray::from_iter((0..all_views.len()).map(mask_bytes))),
        fixed_list(pos, 3),
        fixed_list(rot, 9),
        fixed_list(intr, 4),
    ];
    let views_struct = StructArray::try_new(view_fields(), view_columns, None)
        .map_err(|e| DatasetError::Batch(format!("building views: {e}")))?;
    let views = ListArray::try_new(
        Arc::new(Field::new(
            "element",
            DataType::Struct(view_fields()),
            false,
        )),
        OffsetBuffer::from_lengths(scenes.iter().map(|s| s.views.len())),
        Arc::new(views_struct),
        None,
    )
    .map_err(|e| DatasetError::Batch(format!("building views list: {e}")))?;

    let objects = objects_column(scenes)?;

    RecordBatch::try_new(
        arrow_schema(),
        vec![Arc::new(ids), Arc::new(views), Arc::new(objects)],
    )
    .map_err(|e| DatasetError::Batch(format!("building record batch: {e}")))
}

/// The `objects` column: each scene's object list (null where the scene has none).
fn objects_column(scenes: &[Scene]) -> Result<ListArray> {
    let objs: Vec<&ObjectMeta> = scenes
        .iter()
        .flat_map(|s| s.objects.iter().flatten())
        .collect();
    let mut opos = Vec::with_capacity(objs.len() * 3);
    for o in &objs {
        opos.extend_from_slice(&o.position);
    }
    let object_columns: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(objs.iter().map(|o| &o.shape))),
        Arc::new(StringArray::from_iter_values(objs.iter().map(|o| &o.color))),
        Arc::new(StringArray::from_iter_values(objs.iter().map(|o| &o.size))),
        Arc::new(StringArray::from_iter_values(
            objs.iter().map(|o| &o.material),
        )),
        fixed_list(opos, 3),
        Arc::new(Float32Array::from_iter_values(objs.iter().map(|o| o.yaw))),
    ];
    let objects_struct = StructArray::try_new(object_fields(), object_columns, None)
        .map_err(|e| DatasetError::Batch(format!("building objects: {e}")))?;
    ListArray::try_new(
        Arc::new(Field::new(
            "element",
            DataType::Struct(object_fields()),
            false,
        )),
        OffsetBuffer::from_lengths(
            scenes
                .iter()
                .map(|s| s.objects.as_ref().map_or(0, |o| o.len())),
        ),
        Arc::new(objects_struct),
        Some(NullBuffer::from_iter(
            scenes.iter().map(|s| s.objects.is_some()),
        )),
    )
    .map_err(|e| DatasetError::Batch(format!("building objects list: {e}")))
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

fn column<'a>(s: &'a StructArray, name: &str, path: &str) -> Result<&'a ArrayRef> {
    s.column_by_name(name)
        .ok_or_else(|| DatasetError::schema(path, format!("missing column `{name}`")))
}

fn f32_rows<'a>(a: &'a ArrayRef, n: usize, name: &str, path: &str) -> Result<&'a [f32]> {
    let l = a
        .as_fixed_size_list_opt()
        .filter(|l| l.value_length() as usize == n)
        .ok_or_else(|| {
            DatasetError::schema(path, format!("`{name}` is not FixedSizeList<Float32, {n}>"))
        })?;
    let vals = l
        .values()
        .as_primitive_opt::<Float32Type>()
        .ok_or_else(|| DatasetError::schema(path, format!("`{name}` items are not Float32")))?;
    // Sliced arrays: the list's offset is in rows.
    let start = l.offset() * n;
    Ok(&vals.values()[start..start + l.len() * n])
}

/// Decodes a record batch (possibly projected) into scenes, validating every view.
/// `path` names the file in errors.
pub fn batch_to_scenes(batch: &RecordBatch, path: &str) -> Result<Vec<Scene>> {
    batch_to_scenes_with(batch, path, ImageCodec::Raw)
}

/// [`batch_to_scenes`] of a file whose images and masks are in `codec` (PNGs decoded in
/// parallel).
pub fn batch_to_scenes_with(
    batch: &RecordBatch,
    path: &str,
    codec: ImageCodec,
) -> Result<Vec<Scene>> {
    let ids = batch
        .column_by_name("scene_id")
        .and_then(|c| c.as_primitive_opt::<arrow::datatypes::UInt64Type>())
        .ok_or_else(|| DatasetError::schema(path, "missing UInt64 column `scene_id`"))?;
    let views = batch
        .column_by_name("views")
        .and_then(|c| c.as_list_opt::<i32>())
        .ok_or_else(|| DatasetError::schema(path, "missing list column `views`"))?;
    let vs = views
        .values()
        .as_struct_opt()
        .ok_or_else(|| DatasetError::schema(path, "`views` items are not structs"))?;
    let widths = column(vs, "width", path)?
        .as_primitive_opt::<UInt32Type>()
        .ok_or_else(|| DatasetError::schema(path, "`views.width` is not UInt32"))?;
    let heights = column(vs, "height", path)?
        .as_primitive_opt::<UInt32Type>()
        .ok_or_else(|| DatasetError::schema(path, "`views.height` is not UInt32"))?;
    let (images, masks) = image_columns(vs, path)?;
    let (pos, rot, intr) = camera_columns(vs, path)?;

    let objects = batch
        .column_by_name("objects")
        .and_then(|c| c.as_list_opt::<i32>());
    let object_rows = match objects {
        Some(list) => Some((list, decode_objects(list, path)?)),
        None => None,
    };

    let mut decoded = match codec {
        ImageCodec::Raw => Vec::new(),
        ImageCodec::Png => decode_pngs(widths, heights, images, masks),
    };
    let offsets = views.value_offsets();
    let mut scenes = Vec::with_capacity(batch.num_rows());
    for row in 0..batch.num_rows() {
        let scene_id = ids.value(row);
        let (start, end) = (offsets[row] as usize, offsets[row + 1] as usize);
        if start == end {
            return Err(DatasetError::InvalidScene {
                path: path.to_string(),
                scene_id,
                reason: "scene has no views".into(),
            });
        }
        let mut scene_views = Vec::with_capacity(end - start);
        for (view, i) in (start..end).enumerate() {
            let camera = camera_at(pos, rot, intr, i);
            let (image, mask) =
                match codec {
                    ImageCodec::Raw => (
                        images.value(i).to_vec(),
                        masks.and_then(|m| m.is_valid(i).then(|| m.value(i).to_vec())),
                    ),
                    ImageCodec::Png => std::mem::replace(&mut decoded[i], Err(String::new()))
                        .map_err(|reason| DatasetError::InvalidView {
                            path: path.to_string(),
                            scene_id,
                            view,
                            reason,
                        })?,
                };
            let v = View {
                width: widths.value(i),
                height: heights.value(i),
                image,
                mask,
                camera,
            };
            v.validate().map_err(|reason| DatasetError::InvalidView {
                path: path.to_string(),
                scene_id,
                view,
                reason,
            })?;
            scene_views.push(v);
        }
        let objects = object_rows.as_ref().and_then(|(list, all)| {
            list.is_valid(row).then(|| {
                let o = list.value_offsets();
                all[o[row] as usize..o[row + 1] as usize].to_vec()
            })
        });
        scenes.push(Scene {
            id: scene_id,
            views: scene_views,
            objects,
        });
    }
    Ok(scenes)
}

/// A PNG view's pixels, or the reason it has none.
type Pixels = std::result::Result<(Vec<u8>, Option<Vec<u8>>), String>;

/// Every view's PNG image and mask decoded, in parallel.
fn decode_pngs(
    widths: &UInt32Array,
    heights: &UInt32Array,
    images: &BinaryArray,
    masks: Option<&BinaryArray>,
) -> Vec<Pixels> {
    (0..images.len())
        .into_par_iter()
        .map(|i| {
            let mask = masks.and_then(|m| m.is_valid(i).then(|| m.value(i)));
            crate::codec::decode_view(widths.value(i), heights.value(i), images.value(i), mask)
        })
        .collect()
}

/// The camera of view `i` from the flattened position, rotation and intrinsics columns.
/// The views' image bytes and, where the file has them, their mask bytes.
fn image_columns<'a>(
    vs: &'a StructArray,
    path: &str,
) -> Result<(&'a BinaryArray, Option<&'a BinaryArray>)> {
    let images = column(vs, "image", path)?
        .as_binary_opt::<i32>()
        .ok_or_else(|| DatasetError::schema(path, "`views.image` is not Binary"))?;
    let masks = match vs.column_by_name("mask") {
        Some(m) => Some(
            m.as_binary_opt::<i32>()
                .ok_or_else(|| DatasetError::schema(path, "`views.mask` is not Binary"))?,
        ),
        None => None,
    };
    Ok((images, masks))
}

/// The views' camera positions, rotations and intrinsics as flat rows of 3, 9 and 4.
fn camera_columns<'a>(
    vs: &'a StructArray,
    path: &str,
) -> Result<(&'a [f32], &'a [f32], &'a [f32])> {
    let pos = f32_rows(
        column(vs, "camera_position", path)?,
        3,
        "views.camera_position",
        path,
    )?;
    let rot = f32_rows(
        column(vs, "camera_rotation", path)?,
        9,
        "views.camera_rotation",
        path,
    )?;
    let intr = f32_rows(column(vs, "intrinsics", path)?, 4, "views.intrinsics", path)?;
    Ok((pos, rot, intr))
}

fn camera_at(pos: &[f32], rot: &[f32], intr: &[f32], i: usize) -> Camera {
    let r = &rot[9 * i..9 * i + 9];
    Camera {
        position: [pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]],
        rotation: [[r[0], r[1], r[2]], [r[3], r[4], r[5]], [r[6], r[7], r[8]]],
        intrinsics: Intrinsics::from_array([
            intr[4 * i],
            intr[4 * i + 1],
            intr[4 * i + 2],
            intr[4 * i + 3],
        ]),
    }
}

fn decode_objects(list: &ListArray, path: &str) -> Result<Vec<ObjectMeta>> {
    let s = list
        .values()
        .as_struct_opt()
        .ok_or_else(|| DatasetError::schema(path, "`objects` items are not structs"))?;
    let text = |name: &str| -> Result<&StringArray> {
        column(s, name, path)?
            .as_string_opt::<i32>()
            .ok_or_else(|| DatasetError::schema(path, format!("`objects.{name}` is not Utf8")))
    };
    let (shape, color, size, material) = (
        text("shape")?,
        text("color")?,
        text("size")?,
        text("material")?,
    );
    let pos = f32_rows(column(s, "position", path)?, 3, "objects.position", path)?;
    let yaw = column(s, "yaw", path)?
        .as_primitive_opt::<Float32Type>()
        .ok_or_else(|| DatasetError::schema(path, "`objects.yaw` is not Float32"))?;
    Ok((0..s.len())
        .map(|i| ObjectMeta {
            shape: shape.value(i).to_string(),
            color: color.value(i).to_string(),
            size: size.value(i).to_string(),
            material: material.value(i).to_string(),
            position: [pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]],
            yaw: yaw.value(i),
        })
        .collect())
}
