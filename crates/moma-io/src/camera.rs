//! `camera.json`: pinhole intrinsics in pixels.

use std::path::Path;

use moma_core::Intrinsics;

use crate::atomic::{atomic_write, write_err};
use crate::error::{IoError, Result};

/// Reads and validates `camera.json`: `{"width","height","fx","fy","cx","cy"}`, all in pixels
/// (width/height integers, the rest numbers). Unknown extra fields are ignored.
///
/// # Errors
/// [`IoError::Json`] (with line and column) for invalid JSON or a missing/mistyped field;
/// [`IoError::Core`] for an empty image size or a non-positive / non-finite focal length or
/// non-finite principal point ([`Intrinsics::validate`]); [`IoError::Io`] when unreadable.
pub fn read_camera(path: impl AsRef<Path>) -> Result<Intrinsics> {
    let path = path.as_ref();
    let text = crate::json_files::read_json_text(path, "camera intrinsics (camera.json)")?;
    parse_camera(path, &text)
}

/// [`read_camera`] on the content of a file already in memory; `path` names it in errors.
///
/// # Errors
/// As [`read_camera`].
pub fn parse_camera(path: &Path, text: &str) -> Result<Intrinsics> {
    let k: Intrinsics = serde_json::from_str(text).map_err(|e| IoError::json(path, &e))?;
    k.validate().map_err(|e| IoError::core(path, e))?;
    Ok(k)
}

/// Writes `camera.json` atomically (pretty-printed, pixels).
///
/// # Errors
/// [`IoError::Core`] for intrinsics that [`read_camera`] would reject; destination not writable.
pub fn write_camera(path: impl AsRef<Path>, intrinsics: &Intrinsics) -> Result<()> {
    let path = path.as_ref();
    intrinsics.validate().map_err(|e| IoError::core(path, e))?;
    let mut text = serde_json::to_string_pretty(intrinsics)
        .map_err(|e| IoError::invalid(path, format!("cannot encode camera as JSON: {e}")))?;
    text.push('\n');
    atomic_write(path, |w| {
        w.write_all(text.as_bytes()).map_err(write_err(path))
    })
}
