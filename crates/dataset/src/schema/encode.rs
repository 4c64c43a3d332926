//! Scenes into a record batch: the writing half of the schema, images and masks raw or
//! PNG-encoded in parallel. Its own file because it shares only the field lists with the
//! reading half ([`super::batch_to_scenes_with`]), which checks everything this trusts.

use super::{ImageCodec, arrow_schema, object_fields, view_fields};
use crate::error::{DatasetError, Result};
use crate::scene::{ObjectMeta, Scene, View};
use arrow::array::{
    ArrayRef, BinaryArray, FixedSizeListArray, Float32Array, ListArray, RecordBatch, StringArray,
    StructArray, UInt32Array, UInt64Array,
};
use arrow::buffer::{NullBuffer, OffsetBuffer};
use arrow::datatypes::{DataType, Field};
use rayon::prelude::*;
use std::sync::Arc;

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
