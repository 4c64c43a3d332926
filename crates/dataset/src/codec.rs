//! PNG storage of a view's pixels ([`crate::schema::ImageCodec::Png`]): the image as an
//! RGB8 PNG, the instance mask as an 8-bit grey PNG, both of the view's size. Decoding
//! checks the size and the colour type against the row, so a wrong picture is an error
//! naming the view, never a silently resized or converted one; the size is checked from
//! the header, before anything is decoded, and decoding is bounded by
//! [`MAX_IMAGE_BYTES`], here and in the importers.

use crate::error::{DatasetError, Result};
use crate::scene::View;
use image::codecs::png::{CompressionType, FilterType, PngDecoder, PngEncoder};
use image::{DynamicImage, ExtendedColorType, ImageDecoder, ImageEncoder};

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

/// The most memory one image may decode to (its pixels, and each conversion's): 64 MiB
/// holds a 4K RGBA frame, some 200 times the releases' images. A header announcing more,
/// a decompression bomb among them, is an error before anything is allocated. Training
/// decodes a row group's views in parallel, so a damaged file can take this much per
/// decoding thread, never more.
pub const MAX_IMAGE_BYTES: u64 = 64 << 20;

/// [`MAX_IMAGE_BYTES`] as the image crate's limits (its decoders' own buffers included).
pub(crate) fn image_limits() -> image::Limits {
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(MAX_IMAGE_BYTES);
    limits
}

/// What went wrong decoding an image, the limit named where it was the limit.
pub(crate) fn image_error(e: image::ImageError) -> String {
    match e {
        image::ImageError::Limits(_) => format!(
            "{e}: it would decode to more than the {} MiB one image may take",
            MAX_IMAGE_BYTES >> 20
        ),
        e => e.to_string(),
    }
}

/// Refuses a `width`×`height` picture whose header announces `bytes` decoded bytes past
/// [`MAX_IMAGE_BYTES`].
pub(crate) fn check_decoded_bytes(width: u32, height: u32, bytes: u64) -> Result<(), String> {
    if bytes > MAX_IMAGE_BYTES {
        return Err(format!(
            "its header announces {width}x{height} pixels, {} MiB decoded, more than the {} \
             MiB one image may take",
            bytes >> 20,
            MAX_IMAGE_BYTES >> 20
        ));
    }
    Ok(())
}

/// Why PNG bytes gave no picture.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum PngError {
    /// Not a PNG, a damaged one, or one over [`MAX_IMAGE_BYTES`].
    Unreadable(String),
    /// The header's `(width, height)` is not the one asked for.
    OtherSize((u32, u32)),
}

impl std::fmt::Display for PngError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Unreadable(e) => f.write_str(e),
            Self::OtherSize((w, h)) => write!(f, "PNG is {w}x{h}, another size than expected"),
        }
    }
}

/// Decodes PNG bytes within [`MAX_IMAGE_BYTES`]. `size`: the `(width, height)` the picture
/// must have. Only the header is read before the size is compared and the decoded bytes
/// are bounded: a header's claim never sizes an allocation.
pub(crate) fn decode_png(
    bytes: &[u8],
    size: Option<(u32, u32)>,
) -> std::result::Result<DynamicImage, PngError> {
    let decoder = PngDecoder::with_limits(std::io::Cursor::new(bytes), image_limits())
        .map_err(|e| PngError::Unreadable(image_error(e)))?;
    let (w, h) = decoder.dimensions();
    if size.is_some_and(|s| s != (w, h)) {
        return Err(PngError::OtherSize((w, h)));
    }
    check_decoded_bytes(w, h, decoder.total_bytes()).map_err(PngError::Unreadable)?;
    DynamicImage::from_decoder(decoder).map_err(|e| PngError::Unreadable(image_error(e)))
}

/// A view's `what` ("image", "mask") PNG of the row's `width`×`height`.
fn decode(
    bytes: &[u8],
    what: &str,
    width: u32,
    height: u32,
) -> std::result::Result<DynamicImage, String> {
    decode_png(bytes, Some((width, height))).map_err(|e| match e {
        PngError::Unreadable(e) => format!("{what}: not a readable PNG ({e})"),
        PngError::OtherSize((w, h)) => {
            format!("{what} PNG is {w}x{h}, the view is {width}x{height}")
        }
    })
}

/// The pixels of a view stored as PNGs: RGB8 image bytes and the mask's ids.
pub fn decode_view(
    width: u32,
    height: u32,
    image: &[u8],
    mask: Option<&[u8]>,
) -> std::result::Result<(Vec<u8>, Option<Vec<u8>>), String> {
    let img = decode(image, "image", width, height)?;
    let DynamicImage::ImageRgb8(rgb) = img else {
        return Err(format!(
            "image PNG is {:?}, expected 8-bit RGB",
            img.color()
        ));
    };
    let mask = match mask {
        None => None,
        Some(bytes) => {
            let m = decode(bytes, "mask", width, height)?;
            let DynamicImage::ImageLuma8(grey) = m else {
                return Err(format!("mask PNG is {:?}, expected 8-bit grey", m.color()));
            };
            Some(grey.into_raw())
        }
    };
    Ok((rgb.into_raw(), mask))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::generator::{GeneratorConfig, generate_scene};
    use crate::schema::{ImageCodec, batch_to_scenes_with, scenes_to_batch};

    /// A PNG whose header announces `width`×`height` RGB8 pixels and whose data is an
    /// empty zlib stream: what a decompression bomb looks like up to its first pixel.
    pub(crate) fn png_header_only(width: u32, height: u32) -> Vec<u8> {
        const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);
        let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
        let mut chunk = |kind: &[u8], data: &[u8]| {
            out.extend((data.len() as u32).to_be_bytes());
            let body = [kind, data].concat();
            out.extend(&body);
            out.extend(CRC32.checksum(&body).to_be_bytes());
        };
        let mut ihdr = width.to_be_bytes().to_vec();
        ihdr.extend(height.to_be_bytes());
        ihdr.extend([8, 2, 0, 0, 0]);
        chunk(b"IHDR", &ihdr);
        chunk(
            b"IDAT",
            &[0x78, 0x01, 0x01, 0x00, 0x00, 0xff, 0xff, 0, 0, 0, 1],
        );
        chunk(b"IEND", &[]);
        out
    }

    /// Two scenes of three `size`² views, their pictures PNG bytes, as a PNG file holds
    /// them.
    fn png_scenes(size: u32) -> Vec<crate::Scene> {
        let cfg = GeneratorConfig {
            image_size: size,
            antialias: 1,
            ..GeneratorConfig::clevr_lite()
        };
        (0..2)
            .map(|i| {
                let mut s = generate_scene(&cfg, 7, "test", i).unwrap();
                for v in &mut s.views {
                    let (image, mask) = encode_view(v).unwrap();
                    (v.image, v.mask) = (image, mask);
                }
                s
            })
            .collect()
    }

    const FILE: &str = "memory://d/train/part-00000.parquet";

    fn read_error(scenes: &[crate::Scene]) -> String {
        let batch = scenes_to_batch(scenes).unwrap();
        batch_to_scenes_with(&batch, FILE, ImageCodec::Png)
            .unwrap_err()
            .to_string()
    }

    /// A 32×32 dataset's view whose PNG announces 100 000 × 100 000 pixels is refused from
    /// its header, naming the file, scene and view and the size the view must have.
    #[test]
    fn a_png_of_another_size_than_its_view_is_refused_from_its_header() {
        let mut scenes = png_scenes(32);
        scenes[1].views[2].image = png_header_only(100_000, 100_000);
        let e = read_error(&scenes);
        assert!(
            e.contains(FILE)
                && e.contains(&format!("scene {}, view 2", scenes[1].id))
                && e.contains("image PNG is 100000x100000, the view is 32x32"),
            "{e}"
        );
    }

    /// A row that agrees with its PNG on a size past the decode limit is refused before
    /// the pixels are allocated (the image crate's own default would allow 512 MiB).
    #[test]
    fn a_png_past_the_decode_limit_is_refused_before_decoding() {
        let mut scenes = png_scenes(8);
        let v = &mut scenes[0].views[1];
        (v.width, v.height) = (5000, 5000);
        v.image = png_header_only(5000, 5000);
        let e = read_error(&scenes);
        assert!(
            e.contains(FILE)
                && e.contains(&format!("scene {}, view 1", scenes[0].id))
                && e.contains("5000x5000 pixels, 71 MiB decoded, more than the 64 MiB"),
            "{e}"
        );
        // Within the limit the same bytes get as far as their (missing) pixels.
        let e = decode_png(&png_header_only(64, 64), Some((64, 64))).unwrap_err();
        assert!(!e.to_string().contains("MiB"), "{e}");
    }
}
