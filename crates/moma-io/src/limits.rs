//! Resource limits on user input: every decoder checks the size a header claims against these
//! limits and against the length of the file *before* it allocates anything for the pixels, so
//! a tiny malicious or corrupt file cannot make `moma` allocate gigabytes (or abort).

use std::path::Path;

use crate::error::{IoError, Result};

/// Largest image side accepted by every decoder, pixels (PNG, JPEG, npy, PFM).
pub const MAX_IMAGE_SIDE_PX: u64 = 65_535;

/// Largest image accepted by every decoder, pixels: [`moma_core::image::MAX_IMAGE_PIXELS`]
/// (2^26 = 67 108 864, e.g. 8192 × 8192), as a `u64` for header arithmetic. A decoded float32 map
/// of this size takes 256 MiB.
pub const MAX_IMAGE_PIXELS: u64 = moma_core::image::MAX_IMAGE_PIXELS as u64;

/// The largest expansion deflate can achieve: a 258-byte match coded in 2 bits gives at most
/// 1032 bytes out per byte in. A PNG whose raw pixel data exceeds `1032 ×` its file length
/// cannot be complete.
pub const DEFLATE_MAX_RATIO: u64 = 1032;

/// Checks a `width × height` claimed by the header of `path` (format `format`) against
/// [`MAX_IMAGE_SIDE_PX`] and [`MAX_IMAGE_PIXELS`].
///
/// # Errors
/// [`IoError::TooLarge`] naming the file, the claimed size and the limit exceeded.
pub fn check_image_size(path: &Path, format: &'static str, width: u64, height: u64) -> Result<()> {
    let too_large = |limit: String| IoError::TooLarge {
        path: path.to_path_buf(),
        format,
        width,
        height,
        limit,
    };
    if width > MAX_IMAGE_SIDE_PX || height > MAX_IMAGE_SIDE_PX {
        return Err(too_large(format!("{MAX_IMAGE_SIDE_PX} pixels per side")));
    }
    if width.saturating_mul(height) > MAX_IMAGE_PIXELS {
        return Err(too_large(format!("{MAX_IMAGE_PIXELS} pixels")));
    }
    Ok(())
}

/// Checks that a `width × height` map about to be written to `path` is one every reader accepts
/// ([`check_image_size`]'s limits): a file is not written that cannot be read back.
///
/// # Errors
/// [`IoError::Invalid`] naming the size and the limit.
pub(crate) fn check_writable_size(path: &Path, width: usize, height: usize) -> Result<()> {
    check_image_size(path, "", width as u64, height as u64).map_err(|e| match e {
        IoError::TooLarge { limit, .. } => IoError::invalid(
            path,
            format!(
                "cannot write a {width}x{height} map: over the limit of {limit} that moma's \
                 readers accept"
            ),
        ),
        other => other,
    })
}

/// Checks that a `width × height` PNG of `bits_per_pixel` can fit in a file of `file_len`
/// bytes: its raw pixel data (at least `width · height · bits_per_pixel / 8` bytes) is at most
/// [`DEFLATE_MAX_RATIO`] times the file length.
///
/// # Errors
/// [`IoError::Corrupt`] naming the claimed size, the bytes it needs and the file length.
pub(crate) fn check_png_length(
    path: &Path,
    width: u64,
    height: u64,
    bits_per_pixel: u64,
    file_len: u64,
) -> Result<()> {
    let raw_bytes = width
        .saturating_mul(height)
        .saturating_mul(bits_per_pixel)
        .div_ceil(8);
    let min_file = raw_bytes.div_ceil(DEFLATE_MAX_RATIO);
    if min_file > file_len {
        return Err(IoError::corrupt(
            path,
            "PNG",
            format!(
                "header claims {width}x{height} pixels ({raw_bytes} bytes of pixel data), which \
                 needs at least {min_file} compressed bytes, but the file has only {file_len}"
            ),
        ));
    }
    Ok(())
}

/// The header of a PNG: width, height and bits per pixel from its `IHDR` chunk, or `None` when
/// the bytes do not start with a PNG signature and an `IHDR` (the decoder then reports the
/// problem).
pub(crate) fn png_ihdr(bytes: &[u8]) -> Option<(u64, u64, u64)> {
    const SIGNATURE: &[u8; 8] = b"\x89PNG\r\n\x1a\n";
    if bytes.len() < 26 || &bytes[..8] != SIGNATURE || &bytes[12..16] != b"IHDR" {
        return None;
    }
    let width = u32::from_be_bytes([bytes[16], bytes[17], bytes[18], bytes[19]]);
    let height = u32::from_be_bytes([bytes[20], bytes[21], bytes[22], bytes[23]]);
    let bit_depth = u64::from(bytes[24]);
    let channels = match bytes[25] {
        0 | 3 => 1,
        2 => 3,
        4 => 2,
        6 => 4,
        _ => return None,
    };
    Some((u64::from(width), u64::from(height), bit_depth * channels))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_are_inclusive() {
        let p = Path::new("x.png");
        assert!(check_image_size(p, "PNG", MAX_IMAGE_SIDE_PX, 1).is_ok());
        assert!(check_image_size(p, "PNG", 8192, 8192).is_ok());
        let e = check_image_size(p, "PNG", 8192, 8193)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("8192x8193") && e.contains("67108864 pixels"),
            "{e}"
        );
        let e = check_image_size(p, "PNG", MAX_IMAGE_SIDE_PX + 1, 1)
            .unwrap_err()
            .to_string();
        assert!(e.contains("65535 pixels per side"), "{e}");
    }

    #[test]
    fn png_length_bound_is_deflates_ratio() {
        let p = Path::new("x.png");
        // 1032 bytes of 8-bit pixels fit in one byte of deflate stream, 1033 do not.
        assert!(check_png_length(p, 1032, 1, 8, 1).is_ok());
        let e = check_png_length(p, 1033, 1, 8, 1).unwrap_err().to_string();
        assert!(e.contains("1033x1") && e.contains("at least 2"), "{e}");
    }
}
