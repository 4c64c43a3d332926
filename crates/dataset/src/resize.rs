//! Views shrunk to a smaller size at import (`osrt data import --resize WxH`), so a
//! release's 320×240 images can be trained on at the size a machine holds: colours
//! averaged over each output pixel's area, instance masks by the nearest source pixel
//! (ids must not blend), the camera's intrinsics scaled so every output pixel's ray goes
//! through the centre of the area it averages.

use crate::camera::Intrinsics;
use crate::scene::{Scene, View};

/// Why a size cannot be the target of a resize.
pub fn check_target(from: [u32; 2], to: [u32; 2]) -> Result<(), String> {
    let [w, h] = to;
    if w == 0 || h == 0 {
        return Err(format!(
            "--resize {w}x{h}: both sides must be at least 1 pixel"
        ));
    }
    if w > from[0] || h > from[1] {
        return Err(format!(
            "--resize {w}x{h}: the release's views are {}×{}; a resize only shrinks them",
            from[0], from[1]
        ));
    }
    Ok(())
}

/// `scene` with every view at `size` (`[width, height]`, no larger than the views).
pub fn resize_scene(mut scene: Scene, size: [u32; 2]) -> Scene {
    for v in &mut scene.views {
        *v = resize_view(v, size);
    }
    scene
}

/// `view` at `[width, height]`.
pub fn resize_view(view: &View, [w, h]: [u32; 2]) -> View {
    let (sw, sh) = (view.width as usize, view.height as usize);
    let (cols, rows) = (area_weights(sw, w as usize), area_weights(sh, h as usize));
    let mut image = Vec::with_capacity(w as usize * h as usize * 3);
    for row in &rows {
        for col in &cols {
            let mut rgb = [0f64; 3];
            for &(y, wy) in row {
                for &(x, wx) in col {
                    let i = 3 * (y * sw + x);
                    for (acc, &v) in rgb.iter_mut().zip(&view.image[i..i + 3]) {
                        *acc += wy * wx * v as f64;
                    }
                }
            }
            image.extend(rgb.map(|v| v.round().clamp(0.0, 255.0) as u8));
        }
    }
    let mask = view.mask.as_ref().map(|m| {
        let mut out = Vec::with_capacity(w as usize * h as usize);
        for oy in 0..h as usize {
            let y = nearest(oy, sh, h as usize);
            for ox in 0..w as usize {
                out.push(m[y * sw + nearest(ox, sw, w as usize)]);
            }
        }
        out
    });
    let (sx, sy) = (w as f32 / sw as f32, h as f32 / sh as f32);
    let k = view.camera.intrinsics;
    let mut camera = view.camera;
    // Pixel coordinates are continuous with pixel `i` covering `[i, i + 1)`: scaling them
    // maps each output pixel's centre onto the centre of the source area it averages.
    camera.intrinsics = Intrinsics {
        fx: k.fx * sx,
        fy: k.fy * sy,
        cx: k.cx * sx,
        cy: k.cy * sy,
    };
    View {
        width: w,
        height: h,
        image,
        mask,
        camera,
    }
}

/// For each of `to` output pixels along a side of `from` source pixels, the source
/// pixels it covers and their weights (overlap / output pixel width, summing to 1).
fn area_weights(from: usize, to: usize) -> Vec<Vec<(usize, f64)>> {
    let scale = from as f64 / to as f64;
    (0..to)
        .map(|o| {
            let (a, b) = (o as f64 * scale, (o + 1) as f64 * scale);
            let first = a.floor() as usize;
            let last = (b.ceil() as usize).min(from);
            (first..last)
                .filter_map(|i| {
                    let overlap = b.min(i as f64 + 1.0) - a.max(i as f64);
                    (overlap > 1e-12).then_some((i, overlap / scale))
                })
                .collect()
        })
        .collect()
}

/// The source pixel nearest output pixel `o`'s centre.
fn nearest(o: usize, from: usize, to: usize) -> usize {
    (((o as f64 + 0.5) * from as f64 / to as f64) as usize).min(from - 1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use crate::math::Vec3;

    fn view(w: u32, h: u32) -> View {
        let n = (w * h) as usize;
        View {
            width: w,
            height: h,
            image: (0..3 * n).map(|i| (i * 7 % 256) as u8).collect(),
            mask: Some((0..n).map(|i| (i % 5) as u8).collect()),
            camera: Camera::look_at(
                Vec3::new(3.0, 1.0, 2.0),
                Vec3::new(0.0, 0.0, 0.0),
                Intrinsics::from_fov(0.8, w, h),
            )
            .unwrap(),
        }
    }

    /// Integer factors average whole blocks; weights always sum to one.
    #[test]
    fn whole_blocks_average_exactly() {
        let v = view(6, 4);
        let r = resize_view(&v, [3, 2]);
        let block = |ox: u32, oy: u32, c: usize| -> u8 {
            let mut s = 0.0;
            for y in 2 * oy..2 * oy + 2 {
                for x in 2 * ox..2 * ox + 2 {
                    s += v.rgb(x, y)[c] as f64;
                }
            }
            (s / 4.0).round() as u8
        };
        for oy in 0..2 {
            for ox in 0..3 {
                for c in 0..3 {
                    assert_eq!(r.rgb(ox, oy)[c], block(ox, oy, c));
                }
            }
        }
        for (from, to) in [(320, 32), (240, 7), (5, 3), (9, 9)] {
            for w in area_weights(from, to) {
                let s: f64 = w.iter().map(|p| p.1).sum();
                assert!((s - 1.0).abs() < 1e-12, "{from}→{to}: {s}");
            }
        }
    }

    /// Masks keep their ids (nearest pixel, no blending); the same size is the identity.
    #[test]
    fn masks_take_the_nearest_id_and_same_size_is_identity() {
        let v = view(6, 4);
        let r = resize_view(&v, [3, 2]);
        let m = r.mask.as_ref().unwrap();
        // Output (1, 1) has its centre at source (3, 3).
        assert_eq!(m[4], v.mask.as_ref().unwrap()[3 * 6 + 3]);
        assert_eq!(resize_view(&v, [6, 4]), v);
    }

    /// An output pixel's ray is the ray through the centre of the area it averages.
    #[test]
    fn rays_go_through_the_centre_of_the_averaged_area() {
        let v = view(320, 240);
        let r = resize_view(&v, [32, 24]);
        for (ox, oy) in [(0, 0), (31, 23), (10, 5)] {
            let small = r.camera.pixel_direction(ox, oy);
            let big = v
                .camera
                .direction_at(10.0 * ox as f64 + 5.0, 10.0 * oy as f64 + 5.0);
            let d = (small - big).norm();
            assert!(d < 1e-5, "{small:?} against {big:?}");
        }
    }

    #[test]
    fn only_shrinking_is_allowed() {
        assert!(check_target([320, 240], [32, 24]).is_ok());
        assert!(
            check_target([320, 240], [640, 24])
                .unwrap_err()
                .contains("only shrinks")
        );
        assert!(check_target([320, 240], [0, 24]).is_err());
    }
}
