//! Sets and prediction folders for the evaluation.
//!
//! A set in memory is moma-io's [`LoadedSet`] (one type for the whole project; invalid depth is
//! `NaN` as [`moma_io::read_depth`] returns it). A prediction folder holds `<frame-id>.npy`,
//! float32 (float64 accepted), shape `(H, W)`, and its index `predictions.json`.

use std::path::Path;

use ndarray::Array2;

use crate::error::{EvalError, Result};

pub use moma_io::{LoadedFrame, LoadedSet};

/// Opens and loads the moma set at `dir` ([`LoadedSet::open`]).
///
/// # Errors
/// Any read error, naming the file.
pub fn load_set(dir: &Path) -> Result<LoadedSet> {
    Ok(LoadedSet::open(dir)?)
}

/// Reads one prediction `<dir>/<frame-id>.npy` (float32 or float64, shape `(H, W)`).
///
/// # Errors
/// Missing file (naming the frame), unreadable array (naming the frame and the file).
pub fn read_prediction(dir: &Path, set: &str, frame: &str) -> Result<Array2<f32>> {
    let path = dir.join(format!("{frame}.npy"));
    if !path.exists() {
        return Err(EvalError::frame(
            set,
            frame,
            format!("missing prediction file {}", path.display()),
        ));
    }
    moma_io::read_npy_f32(&path).map_err(|source| EvalError::frame_io(set, frame, source))
}

fn io_err(path: &Path, action: &'static str, source: std::io::Error) -> moma_io::IoError {
    moma_io::IoError::Io {
        path: path.to_path_buf(),
        action,
        source,
    }
}

/// Creates the parent folder of `path` (output helpers of `moma-io` write into existing folders).
///
/// # Errors
/// The folder cannot be created.
pub fn create_parent(path: &Path) -> Result<()> {
    match path.parent() {
        Some(parent) if !parent.as_os_str().is_empty() => std::fs::create_dir_all(parent)
            .map_err(|e| io_err(parent, "create directory", e).into()),
        _ => Ok(()),
    }
}

/// Writes a text file atomically ([`moma_io::atomic_write`]), creating parent folders.
///
/// # Errors
/// I/O failure.
pub fn write_text(path: &Path, text: &str) -> Result<()> {
    create_parent(path)?;
    moma_io::atomic_write(path, |w| {
        w.write_all(text.as_bytes())
            .map_err(|e| io_err(path, "write", e))
    })?;
    Ok(())
}

/// Colour of the placeholder `rgb.png` written for frames without RGB (the layout requires one).
pub const PLACEHOLDER_RGB: [u8; 3] = [128, 128, 128];

/// Writes a whole set in the moma layout ([`LoadedSet::write`]; depth as uint16 mm).
///
/// # Errors
/// Any write error, naming the file.
pub fn write_set(dir: &Path, set: &LoadedSet) -> Result<()> {
    Ok(set.write(dir)?)
}
