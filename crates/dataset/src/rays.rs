//! Rays derived at load time from a view's camera (never stored): origin = camera centre,
//! unit direction through each pixel centre (convention in [`crate::camera`]).

use crate::camera::Camera;

/// Per-pixel rays of one view, row-major, 3 floats per pixel.
#[derive(Debug, Clone, PartialEq)]
pub struct Rays {
    /// `[h * w * 3]`
    pub origins: Vec<f32>,
    /// `[h * w * 3]`, unit length
    pub directions: Vec<f32>,
}

/// Origin and unit direction of pixel `(u, v)` (column, row).
pub fn pixel_ray(camera: &Camera, u: u32, v: u32) -> ([f32; 3], [f32; 3]) {
    (camera.position, camera.pixel_direction(u, v).to_f32())
}

/// Rays of every pixel of a `width × height` view, row 0 first.
pub fn view_rays(camera: &Camera, width: u32, height: u32) -> Rays {
    view_rays_strided(camera, width, height, 1)
}

/// The rays of every `stride`-th pixel along both axes from pixel `stride / 2` on, in
/// row-major order: each the full-resolution ray of its pixel.
pub fn view_rays_strided(camera: &Camera, width: u32, height: u32, stride: usize) -> Rays {
    let (width, height) = (width as usize, height as usize);
    let n = width.div_ceil(stride) * height.div_ceil(stride);
    let mut origins = Vec::with_capacity(n * 3);
    let mut directions = Vec::with_capacity(n * 3);
    for v in (stride / 2..height).step_by(stride) {
        for u in (stride / 2..width).step_by(stride) {
            let (u, v) = (u as u32, v as u32);
            let (o, d) = pixel_ray(camera, u, v);
            origins.extend_from_slice(&o);
            directions.extend_from_slice(&d);
        }
    }
    Rays {
        origins,
        directions,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use crate::math::Vec3;

    fn camera(w: u32, h: u32) -> Camera {
        let k = Intrinsics::from_fov(45f64.to_radians(), w, h);
        Camera::look_at(Vec3::new(3.0, -4.0, 2.5), Vec3::new(0.2, 0.1, 0.0), k).unwrap()
    }

    fn dir(r: &Rays, w: u32, u: u32, v: u32) -> Vec3 {
        let i = 3 * (v as usize * w as usize + u as usize);
        Vec3::new(
            r.directions[i] as f64,
            r.directions[i + 1] as f64,
            r.directions[i + 2] as f64,
        )
    }

    #[test]
    fn centre_pixel_ray_is_the_forward_axis() {
        // Odd sizes put a pixel centre exactly on the principal point.
        let (w, h) = (33, 21);
        let c = camera(w, h);
        let r = view_rays(&c, w, h);
        let d = dir(&r, w, w / 2, h / 2);
        assert!((d - c.axis(2)).norm() < 1e-6, "{d:?} vs {:?}", c.axis(2));
        assert_eq!(&r.origins[..3], &c.position);
    }

    #[test]
    fn rays_are_unit_length() {
        let (w, h) = (16, 12);
        let r = view_rays(&camera(w, h), w, h);
        assert_eq!(r.directions.len(), (w * h * 3) as usize);
        for d in r.directions.chunks(3) {
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            assert!((n - 1.0).abs() < 1e-6, "{n}");
        }
    }

    #[test]
    fn corner_rays_are_symmetric_about_the_forward_axis() {
        let (w, h) = (20, 14);
        let c = camera(w, h);
        let r = view_rays(&c, w, h);
        let (right, down, fwd) = (c.axis(0), c.axis(1), c.axis(2));
        let corners = [(0, 0), (w - 1, 0), (0, h - 1), (w - 1, h - 1)];
        let ds: Vec<Vec3> = corners.iter().map(|&(u, v)| dir(&r, w, u, v)).collect();
        // Same angle to the forward axis, mirrored right/down components.
        for d in &ds {
            assert!((d.dot(fwd) - ds[0].dot(fwd)).abs() < 1e-6);
        }
        assert!((ds[0].dot(right) + ds[1].dot(right)).abs() < 1e-6);
        assert!((ds[0].dot(down) + ds[2].dot(down)).abs() < 1e-6);
        assert!(
            ds[0].dot(right) < 0.0 && ds[0].dot(down) < 0.0,
            "top-left looks left and up"
        );
        assert!((ds[3].dot(right) - ds[1].dot(right)).abs() < 1e-6);
    }
}
