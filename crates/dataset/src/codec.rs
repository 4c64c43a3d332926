//! PNG storage of a view's pixels ([`crate::schema::ImageCodec::Png`]): the image as an
//! RGB8 PNG, the instance mask as an 8-bit grey PNG, both of the view's size. Decoding
//! checks the size and the colour type against the row, so a wrong picture is an error
//! naming the view, never a silently resized or converted one.

use crate::error::{DatasetError, Result};
use crate::scene::View;
use image::codecs::png::{CompressionType, FilterType, PngEncoder};
use image::{DynamicImage, ExtendedColorType, ImageEncoder, ImageFormat};

fn png(pixels: &[u8], width: u32, height: u32, color: ExtendedColorType) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    PngEncoder::new_with_quality(&mut out, CompressionType::Default, FilterType::Adaptive)
        .write_image(pixels, width, height, color)
        .map_err(|e| DatasetError::Batch(format!("encoding a {width}x{height} PNG: {e}")))?;
    Ok(out)
}

/// The PNGs of a view's image and mask.
pub fn encode_view(v: &View) -> Result<(Vec<u8>, Option<Vec<u8>>)> {
    let image = png(&v.image, v.width, v.height, ExtendedColorType::Rgb8)?;
    let mask = v
        .mask
        .as_ref()
        .map(|m| png(m, v.width, v.height, ExtendedColorType::L8))
        .transpose()?;
    Ok((image, mask))
}

fn decode(bytes: &[u8], what: &str) -> std::result::Result<DynamicImage, String> {
    image::load_from_memory_with_format(bytes, ImageFormat::Png)
        .map_err(|e| format!("{what}: not a readable PNG ({e})"))
}

fn check_size(
    img: &DynamicImage,
    width: u32,
    height: u32,
    what: &str,
) -> std::result::Result<(), String> {
    if (img.width(), img.height()) != (width, height) {
        return Err(format!(
            "{what} PNG is {}x{}, the view is {width}x{height}",
            img.width(),
            img.height()
        ));
    }
    Ok(())
}

/// The pixels of a view stored as PNGs: RGB8 image bytes and the mask's ids.
pub fn decode_view(
    width: u32,
    height: u32,
    image: &[u8],
    mask: Option<&[u8]>,
) -> std::result::Result<(Vec<u8>, Option<Vec<u8>>), String> {
    let img = decode(image, "image")?;
    check_size(&img, width, height, "image")?;
    let DynamicImage::ImageRgb8(rgb) = img else {
        return Err(format!(
            "image PNG is {:?}, expected 8-bit RGB",
            img.color()
        ));
    };
    let mask = match mask {
        None => None,
        Some(bytes) => {
            let m = decode(bytes, "mask")?;
            check_size(&m, width, height, "mask")?;
            let DynamicImage::ImageLuma8(grey) = m else {
                return Err(format!("mask PNG is {:?}, expected 8-bit grey", m.color()));
            };
            Some(grey.into_raw())
        }
    };
    Ok((rgb.into_raw(), mask))
}
