//! Masks (binary regions) and RGB images.

use std::path::Path;

use image::{DynamicImage, ImageFormat, RgbImage};
use moma_core::{ImageSize, Mask};
use ndarray::Array2;

use crate::atomic::atomic_write;
use crate::error::{IoError, Result};
use crate::png_util::{PngPixels, decode_image_bytes, encode_png};

/// Reads a mask PNG: a pixel is inside when its value is nonzero.
///
/// The canonical mask is 8-bit grayscale 0/255 (what [`write_mask`] writes). Other PNG pixel
/// types are accepted and converted: 1/2/4-bit and 16-bit grayscale (nonzero = inside),
/// grayscale+alpha, RGB, RGBA and palette images (inside when any colour channel is nonzero;
/// alpha is ignored, palette entries are looked up first).
///
/// # Errors
/// Unreadable ([`IoError::Io`]) or corrupt/truncated ([`IoError::Corrupt`]) PNG.
pub fn read_mask(path: impl AsRef<Path>) -> Result<Mask> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, "read", e))?;
    mask_from_bytes(path, &bytes)
}

/// [`read_mask`] on the content of a file already in memory; `path` names it in errors.
///
/// # Errors
/// As [`read_mask`]; [`IoError::TooLarge`] / [`IoError::Corrupt`] when the header claims more
/// than [`crate::MAX_IMAGE_PIXELS`] pixels or more pixel data than the file can hold (checked
/// before anything is allocated).
pub fn mask_from_bytes(path: &Path, bytes: &[u8]) -> Result<Mask> {
    Ok(Mask::new(labels_from_bytes(path, bytes)?.mapv(|l| l != 0)))
}

/// The values of a mask PNG as labels: grey levels, or colours packed 16 bits a channel.
fn labels_from_bytes(path: &Path, bytes: &[u8]) -> Result<Array2<u64>> {
    let img = decode_image_bytes(path, bytes, Some(ImageFormat::Png))?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let labels: Vec<u64> = match img {
        DynamicImage::ImageLuma8(b) => b.into_raw().into_iter().map(u64::from).collect(),
        DynamicImage::ImageLuma16(b) => b.into_raw().into_iter().map(u64::from).collect(),
        other => other
            .to_rgb16()
            .pixels()
            .map(|p| p.0.iter().fold(0u64, |acc, &c| (acc << 16) | u64::from(c)))
            .collect(),
    };
    Array2::from_shape_vec((h, w), labels).map_err(|e| IoError::corrupt(path, "PNG", e.to_string()))
}

/// Reads the objects to grasp from a mask PNG ([`read_mask`]'s pixel types): an instance label
/// image (one grey level or colour per object, as segmentation tools write them) keeps objects
/// apart that touch ([`Mask::from_labels`]: the pixels along the seam between two objects are
/// outside, so that each object is its own 8-connected component and no grasp straddles two);
/// any other mask reads as [`read_mask`] reads it. For `moma grasp --mask` and the ROS 2
/// node's `--mask`; evaluation regions, sample and workspace masks are read by [`read_mask`].
///
/// # Errors
/// As [`read_mask`], plus [`IoError::SizeMismatch`] when it is not `expected` in size.
pub fn read_object_mask_sized(path: impl AsRef<Path>, expected: ImageSize) -> Result<Mask> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, "read", e))?;
    let mask = Mask::from_labels(labels_from_bytes(path, &bytes)?.view());
    IoError::expect_size(path, expected, mask.size())?;
    Ok(mask)
}

/// Reads a mask ([`read_mask`]) and checks it is `expected` pixels in size.
///
/// # Errors
/// As [`read_mask`], plus [`IoError::SizeMismatch`].
pub fn read_mask_sized(path: impl AsRef<Path>, expected: ImageSize) -> Result<Mask> {
    let path = path.as_ref();
    let mask = read_mask(path)?;
    IoError::expect_size(path, expected, mask.size())?;
    Ok(mask)
}

/// Writes a mask atomically as an 8-bit grayscale PNG, 255 inside and 0 outside.
///
/// # Errors
/// Destination not writable; an empty mask.
pub fn write_mask(path: impl AsRef<Path>, mask: &Mask) -> Result<()> {
    let path = path.as_ref();
    let size = mask.size();
    let data: Vec<u8> = mask
        .data()
        .iter()
        .map(|&b| if b { 255 } else { 0 })
        .collect();
    atomic_write(path, |w| {
        encode_png(
            w,
            path,
            size.width,
            size.height,
            PngPixels::Gray8(&data),
            &[],
        )
    })
}

/// Reads an 8-bit RGB image from PNG or JPEG (detected from the content, not the extension).
///
/// Other pixel types are converted: 8-bit grayscale is replicated to three channels, alpha is
/// dropped (not composited), 16-bit colour channels are scaled to 8 bits (`v · 255 / 65535`,
/// rounded). A 16-bit single-channel image is refused: that is how depth maps are stored, and
/// passing one where the colour image belongs is a mistake, not a grey frame (a 16-bit mono
/// camera image must be converted to 8 bits first).
///
/// # Errors
/// Unreadable ([`IoError::Io`]), not PNG/JPEG, corrupt or truncated ([`IoError::Corrupt`]);
/// [`IoError::Invalid`] for a 16-bit single-channel image.
pub fn read_rgb(path: impl AsRef<Path>) -> Result<RgbImage> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, "read", e))?;
    rgb_from_bytes(path, &bytes)
}

/// [`read_rgb`] on the content of a file already in memory; `path` names it in errors.
///
/// # Errors
/// As [`read_rgb`]; [`IoError::TooLarge`] when the header claims more than
/// [`crate::MAX_IMAGE_PIXELS`] pixels (checked before anything is allocated).
pub fn rgb_from_bytes(path: &Path, bytes: &[u8]) -> Result<RgbImage> {
    let img = decode_image_bytes(path, bytes, None)?;
    if img.color() == image::ColorType::L16 {
        return Err(IoError::invalid(
            path,
            "is a 16-bit single-channel image, the format of depth maps in millimetres, where \
             an RGB image was expected (pass the frame's colour image)",
        ));
    }
    Ok(img.to_rgb8())
}

/// Reads an RGB image ([`read_rgb`]) and checks it is `expected` pixels in size.
///
/// # Errors
/// As [`read_rgb`], plus [`IoError::SizeMismatch`].
pub fn read_rgb_sized(path: impl AsRef<Path>, expected: ImageSize) -> Result<RgbImage> {
    let path = path.as_ref();
    let img = read_rgb(path)?;
    IoError::expect_size(path, expected, rgb_size(&img))?;
    Ok(img)
}

/// The size of an RGB image in pixels.
pub fn rgb_size(img: &RgbImage) -> ImageSize {
    ImageSize::new(img.width() as usize, img.height() as usize)
}

/// JPEG quality used by [`write_rgb`] for `.jpg`/`.jpeg` outputs.
pub const JPEG_QUALITY: u8 = 95;

/// Writes `img` atomically as a PNG whose `Description` text chunk is `description` (what the
/// picture shows, for viewers and scripts: [`read_png_description`]); characters outside
/// Latin-1 (a PNG text chunk's) are spelt out or replaced (`σ` → `sigma`).
///
/// # Errors
/// An empty image; destination not writable.
pub fn write_rgb_png_described(
    path: impl AsRef<Path>,
    img: &RgbImage,
    description: &str,
) -> Result<()> {
    let path = path.as_ref();
    let latin1: String = description
        .replace('σ', "sigma")
        .replace(['−', '–'], "-")
        .chars()
        .map(|c| if (c as u32) < 256 { c } else { '?' })
        .collect();
    let (w, h) = (img.width() as usize, img.height() as usize);
    atomic_write(path, |out| {
        encode_png(
            out,
            path,
            w,
            h,
            PngPixels::Rgb8(img.as_raw()),
            &[("Description", latin1)],
        )
    })
}

/// The `Description` text chunk of a PNG ([`write_rgb_png_described`], the colour maps of
/// [`crate::write_depth_colormap`]); `None` without one.
///
/// # Errors
/// Unreadable or corrupt PNG.
pub fn read_png_description(path: impl AsRef<Path>) -> Result<Option<String>> {
    Ok(crate::png_util::read_png_texts(path.as_ref())?
        .into_iter()
        .find(|(k, _)| k == "Description")
        .map(|(_, v)| v))
}

/// Writes an 8-bit RGB image atomically: PNG for `.png`, JPEG (quality [`JPEG_QUALITY`]) for
/// `.jpg`/`.jpeg` (case-insensitive).
///
/// # Errors
/// [`IoError::Unsupported`] for other extensions; destination not writable; an empty image.
pub fn write_rgb(path: impl AsRef<Path>, img: &RgbImage) -> Result<()> {
    let path = path.as_ref();
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let (w, h) = (img.width() as usize, img.height() as usize);
    match ext.as_str() {
        "png" => atomic_write(path, |out| {
            encode_png(out, path, w, h, PngPixels::Rgb8(img.as_raw()), &[])
        }),
        "jpg" | "jpeg" => {
            if w == 0 || h == 0 {
                return Err(IoError::invalid(
                    path,
                    format!("cannot write an empty {w}x{h} image"),
                ));
            }
            atomic_write(path, |out| {
                let enc = image::codecs::jpeg::JpegEncoder::new_with_quality(out, JPEG_QUALITY);
                img.write_with_encoder(enc).map_err(|e| match e {
                    image::ImageError::IoError(io) => IoError::io(path, "write", io),
                    other => IoError::invalid(path, format!("JPEG encoding failed: {other}")),
                })
            })
        }
        _ => Err(IoError::unsupported(
            path,
            "image file extension",
            if ext.is_empty() {
                "<none>".to_string()
            } else {
                ext
            },
            "'.png', '.jpg' or '.jpeg'",
        )),
    }
}
