//! In-memory scene types: what one Parquet row decodes to.

use crate::camera::Camera;
use serde::{Deserialize, Serialize};

/// One view of a scene: an RGB8 image, its optional instance mask and its camera.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    pub width: u32,
    pub height: u32,
    /// Row-major RGB8, `height * width * 3` bytes, row 0 at the top.
    pub image: Vec<u8>,
    /// Row-major instance ids, `height * width` bytes: 0 = background, `k` = object `k`.
    /// `None` when the dataset has no masks or the reader did not project them.
    pub mask: Option<Vec<u8>>,
    pub camera: Camera,
}

impl View {
    pub fn num_pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// RGB of pixel `(u, v)` (column, row).
    pub fn rgb(&self, u: u32, v: u32) -> [u8; 3] {
        let i = 3 * (v as usize * self.width as usize + u as usize);
        [self.image[i], self.image[i + 1], self.image[i + 2]]
    }

    /// Checks image and mask sizes and the camera; the message says what is wrong.
    pub fn validate(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!(
                "image size {}x{} is empty",
                self.width, self.height
            ));
        }
        let px = self.num_pixels();
        // 2^32 × 2^32 × 3 overflows even 64 bits: a crafted size is an error, not a panic.
        let Some(rgb) = px.checked_mul(3) else {
            return Err(format!(
                "image size {}x{} is too large",
                self.width, self.height
            ));
        };
        if self.image.len() != rgb {
            return Err(format!(
                "image has {} bytes, expected {} for {}x{} RGB8",
                self.image.len(),
                rgb,
                self.width,
                self.height
            ));
        }
        if let Some(m) = &self.mask
            && m.len() != px
        {
            return Err(format!(
                "mask has {} bytes, expected {} for {}x{}",
                m.len(),
                px,
                self.width,
                self.height
            ));
        }
        self.camera.validate()
    }
}

/// Per-object metadata, as the generator (or an importer) knows it. Object `k` in the
/// list is instance id `k + 1` in the masks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ObjectMeta {
    pub shape: String,
    pub color: String,
    pub size: String,
    pub material: String,
    /// Centre of the object's base on the floor, world coordinates.
    pub position: [f32; 3],
    /// Rotation about the world `z` axis, radians.
    pub yaw: f32,
}

/// One scene: as many views as it has (no padding) and optional object metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene {
    pub id: u64,
    pub views: Vec<View>,
    pub objects: Option<Vec<ObjectMeta>>,
}

impl Scene {
    /// Number of objects, from metadata where present, otherwise the largest mask id.
    pub fn num_objects(&self) -> Option<usize> {
        if let Some(o) = &self.objects {
            return Some(o.len());
        }
        let mut max = None;
        for v in &self.views {
            let m = v.mask.as_ref()?;
            let k = m.iter().copied().max().unwrap_or(0) as usize;
            max = Some(max.map_or(k, |x: usize| x.max(k)));
        }
        max
    }
}
