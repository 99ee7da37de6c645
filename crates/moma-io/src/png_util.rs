//! Internal PNG/JPEG helpers shared by the depth, mask, RGB and colour-map modules.

use std::fs::File;
use std::io::{BufReader, Write};
use std::path::Path;

use image::{DynamicImage, ImageFormat, ImageReader};

use crate::error::{IoError, Result};

/// Opens `path` (an [`IoError::Io`] when it cannot be opened) and decodes it as `format`
/// (PNG or JPEG; `None`: guessed from the content). Decoding failures, truncation included,
/// are [`IoError::Corrupt`].
pub(crate) fn decode_image(path: &Path, format: Option<ImageFormat>) -> Result<DynamicImage> {
    let file = File::open(path).map_err(|e| IoError::io(path, "open", e))?;
    let mut reader = ImageReader::new(BufReader::new(file));
    let name = match format {
        Some(f) => {
            reader.set_format(f);
            format_name(f)
        }
        None => {
            reader = reader
                .with_guessed_format()
                .map_err(|e| IoError::io(path, "read", e))?;
            match reader.format() {
                Some(f) => format_name(f),
                None => {
                    return Err(IoError::corrupt(
                        path,
                        "image",
                        "content is neither PNG nor JPEG (unrecognised signature)",
                    ));
                }
            }
        }
    };
    reader
        .decode()
        .map_err(|e| IoError::corrupt(path, name, e.to_string()))
}

fn format_name(f: ImageFormat) -> &'static str {
    match f {
        ImageFormat::Png => "PNG",
        ImageFormat::Jpeg => "JPEG",
        _ => "image",
    }
}

/// A short name of a decoded image's pixel type, for error messages.
pub(crate) fn pixel_type(img: &DynamicImage) -> String {
    let c = img.color();
    format!(
        "{:?} ({} channel(s), {} bits per channel)",
        c,
        c.channel_count(),
        c.bits_per_pixel() / u16::from(c.channel_count())
    )
}

/// Pixel layouts this crate writes.
#[derive(Clone, Copy)]
pub(crate) enum PngPixels<'a> {
    /// 8-bit grayscale, one byte per pixel.
    Gray8(&'a [u8]),
    /// 16-bit grayscale, native `u16` per pixel (written big-endian as PNG requires).
    Gray16(&'a [u16]),
    /// 8-bit RGB, three bytes per pixel.
    Rgb8(&'a [u8]),
}

/// Encodes a PNG with optional `tEXt` chunks (keyword, Latin-1 text) placed before the image data.
pub(crate) fn encode_png(
    w: &mut dyn Write,
    path: &Path,
    width: usize,
    height: usize,
    pixels: PngPixels<'_>,
    texts: &[(&str, String)],
) -> Result<()> {
    let too_big = || IoError::invalid(path, format!("image {width}x{height} is too large for PNG"));
    let (w32, h32) = (
        u32::try_from(width).map_err(|_| too_big())?,
        u32::try_from(height).map_err(|_| too_big())?,
    );
    if width == 0 || height == 0 {
        return Err(IoError::invalid(
            path,
            format!("cannot write an empty {width}x{height} image as PNG"),
        ));
    }
    let enc_err = |e: png::EncodingError| match e {
        png::EncodingError::IoError(io) => IoError::io(path, "write", io),
        other => IoError::invalid(path, format!("PNG encoding failed: {other}")),
    };
    let mut enc = png::Encoder::new(w, w32, h32);
    let bytes16;
    let data: &[u8] = match pixels {
        PngPixels::Gray8(d) => {
            enc.set_color(png::ColorType::Grayscale);
            enc.set_depth(png::BitDepth::Eight);
            d
        }
        PngPixels::Gray16(d) => {
            enc.set_color(png::ColorType::Grayscale);
            enc.set_depth(png::BitDepth::Sixteen);
            bytes16 = d.iter().flat_map(|v| v.to_be_bytes()).collect::<Vec<u8>>();
            &bytes16
        }
        PngPixels::Rgb8(d) => {
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            d
        }
    };
    for (k, v) in texts {
        enc.add_text_chunk((*k).to_string(), v.clone())
            .map_err(enc_err)?;
    }
    let mut writer = enc.write_header().map_err(enc_err)?;
    writer.write_image_data(data).map_err(enc_err)?;
    writer.finish().map_err(enc_err)
}

/// The `tEXt` chunks (keyword, text) of a PNG that precede its image data.
pub(crate) fn read_png_texts(path: &Path) -> Result<Vec<(String, String)>> {
    let file = File::open(path).map_err(|e| IoError::io(path, "open", e))?;
    let decoder = png::Decoder::new(BufReader::new(file));
    let reader = decoder
        .read_info()
        .map_err(|e| IoError::corrupt(path, "PNG", e.to_string()))?;
    Ok(reader
        .info()
        .uncompressed_latin1_text
        .iter()
        .map(|t| (t.keyword.clone(), t.text.clone()))
        .collect())
}
