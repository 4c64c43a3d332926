//! Pictures of renders: colour images and slot segmentations side by side, scaled up
//! for people (nearest neighbour: 32×32 renders stay crisp), as PNG strips and an
//! animated GIF.

use crate::{Result, SweepError};
use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, Rgb, RgbImage};
use std::path::Path;

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

fn io_err(path: &Path, e: impl std::fmt::Display) -> SweepError {
    SweepError::Io {
        path: path.display().to_string(),
        reason: e.to_string(),
    }
}

pub fn write_png(path: &Path, img: &RgbImage) -> Result<()> {
    img.save_with_format(path, image::ImageFormat::Png)
        .map_err(|e| io_err(path, e))
}

/// An endlessly looping GIF of `frames` (all the same size), `delay_ms` per frame.
pub fn write_gif(path: &Path, frames: &[RgbImage], delay_ms: u32) -> Result<()> {
    let file = std::fs::File::create(path).map_err(|e| io_err(path, e))?;
    let mut enc = GifEncoder::new_with_speed(std::io::BufWriter::new(file), 10);
    enc.set_repeat(Repeat::Infinite)
        .map_err(|e| io_err(path, e))?;
    let frames = frames.iter().map(|f| {
        Frame::from_parts(
            image::DynamicImage::ImageRgb8(f.clone()).to_rgba8(),
            0,
            0,
            Delay::from_numer_denom_ms(delay_ms, 1),
        )
    });
    enc.encode_frames(frames).map_err(|e| io_err(path, e))
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
    }

    #[test]
    fn gifs_hold_every_frame() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.gif");
        let frames: Vec<RgbImage> = (0..3).map(|i| segmentation_image(4, 4, &[i; 16])).collect();
        write_gif(&path, &frames, 80).unwrap();
        let dec = image::codecs::gif::GifDecoder::new(std::io::BufReader::new(
            std::fs::File::open(&path).unwrap(),
        ))
        .unwrap();
        use image::AnimationDecoder;
        let got = dec.into_frames().collect_frames().unwrap();
        assert_eq!(got.len(), 3);
        let px = got[2].buffer().get_pixel(1, 1);
        let want = slot_colour(2);
        for c in 0..3 {
            assert!(
                (px[c] as i32 - want[c] as i32).abs() <= 8,
                "{px:?} vs {want:?}"
            );
        }
    }
}
