//! MSN-Hard: Kubric's `multi_shapenet_conditional` frames (sunds' `multi_shapenet`
//! builder, data version 2.8.0), as TFDS TFRecord shards (`*-train.tfrecord-NNNNN-of-MMMMM`,
//! `*-val…`, `*-test…`). One `tf.train.Example` per scene (`tfrecord.rs` frames it), its
//! nested features flattened with `/`:
//!
//! ```text
//! scene_name                              bytes_list  "scene_{seed}"
//! cameras/camera_K/color_image            bytes_list  PNG, RGB8 (128×128)
//! cameras/camera_K/instance_image         bytes_list  PNG, 8-bit grey: Kubric's instance ids
//! cameras/camera_K/intrinsics/K           float_list  3×3 row-major, pixels
//! cameras/camera_K/extrinsics/R           float_list  3×3 row-major, world → camera
//! cameras/camera_K/extrinsics/t           float_list  3, world → camera
//! (depth_image, category_image, distortion, pose, frame_name, … are not read)
//! ```
//!
//! for K = 0 … 9. Extrinsics are OpenCV axes (x right, y down, z forward):
//! `X_cam = R · X_world + t`, so the camera sits at `−Rᵀ t` and its camera-to-world
//! rotation is `Rᵀ`, the osrt convention (`crate::camera`); rays go through pixel centres
//! (+0.5), as sunds' own ray task does. Masks follow the public OSRT loader:
//! `clip(instance, 1, 34) − 1`, so ids 0 and 1 are both background (0) and objects are
//! 1 … 33. Scene ids are the record's position over the shards (train, then val, then
//! test, files in name order); object counts are not in the records.
//!
//! Facts gathered from the public sunds builder (frames_builder.py, utils.py), TFDS's
//! example serializer (images as PNG bytes, float tensors as flat float lists) and the
//! public OSRT loader (osrt/data/multishapenet.py). The public builder's snapshot has no
//! `multi_shapenet_conditional` configuration (the loaders say 128×128 and 10 cameras):
//! the camera count and image size are read from the records themselves, and intrinsics
//! come from each camera's `K`.

use super::tfrecord::{RecordRef, index_file, read_record};
use super::{Source, Splits};
use crate::camera::{Camera, Intrinsics};
use crate::error::{DatasetError, Result};
use crate::scene::{Scene, View};
use prost::Message;
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// The generated `tf.train.Example` messages (`proto/tensorflow/example.proto`).
pub mod tf {
    include!(concat!(env!("OUT_DIR"), "/tensorflow.rs"));
}

/// The masks' largest id after `clip(instance, 1, 34) − 1`.
const LAST_ID: u8 = 33;

pub struct KubricSource {
    dir: PathBuf,
    records: Vec<RecordRef>,
    splits: Splits,
    views: usize,
    image_size: [u32; 2],
}

fn bad(path: impl AsRef<Path>, reason: impl Into<String>) -> DatasetError {
    DatasetError::Import {
        path: path.as_ref().display().to_string(),
        reason: reason.into(),
    }
}

/// The shards of `split` in `dir`, by name.
fn shards(dir: &Path, split: &str) -> Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| bad(dir, e.to_string()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.contains(&format!("-{split}.tfrecord")))
        })
        .collect();
    files.sort();
    Ok(files)
}

impl KubricSource {
    /// Indexes every shard of `dir` (record headers only) and reads the first record for
    /// the view count and image size.
    pub fn open(dir: &Path) -> Result<Self> {
        let mut records = Vec::new();
        let mut bounds = Vec::new();
        for split in ["train", "val", "test"] {
            let start = records.len() as u64;
            let files = shards(dir, split)?;
            // The first bad shard in name order is the one named, however the threads ran.
            let indexed: Vec<Result<Vec<RecordRef>>> =
                files.par_iter().map(|f| index_file(f)).collect();
            let indexed = indexed.into_iter().collect::<Result<Vec<_>>>()?;
            records.extend(indexed.into_iter().flatten());
            bounds.push(start..records.len() as u64);
        }
        if records.is_empty() {
            return Err(bad(
                dir,
                "no TFRecord shards (*-train.tfrecord-*, *-val.tfrecord-*, *-test.tfrecord-*)",
            ));
        }
        let mut src = Self {
            dir: dir.to_path_buf(),
            records,
            splits: Splits {
                train: bounds[0].clone(),
                val: bounds[1].clone(),
                test: bounds[2].clone(),
            },
            views: 0,
            image_size: [0, 0],
        };
        let first = src.example(0)?;
        let features = &first.features.as_ref().map(|f| &f.feature);
        src.views = (0..)
            .take_while(|k| {
                features.is_some_and(|f| f.contains_key(&format!("cameras/camera_{k}/color_image")))
            })
            .count();
        if src.views == 0 {
            return Err(bad(
                &src.records[0].file,
                "record 0 has no cameras/camera_0/color_image",
            ));
        }
        let v = src.view(&first, 0, 0)?;
        src.image_size = [v.width, v.height];
        Ok(src)
    }

    /// The shards' own splits, as ranges of record positions.
    pub fn splits(&self) -> Splits {
        self.splits.clone()
    }

    fn example(&self, index: u64) -> Result<tf::Example> {
        let r = &self.records[index as usize];
        let bytes = read_record(r, index as usize)?;
        tf::Example::decode(bytes.as_slice()).map_err(|e| {
            bad(
                &r.file,
                format!("record at byte {}: not a tf.train.Example: {e}", r.offset),
            )
        })
    }

    fn view(&self, ex: &tf::Example, index: u64, k: usize) -> Result<View> {
        let r = &self.records[index as usize];
        let at = |key: &str| format!("record {index} at byte {}: `{key}`", r.offset);
        let feature = |key: &str| {
            ex.features
                .as_ref()
                .and_then(|f| f.feature.get(key))
                .and_then(|f| f.kind.as_ref())
                .ok_or_else(|| bad(&r.file, format!("{} is missing", at(key))))
        };
        let bytes = |key: &str| match feature(key)? {
            tf::feature::Kind::BytesList(b) if b.value.len() == 1 => Ok(b.value[0].clone()),
            _ => Err(bad(&r.file, format!("{} is not one bytes value", at(key)))),
        };
        let floats = |key: &str, n: usize| match feature(key)? {
            tf::feature::Kind::FloatList(f) if f.value.len() == n => Ok(f.value.clone()),
            _ => Err(bad(&r.file, format!("{} is not {n} floats", at(key)))),
        };
        let p = format!("cameras/camera_{k}/");
        let png = |key: &str| {
            let b = bytes(key)?;
            super::decode_png(&b).map_err(|e| bad(&r.file, format!("{}: {e}", at(key))))
        };
        let color = png(&format!("{p}color_image"))?.into_rgb8();
        let (width, height) = color.dimensions();
        let instance = png(&format!("{p}instance_image"))?;
        let image::DynamicImage::ImageLuma8(ids) = instance else {
            return Err(bad(
                &r.file,
                format!("{} is not 8-bit grey", at(&format!("{p}instance_image"))),
            ));
        };
        if ids.dimensions() != (width, height) {
            return Err(bad(
                &r.file,
                format!(
                    "{}: another size than the colour image",
                    at(&format!("{p}instance_image"))
                ),
            ));
        }
        let mask = ids
            .into_raw()
            .into_iter()
            .map(|i| i.clamp(1, LAST_ID + 1) - 1)
            .collect();
        let kk = floats(&format!("{p}intrinsics/K"), 9)?;
        let rr = floats(&format!("{p}extrinsics/R"), 9)?;
        let t = floats(&format!("{p}extrinsics/t"), 3)?;
        // Camera-to-world is Rᵀ; the centre −Rᵀ t.
        let rotation = [0, 1, 2].map(|i| [0, 1, 2].map(|j| rr[3 * j + i]));
        let position = [0, 1, 2].map(|i| -(0..3).map(|j| rr[3 * j + i] * t[j]).sum::<f32>());
        let camera = Camera {
            position,
            rotation,
            intrinsics: Intrinsics {
                fx: kk[0],
                fy: kk[4],
                cx: kk[2],
                cy: kk[5],
            },
        };
        let view = View {
            width,
            height,
            image: color.into_raw(),
            mask: Some(mask),
            camera,
        };
        view.validate()
            .map_err(|e| bad(&r.file, format!("record {index}, camera {k}: {e}")))?;
        Ok(view)
    }
}

impl Source for KubricSource {
    fn num_scenes(&self) -> u64 {
        self.records.len() as u64
    }

    fn counts(&self, _index: u64) -> (usize, Option<usize>) {
        (self.views, None)
    }

    fn scene(&self, index: u64) -> Result<Scene> {
        let ex = self.example(index)?;
        let views = (0..self.views)
            .map(|k| self.view(&ex, index, k))
            .collect::<Result<Vec<_>>>()?;
        Ok(Scene {
            id: index,
            views,
            objects: None,
        })
    }

    fn image_size(&self) -> Result<[u32; 2]> {
        Ok(self.image_size)
    }

    fn has_masks(&self) -> bool {
        true
    }

    fn view_origin(&self, index: u64, view: usize) -> String {
        let r = &self.records[index as usize];
        format!(
            "{}: record {index} at byte {}, camera {view}",
            r.file.display(),
            r.offset
        )
    }
}

impl std::fmt::Debug for KubricSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "KubricSource({}, {} records)",
            self.dir.display(),
            self.records.len()
        )
    }
}
