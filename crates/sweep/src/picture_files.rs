//! Pictures of renders as files: PNG strips and animated GIFs of the panels
//! [`osrt_trainer::pictures`] draws.

use crate::{Result, SweepError};
use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, RgbImage};
use std::path::Path;

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
    use osrt_trainer::pictures::{segmentation_image, slot_colour};

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
