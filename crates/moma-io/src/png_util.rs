//! Internal PNG/JPEG helpers shared by the depth, mask, RGB and colour-map modules.

use std::fs::File;
use std::io::{BufReader, Cursor, Write};
use std::path::Path;

use image::{DynamicImage, ImageDecoder, ImageFormat, ImageReader, Limits};

use crate::error::{IoError, Result};
use crate::limits::{
    MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE_PX, check_image_size, check_png_length, png_ihdr,
};

/// Decodes the content of `path` (`bytes`) as `format` (PNG or JPEG; `None`: guessed from the
/// content). The size the header claims is checked before any pixel memory is allocated
/// ([`check_image_size`], and for PNG [`check_png_length`]). Decoding failures, truncation
/// included, are [`IoError::Corrupt`].
pub(crate) fn decode_image_bytes(
    path: &Path,
    bytes: &[u8],
    format: Option<ImageFormat>,
) -> Result<DynamicImage> {
    let mut reader = ImageReader::new(Cursor::new(bytes));
    let format = match format {
        Some(f) => f,
        None => {
            reader = reader
                .with_guessed_format()
                .map_err(|e| IoError::io(path, "read", e))?;
            match reader.format() {
                Some(f @ (ImageFormat::Png | ImageFormat::Jpeg)) => f,
                _ => {
                    return Err(IoError::corrupt(
                        path,
                        "image",
                        "content is neither PNG nor JPEG (unrecognised signature)",
                    ));
                }
            }
        }
    };
    let name = format_name(format);
    if format == ImageFormat::Png
        && let Some((width, height, bits_per_pixel)) = png_ihdr(bytes)
    {
        check_image_size(path, name, width, height)?;
        check_png_length(path, width, height, bits_per_pixel, bytes.len() as u64)?;
    }
    reader.set_format(format);
    let corrupt = |e: image::ImageError| IoError::corrupt(path, name, e.to_string());
    let mut decoder = reader.into_decoder().map_err(corrupt)?;
    let (width, height) = decoder.dimensions();
    check_image_size(path, name, u64::from(width), u64::from(height))?;
    let mut limits = Limits::default();
    limits.max_image_width = Some(MAX_IMAGE_SIDE_PX as u32);
    limits.max_image_height = Some(MAX_IMAGE_SIDE_PX as u32);
    // The largest pixel type (RGBA, 16 bits per channel) at the largest accepted size.
    limits.max_alloc = Some(MAX_IMAGE_PIXELS * 8);
    decoder.set_limits(limits).map_err(corrupt)?;
    DynamicImage::from_decoder(decoder).map_err(corrupt)
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
