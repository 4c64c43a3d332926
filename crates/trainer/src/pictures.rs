//! Pictures of renders: colour images and slot segmentations side by side, scaled up
//! for people (nearest neighbour: 32×32 renders stay crisp). Evaluations leave them for
//! TensorBoard (`RUN/eval/`); `osrt render` and reports write them as files.

use crate::eval::EvalSample;
use image::{Rgb, RgbImage};

/// Pixels between panels of a strip.
const GAP: u32 = 2;

/// The colour of slot `slot` (the project's one palette).
pub fn slot_colour(slot: u32) -> [u8; 3] {
    osrt_dataset::palette::label_colour(slot)
}

/// An RGB image from `[h * w * 3]` floats in `[0, 1]` (clamped; NaN shows as black).
pub fn rgb_image(width: u32, height: u32, rgb: &[f32]) -> RgbImage {
    let bytes = rgb
        .iter()
        .map(|&x| (x.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    RgbImage::from_raw(width, height, bytes).expect("rgb buffer of the image's size")
}

/// A dataset view's RGB8 bytes as an image; `None` if the size does not match.
pub fn rgb8_image(width: u32, height: u32, bytes: Vec<u8>) -> Option<RgbImage> {
    RgbImage::from_raw(width, height, bytes)
}

/// One palette colour per pixel from per-pixel slot ids.
pub fn segmentation_image(width: u32, height: u32, labels: &[u32]) -> RgbImage {
    let bytes = labels.iter().flat_map(|&l| slot_colour(l)).collect();
    RgbImage::from_raw(width, height, bytes).expect("label buffer of the image's size")
}

/// Panels side by side, each scaled by `scale`, on white, separated by [`GAP`] pixels.
pub fn strip(panels: &[RgbImage], scale: u32) -> RgbImage {
    let scale = scale.max(1);
    let h = panels.iter().map(|p| p.height()).max().unwrap_or(0) * scale;
    let w: u32 = panels.iter().map(|p| p.width() * scale).sum::<u32>()
        + GAP * panels.len().saturating_sub(1) as u32;
    let mut out = RgbImage::from_pixel(w.max(1), h.max(1), Rgb([255, 255, 255]));
    let mut x0 = 0;
    for p in panels {
        for (x, y, px) in p.enumerate_pixels() {
            for dy in 0..scale {
                for dx in 0..scale {
                    out.put_pixel(x0 + x * scale + dx, y * scale + dy, *px);
                }
            }
        }
        x0 += p.width() * scale + GAP;
    }
    out
}

/// `img` as PNG bytes.
pub fn png_bytes(img: &RgbImage) -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png)
        .expect("an RGB8 image encodes as PNG in memory");
    out.into_inner()
}

/// Height pictures of small renders are scaled up to (at least).
const MIN_PICTURE_HEIGHT: u32 = 96;

/// The pictures an evaluation leaves, as `(name, PNG)`: `render` (the first input view,
/// the target view's ground truth, its render) and, where the decoder has slot weights,
/// `segmentation` (the target's object mask, where the data has one, and the slots).
pub fn eval_pictures(s: &EvalSample) -> Vec<(&'static str, Vec<u8>)> {
    let (w, h) = (s.target.width, s.target.height);
    let scale = MIN_PICTURE_HEIGHT.div_ceil(h.max(1)).max(1);
    let mut render = Vec::new();
    render.extend(rgb8_image(
        s.input.width,
        s.input.height,
        s.input.image.clone(),
    ));
    render.extend(rgb8_image(w, h, s.target.image.clone()));
    render.push(rgb_image(w, h, &s.rgb));
    let mut out = vec![("render", png_bytes(&strip(&render, scale)))];
    if let Some(labels) = &s.labels {
        let mut seg = Vec::new();
        if let Some(mask) = &s.target.mask {
            let ids: Vec<u32> = mask.iter().map(|&m| m as u32).collect();
            seg.push(segmentation_image(w, h, &ids));
        }
        seg.push(segmentation_image(w, h, labels));
        out.push(("segmentation", png_bytes(&strip(&seg, scale))));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strips_scale_panels_and_keep_their_pixels() {
        let a = rgb_image(
            2,
            2,
            &[
                0.0,
                0.0,
                0.0,
                1.0,
                1.0,
                1.0,
                0.5,
                0.2,
                2.0,
                -1.0,
                f32::NAN,
                0.0,
            ],
        );
        let b = segmentation_image(2, 2, &[0, 1, 2, 13]);
        assert_eq!(a.get_pixel(1, 0), &Rgb([255, 255, 255]));
        assert_eq!(a.get_pixel(0, 1), &Rgb([128, 51, 255]), "clamped above");
        assert_eq!(
            a.get_pixel(1, 1),
            &Rgb([0, 0, 0]),
            "clamped below, NaN black"
        );
        assert_eq!(b.get_pixel(1, 1), &Rgb(slot_colour(3)), "palette repeats");
        let s = strip(&[a.clone(), b.clone()], 3);
        assert_eq!(s.dimensions(), (2 * 6 + GAP, 6));
        assert_eq!(s.get_pixel(5, 5), a.get_pixel(1, 1));
        assert_eq!(s.get_pixel(6, 0), &Rgb([255, 255, 255]), "the gap is white");
        assert_eq!(s.get_pixel(6 + GAP + 3, 0), b.get_pixel(1, 0));
        let png = png_bytes(&s);
        let back = image::load_from_memory(&png).unwrap().to_rgb8();
        assert_eq!(back, s, "PNG is lossless");
    }
}
