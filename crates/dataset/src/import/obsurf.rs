//! CLEVR-3D and MSN-Easy as ObSuRF released them (read by the public OSRT/SRT loaders):
//!
//! ```text
//! SRC/metadata.npz          camera_pos [S, V, 3]; shape [S, K] (> 0: object present);
//!                           optional 3d_coords [S, K, 3], color, size, material, rotation [S, K]
//! SRC/images/img_{s}_{v}.png    RGB or RGBA (the first three channels are taken)
//! SRC/masks/masks_{s}_{v}.png   8-bit instance ids, 0 = background (also `mask_{s}_{v}.png`)
//! SRC/depths/…                  not read
//! ```
//!
//! Cameras look at the origin with world `z` up, a 0.035 focal length on a 0.032-wide
//! sensor, rays through pixel centres, row 0 at the top. In the osrt convention
//! (`crate::camera`) that is [`Camera::look_at`] the origin with square pixels of
//! `fx = fy = 0.035 · width / 0.032` (350 px at 320×240) and the principal point at the
//! image centre: the loaders' ray of pixel `(u, v)` is `forward · 0.035 + right ·
//! (u + 0.5 − width/2) · p + down · (v + 0.5 − height/2) · p` with pixel pitch
//! `p = 0.032 / width`, which is ours divided by `fx`. Objects keep the release's values
//! (`shape`, `color`, `size`, `material` as their codes, `3d_coords` as the position,
//! `rotation` as the yaw, in the release's unit); object `k` is mask id `k + 1`.

use super::Source;
use super::npy::{Array, read_npz};
use crate::camera::{Camera, Intrinsics};
use crate::error::{DatasetError, Result};
use crate::math::Vec3;
use crate::scene::{ObjectMeta, Scene, View};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The arrays of `metadata.npz` the import reads; the release's others are not even
/// decompressed.
const METADATA_ARRAYS: [&str; 7] = [
    "camera_pos",
    "shape",
    "3d_coords",
    "color",
    "size",
    "material",
    "rotation",
];

/// Focal length and sensor width of the release's cameras (Blender units).
const FOCAL: f64 = 0.035;
const SENSOR_WIDTH: f64 = 0.032;

pub struct ObsurfSource {
    root: PathBuf,
    camera_pos: Array,
    shape: Array,
    metadata: BTreeMap<String, Array>,
    views: usize,
    has_masks: bool,
}

fn bad(path: impl AsRef<Path>, reason: impl Into<String>) -> DatasetError {
    DatasetError::Import {
        path: path.as_ref().display().to_string(),
        reason: reason.into(),
    }
}

impl ObsurfSource {
    /// Opens a release folder: reads and checks `metadata.npz`.
    pub fn open(root: &Path) -> Result<Self> {
        let meta_path = root.join("metadata.npz");
        let file = std::fs::File::open(&meta_path).map_err(|e| bad(&meta_path, e.to_string()))?;
        let mut metadata = read_npz(
            std::io::BufReader::new(file),
            &meta_path.display().to_string(),
            &METADATA_ARRAYS,
        )?;
        let mut take = |key: &str| {
            metadata
                .remove(key)
                .ok_or_else(|| bad(&meta_path, format!("no `{key}` array")))
        };
        let camera_pos = take("camera_pos")?;
        let shape = take("shape")?;
        let (cs, ss) = (&camera_pos.shape, &shape.shape);
        if cs.len() != 3 || cs[2] != 3 || camera_pos.number_row(0).is_none() {
            return Err(bad(
                &meta_path,
                format!("`camera_pos` is {cs:?}, expected numbers [S, V, 3]"),
            ));
        }
        if ss.len() != 2 || ss[0] != cs[0] || shape.number_row(0).is_none() {
            return Err(bad(
                &meta_path,
                format!("`shape` is {ss:?}, expected numbers [{}, K]", cs[0]),
            ));
        }
        // Optional per-object arrays must have a row per scene and an entry per object.
        metadata.retain(|k, a| {
            let fits = a.shape.first() == Some(&ss[0]) && a.shape.get(1) == Some(&ss[1]);
            if !fits {
                eprintln!(
                    "{}: `{k}` {:?} does not fit [S, K]; left out",
                    meta_path.display(),
                    a.shape
                );
            }
            fits
        });
        Ok(Self {
            views: cs[1],
            has_masks: root.join("masks").is_dir(),
            root: root.to_path_buf(),
            camera_pos,
            shape,
            metadata,
        })
    }

    /// The mask file of a view, in either spelling of the releases.
    fn mask_path(&self, s: u64, v: usize) -> PathBuf {
        let plural = self.root.join(format!("masks/masks_{s}_{v}.png"));
        if plural.exists() {
            return plural;
        }
        self.root.join(format!("masks/mask_{s}_{v}.png"))
    }

    fn view(&self, s: u64, v: usize) -> Result<View> {
        let img_path = self.root.join(format!("images/img_{s}_{v}.png"));
        let img = super::open_image(&img_path)
            .map_err(|e| bad(&img_path, format!("scene {s}, view {v}: {e}")))?
            .into_rgb8();
        let (width, height) = img.dimensions();
        let mask = if self.has_masks {
            let mask_path = self.mask_path(s, v);
            let m = super::open_image(&mask_path)
                .map_err(|e| bad(&mask_path, format!("scene {s}, view {v}: {e}")))?;
            let image::DynamicImage::ImageLuma8(m) = m else {
                return Err(bad(
                    &mask_path,
                    format!("{:?}, expected 8-bit instance ids", m.color()),
                ));
            };
            if m.dimensions() != (width, height) {
                return Err(bad(
                    &mask_path,
                    format!("{:?}, the image is {width}x{height}", m.dimensions()),
                ));
            }
            Some(m.into_raw())
        } else {
            None
        };
        let p = self
            .camera_pos
            .number_row(s as usize)
            .expect("checked at open");
        let pos = Vec3::new(p[3 * v], p[3 * v + 1], p[3 * v + 2]);
        let f = FOCAL * width as f64 / SENSOR_WIDTH;
        let intrinsics = Intrinsics {
            fx: f as f32,
            fy: f as f32,
            cx: width as f32 / 2.0,
            cy: height as f32 / 2.0,
        };
        let camera = Camera::look_at(pos, Vec3::new(0.0, 0.0, 0.0), intrinsics).map_err(|e| {
            bad(
                self.root.join("metadata.npz"),
                format!("scene {s}, view {v}: {e}"),
            )
        })?;
        Ok(View {
            width,
            height,
            image: img.into_raw(),
            mask,
            camera,
        })
    }

    fn objects(&self, s: u64) -> Vec<ObjectMeta> {
        let s = s as usize;
        let shape = self.shape.number_row(s).expect("checked at open");
        let text = |key: &str, k: usize| {
            self.metadata
                .get(key)
                .and_then(|a| a.text_at(s, k * a.row_len() / shape.len()))
                .unwrap_or_default()
        };
        let number = |key: &str, k: usize, j: usize| {
            self.metadata
                .get(key)
                .and_then(|a| {
                    let per = a.row_len() / shape.len();
                    a.number_row(s).and_then(|r| r.get(k * per + j).copied())
                })
                .unwrap_or(0.0) as f32
        };
        (0..shape.len())
            .filter(|&k| shape[k] > 0.0)
            .map(|k| ObjectMeta {
                shape: self.shape.text_at(s, k).unwrap_or_default(),
                color: text("color", k),
                size: text("size", k),
                material: text("material", k),
                position: [0, 1, 2].map(|j| number("3d_coords", k, j)),
                yaw: number("rotation", k, 0),
            })
            .collect()
    }
}

impl Source for ObsurfSource {
    fn num_scenes(&self) -> u64 {
        self.shape.shape[0] as u64
    }

    fn counts(&self, index: u64) -> (usize, Option<usize>) {
        let row = self.shape.number_row(index as usize).unwrap_or(&[]);
        (self.views, Some(row.iter().filter(|&&x| x > 0.0).count()))
    }

    fn scene(&self, index: u64) -> Result<Scene> {
        let views = (0..self.views)
            .map(|v| self.view(index, v))
            .collect::<Result<Vec<_>>>()?;
        Ok(Scene {
            id: index,
            views,
            objects: Some(self.objects(index)),
        })
    }

    fn image_size(&self) -> Result<[u32; 2]> {
        let first = self.root.join("images/img_0_0.png");
        super::image_dimensions(&first).map_err(|e| bad(&first, format!("scene 0, view 0: {e}")))
    }

    fn has_masks(&self) -> bool {
        self.has_masks
    }

    fn view_origin(&self, index: u64, view: usize) -> String {
        self.root
            .join(format!("images/img_{index}_{view}.png"))
            .display()
            .to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::import::npy::Values;

    /// One scene of one view whose image files are those in `root`.
    fn source(root: &Path) -> ObsurfSource {
        ObsurfSource {
            root: root.to_path_buf(),
            camera_pos: Array {
                shape: vec![1, 1, 3],
                values: Values::Numbers(vec![1.0, 2.0, 3.0]),
            },
            shape: Array {
                shape: vec![1, 1],
                values: Values::Numbers(vec![1.0]),
            },
            metadata: BTreeMap::new(),
            views: 1,
            has_masks: false,
        }
    }

    /// The dataset's view size comes from the first image's header: a header announcing
    /// more than one image may decode to is refused there, naming that file, before its
    /// size is believed.
    #[test]
    fn the_view_size_is_not_taken_from_a_header_past_the_decode_limit() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("images")).unwrap();
        let first = dir.path().join("images/img_0_0.png");
        std::fs::write(&first, crate::codec::tests::png_header_only(32, 24)).unwrap();
        assert_eq!(source(dir.path()).image_size().unwrap(), [32, 24]);
        std::fs::write(
            &first,
            crate::codec::tests::png_header_only(100_000, 100_000),
        )
        .unwrap();
        let e = source(dir.path()).image_size().unwrap_err().to_string();
        assert!(
            e.contains(&first.display().to_string()) && e.contains("more than the 64 MiB"),
            "{e}"
        );
    }
}
