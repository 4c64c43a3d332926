//! Camera model and its convention. Every view in a dataset carries one [`Camera`].
//!
//! # Convention
//! - **World**: right-handed, `z` up, the floor is the plane `z = 0`.
//! - **Camera frame** (OpenCV axes): `x` right, `y` down, `z` forward (viewing direction).
//! - **`rotation`** is camera-to-world, stored row-major: `rotation[i][j]` is row `i`,
//!   column `j`. Its columns are the camera's right, down and forward axes expressed in
//!   world coordinates, so a camera-frame vector `d_c` maps to `d_w = R · d_c`.
//! - **`position`** is the camera centre in world coordinates; it is every ray's origin.
//! - **Intrinsics** are pinhole, in pixels: `fx, fy` focal lengths, `(cx, cy)` principal
//!   point. Pixel `(u, v)` is column `u`, row `v`; row 0 is the **top** of the image; a
//!   pixel's centre is `(u + 0.5, v + 0.5)`, so for a centred principal point
//!   `cx = width / 2`, `cy = height / 2`.
//! - The ray of pixel `(u, v)`: `d_c = ((u + 0.5 − cx) / fx, (v + 0.5 − cy) / fy, 1)`,
//!   direction `normalize(R · d_c)`, origin `position`.
//!
//! This is the convention of kubric/MSN-Hard (OpenCV extrinsics inverted to
//! camera-to-world) and matches ObSuRF's CLEVR-3D cameras after conversion.

use crate::math::Vec3;
use serde::{Deserialize, Serialize};

/// Pinhole intrinsics in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
}

impl Intrinsics {
    /// Square pixels, principal point at the image centre, horizontal field of view `fov_x`.
    pub fn from_fov(fov_x_radians: f64, width: u32, height: u32) -> Self {
        let fx = (width as f64 / 2.0) / (fov_x_radians / 2.0).tan();
        Self {
            fx: fx as f32,
            fy: fx as f32,
            cx: width as f32 / 2.0,
            cy: height as f32 / 2.0,
        }
    }

    pub fn to_array(self) -> [f32; 4] {
        [self.fx, self.fy, self.cx, self.cy]
    }

    pub fn from_array(a: [f32; 4]) -> Self {
        Self {
            fx: a[0],
            fy: a[1],
            cx: a[2],
            cy: a[3],
        }
    }
}

/// A calibrated camera (see the module docs for the convention).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub position: [f32; 3],
    /// Camera-to-world rotation, row-major.
    pub rotation: [[f32; 3]; 3],
    pub intrinsics: Intrinsics,
}

/// Largest tolerated deviation of `RᵀR` from the identity (f32 storage keeps ~1e-7).
const ORTHONORMAL_TOL: f64 = 1e-3;

impl Camera {
    /// A camera at `position` looking at `target`, with world `z` as up.
    ///
    /// Fails when the viewing direction is zero or parallel to `z` (no unique roll).
    pub fn look_at(position: Vec3, target: Vec3, intrinsics: Intrinsics) -> Result<Self, String> {
        let forward = target - position;
        if forward.norm().is_nan() || forward.norm() <= 1e-12 {
            return Err("camera position equals its target: zero viewing direction".into());
        }
        let forward = forward.normalized();
        let right = forward.cross(Vec3::Z);
        if right.norm().is_nan() || right.norm() <= 1e-9 {
            return Err("viewing direction is parallel to the up axis".into());
        }
        let right = right.normalized();
        let down = forward.cross(right);
        let cols = [right, down, forward];
        let mut rotation = [[0f32; 3]; 3];
        for (j, c) in cols.iter().enumerate() {
            let c = c.to_f32();
            for i in 0..3 {
                rotation[i][j] = c[i];
            }
        }
        Ok(Self {
            position: position.to_f32(),
            rotation,
            intrinsics,
        })
    }

    /// Column `j` of the rotation: 0 = right, 1 = down, 2 = forward, in world coordinates.
    pub fn axis(&self, j: usize) -> Vec3 {
        Vec3::new(
            self.rotation[0][j] as f64,
            self.rotation[1][j] as f64,
            self.rotation[2][j] as f64,
        )
    }

    pub fn position(&self) -> Vec3 {
        Vec3::from_f32(self.position)
    }

    /// This camera expressed in `reference`'s camera frame: position `Rᵣᵀ(p − pᵣ)`,
    /// rotation `Rᵣᵀ R`. The rays of the result are this camera's rays seen from the
    /// reference camera, so moving every camera of a scene by one rigid motion leaves them
    /// unchanged (what an unposed model relies on).
    pub fn relative_to(&self, reference: &Camera) -> Camera {
        let axes = [reference.axis(0), reference.axis(1), reference.axis(2)];
        let p = self.position() - reference.position();
        let position = Vec3::new(axes[0].dot(p), axes[1].dot(p), axes[2].dot(p)).to_f32();
        let mut rotation = [[0f32; 3]; 3];
        for (i, row) in rotation.iter_mut().enumerate() {
            for (j, r) in row.iter_mut().enumerate() {
                *r = axes[i].dot(self.axis(j)) as f32;
            }
        }
        Camera {
            position,
            rotation,
            intrinsics: self.intrinsics,
        }
    }

    /// Unit world-space direction through continuous image coordinates `(x, y)` in pixels
    /// (pixel centres are at half-integers).
    pub fn direction_at(&self, x: f64, y: f64) -> Vec3 {
        let k = &self.intrinsics;
        let dc = Vec3::new(
            (x - k.cx as f64) / k.fx as f64,
            (y - k.cy as f64) / k.fy as f64,
            1.0,
        );
        (self.axis(0) * dc.x + self.axis(1) * dc.y + self.axis(2) * dc.z).normalized()
    }

    /// Unit direction of the ray through the centre of pixel `(u, v)` (column, row).
    pub fn pixel_direction(&self, u: u32, v: u32) -> Vec3 {
        self.direction_at(u as f64 + 0.5, v as f64 + 0.5)
    }

    /// Projects a world point to continuous pixel coordinates; `None` behind the camera.
    pub fn project(&self, p: Vec3) -> Option<(f64, f64)> {
        let d = p - self.position();
        let z = d.dot(self.axis(2));
        if z <= 1e-9 {
            return None;
        }
        let k = &self.intrinsics;
        let x = d.dot(self.axis(0)) / z * k.fx as f64 + k.cx as f64;
        let y = d.dot(self.axis(1)) / z * k.fy as f64 + k.cy as f64;
        Some((x, y))
    }

    /// Checks what the ray derivation relies on: finite values, an orthonormal
    /// right-handed rotation, and positive focal lengths. The message says what is wrong.
    pub fn validate(&self) -> Result<(), String> {
        let all = self
            .position
            .into_iter()
            .chain(self.rotation.iter().flatten().copied())
            .chain(self.intrinsics.to_array());
        if let Some(bad) = all.clone().find(|v| !v.is_finite()) {
            return Err(format!("camera has a non-finite value ({bad})"));
        }
        let k = self.intrinsics;
        if !(k.fx > 0.0 && k.fy > 0.0) {
            return Err(format!(
                "focal lengths must be positive, found fx = {}, fy = {}",
                k.fx, k.fy
            ));
        }
        let cols = [self.axis(0), self.axis(1), self.axis(2)];
        let mut worst: f64 = 0.0;
        for i in 0..3 {
            for j in 0..3 {
                let expected = if i == j { 1.0 } else { 0.0 };
                worst = worst.max((cols[i].dot(cols[j]) - expected).abs());
            }
        }
        if worst > ORTHONORMAL_TOL {
            return Err(format!(
                "rotation is not orthonormal (max |RᵀR − I| = {worst:.3e}, tolerance {ORTHONORMAL_TOL:e}); \
                 a zero or degenerate axis gives no viewing direction"
            ));
        }
        let det = cols[0].dot(cols[1].cross(cols[2]));
        if det < 0.0 {
            return Err(
                "rotation is a reflection (determinant −1), expected a proper rotation".into(),
            );
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam(w: u32, h: u32) -> Camera {
        let k = Intrinsics::from_fov(50f64.to_radians(), w, h);
        Camera::look_at(Vec3::new(7.0, -6.0, 5.0), Vec3::ZERO, k).unwrap()
    }

    #[test]
    fn look_at_axes_follow_the_convention() {
        // Looking along +y with z up: right is +x, down is −z.
        let k = Intrinsics::from_fov(1.0, 8, 8);
        let c = Camera::look_at(Vec3::ZERO, Vec3::new(0.0, 5.0, 0.0), k).unwrap();
        let close = |a: Vec3, b: Vec3| (a - b).norm() < 1e-6;
        assert!(close(c.axis(0), Vec3::new(1.0, 0.0, 0.0)));
        assert!(close(c.axis(1), Vec3::new(0.0, 0.0, -1.0)));
        assert!(close(c.axis(2), Vec3::new(0.0, 1.0, 0.0)));
        c.validate().unwrap();
    }

    #[test]
    fn projection_inverts_pixel_rays() {
        let c = cam(32, 24);
        let d = c.pixel_direction(5, 17);
        let (x, y) = c.project(c.position() + d * 3.0).unwrap();
        assert!((x - 5.5).abs() < 1e-4 && (y - 17.5).abs() < 1e-4, "{x} {y}");
        // Top-left pixel looks up and left of the forward axis: row 0 is the top.
        let tl = c.pixel_direction(0, 0);
        assert!(tl.dot(c.axis(0)) < 0.0 && tl.dot(c.axis(1)) < 0.0);
        assert!(
            tl.z > c.axis(2).z,
            "row 0 must look higher in the world than the centre"
        );
    }

    /// A camera relative to itself sits at the origin looking along +z; relative poses
    /// do not change when both cameras move by one rigid motion.
    #[test]
    fn relative_cameras_ignore_a_shared_rigid_motion() {
        let a = cam(16, 12);
        let k = a.intrinsics;
        let b = Camera::look_at(Vec3::new(-3.0, 8.0, 2.0), Vec3::new(0.5, 0.0, 0.0), k).unwrap();
        let own = a.relative_to(&a);
        assert!(own.position().norm() < 1e-5);
        assert!((own.axis(2) - Vec3::new(0.0, 0.0, 1.0)).norm() < 1e-6);
        // Rotate the world 70° about z and shift it: the same scene, elsewhere.
        let (s, c) = 70f64.to_radians().sin_cos();
        let moved = |cam: &Camera| {
            let m = |v: Vec3| Vec3::new(c * v.x - s * v.y, s * v.x + c * v.y, v.z);
            let p = m(cam.position()) + Vec3::new(4.0, -2.0, 1.5);
            Camera::look_at(p, p + m(cam.axis(2)), k).unwrap()
        };
        let (before, after) = (b.relative_to(&a), moved(&b).relative_to(&moved(&a)));
        assert!((before.position() - after.position()).norm() < 1e-4);
        for j in 0..3 {
            assert!((before.axis(j) - after.axis(j)).norm() < 1e-5);
        }
        after.validate().unwrap();
    }

    #[test]
    fn validation_rejects_degenerate_cameras() {
        let good = cam(8, 8);
        let mut nan = good;
        nan.position[1] = f32::NAN;
        assert!(nan.validate().unwrap_err().contains("non-finite"));
        let mut zero = good;
        zero.rotation[0][2] = 0.0;
        zero.rotation[1][2] = 0.0;
        zero.rotation[2][2] = 0.0;
        assert!(zero.validate().unwrap_err().contains("orthonormal"));
        let mut mirror = good;
        for row in mirror.rotation.iter_mut() {
            row[0] = -row[0];
        }
        assert!(mirror.validate().unwrap_err().contains("reflection"));
        let mut f = good;
        f.intrinsics.fx = 0.0;
        assert!(f.validate().unwrap_err().contains("focal"));
        assert!(Camera::look_at(Vec3::ZERO, Vec3::ZERO, good.intrinsics).is_err());
        assert!(Camera::look_at(Vec3::ZERO, Vec3::new(0.0, 0.0, -3.0), good.intrinsics).is_err());
    }
}
