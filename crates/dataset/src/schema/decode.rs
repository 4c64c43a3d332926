//! A record batch back into scenes: the reading half of the schema, every column's type
//! checked and every view validated, PNGs decoded in parallel, errors naming the file,
//! the scene and the view. Its own file because it trusts nothing of the file it reads,
//! unlike the writing half (`encode`).

use super::ImageCodec;
use crate::camera::{Camera, Intrinsics};
use crate::error::{DatasetError, Result};
use crate::scene::{ObjectMeta, Scene, View};
use arrow::array::{
    Array, ArrayRef, AsArray, BinaryArray, ListArray, RecordBatch, StringArray, StructArray,
    UInt32Array,
};
use arrow::datatypes::{Float32Type, UInt32Type};
use rayon::prelude::*;

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

/// Decodes a record batch (possibly projected) of a file whose images and masks are in
/// `codec` into scenes (PNGs decoded in parallel), validating every view. `path` names the
/// file in errors.
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

/// The camera of view `i` from the flattened position, rotation and intrinsics columns.
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
