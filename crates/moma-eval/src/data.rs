//! In-memory moma sets for the evaluation, loaded and written through `moma-io`.
//!
//! The file formats and the directory layout (`SET/camera.json`, `SET/frames/ID/{rgb,depth,
//! mask,raw_depth}.png`) are those of [`moma_io::MomaSet`] / [`moma_io::MomaSetWriter`]; this
//! module only holds a whole set in memory (the protocol visits every frame once per seed and
//! method) and keeps the evaluation's convention that invalid depth is `0`.
//!
//! A prediction folder holds `<frame-id>.npy`, float32 (float64 accepted), shape `(H, W)`.

use std::path::{Path, PathBuf};

use image::RgbImage;
use moma_core::{ImageSize, Intrinsics, Mask, MetricDepth};
use ndarray::Array2;

use crate::error::{EvalError, Result};

/// One frame of a set, fully loaded.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Frame id (the folder name).
    pub id: String,
    /// 8-bit RGB, when known (always present in a set loaded from disk).
    pub rgb: Option<RgbImage>,
    /// Ground-truth depth in metres (invalid = 0).
    pub gt: MetricDepth,
    /// Evaluation region; `None` = whole image.
    pub mask: Option<Mask>,
    /// What the depth sensor saw (transparent sets), metres, invalid = 0.
    pub raw_depth: Option<MetricDepth>,
}

/// A fixed-camera set in the moma layout.
#[derive(Debug, Clone)]
pub struct MomaSet {
    /// Set name (the folder's name).
    pub name: String,
    /// The set folder.
    pub dir: PathBuf,
    /// Camera intrinsics (pixels).
    pub intrinsics: Intrinsics,
    /// Frames sorted by id.
    pub frames: Vec<Frame>,
}

impl MomaSet {
    /// Image size of the set.
    pub fn size(&self) -> ImageSize {
        self.intrinsics.size()
    }
    /// Index of a frame by id.
    pub fn frame_index(&self, id: &str) -> Option<usize> {
        self.frames.iter().position(|f| f.id == id)
    }
}

/// The set's name: the last component of its (canonical) path.
pub fn set_name(dir: &Path) -> String {
    dir.canonicalize()
        .ok()
        .and_then(|p| p.file_name().map(|s| s.to_string_lossy().into_owned()))
        .or_else(|| dir.file_name().map(|s| s.to_string_lossy().into_owned()))
        .unwrap_or_else(|| dir.display().to_string())
}

/// `moma-io` reads "no measurement" as NaN; the evaluation keeps invalid depth as 0.
fn nan_to_zero(mut d: MetricDepth) -> MetricDepth {
    d.depth_m.mapv_inplace(|z| if z.is_nan() { 0.0 } else { z });
    d
}

/// Loads a whole set with [`moma_io::MomaSet::open`] and the frame loaders (every map is checked
/// against the camera's size).
///
/// # Errors
/// Missing `camera.json` / `frames/` / `depth.png` / `rgb.png`, unreadable files, size
/// mismatches; per-frame errors name the set and the frame.
pub fn load_set(dir: &Path) -> Result<MomaSet> {
    let name = set_name(dir);
    let opened = moma_io::MomaSet::open(dir)?;
    let frame_err = |id: &str| {
        let (set, frame) = (name.clone(), id.to_string());
        move |source| EvalError::frame_io(&set, &frame, source)
    };
    let mut frames = Vec::with_capacity(opened.frames.len());
    for f in &opened.frames {
        let gt = f.load_depth().map_err(frame_err(&f.id))?;
        let rgb = f.load_rgb().map_err(frame_err(&f.id))?;
        let mask = f.load_mask().map_err(frame_err(&f.id))?;
        let raw_depth = f.load_raw_depth().map_err(frame_err(&f.id))?;
        frames.push(Frame {
            id: f.id.clone(),
            rgb: Some(rgb),
            gt: nan_to_zero(gt),
            mask,
            raw_depth: raw_depth.map(nan_to_zero),
        });
    }
    Ok(MomaSet {
        name,
        dir: dir.to_path_buf(),
        intrinsics: opened.camera,
        frames,
    })
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

/// Writes a whole set in the moma layout with [`moma_io::MomaSetWriter`] (depth as uint16 mm).
/// Frames without RGB get a uniform grey `rgb.png` ([`PLACEHOLDER_RGB`]).
///
/// # Errors
/// I/O failure or size mismatch (naming the frame).
pub fn write_set(dir: &Path, set: &MomaSet) -> Result<()> {
    let writer = moma_io::MomaSetWriter::create(dir, &set.intrinsics)?;
    let size = set.size();
    let placeholder = RgbImage::from_pixel(
        size.width as u32,
        size.height as u32,
        image::Rgb(PLACEHOLDER_RGB),
    );
    for f in &set.frames {
        let data = moma_io::FrameData {
            rgb: f.rgb.as_ref().unwrap_or(&placeholder),
            depth: &f.gt,
            mask: f.mask.as_ref(),
            raw_depth: f.raw_depth.as_ref(),
        };
        writer
            .write_frame(&f.id, data)
            .map_err(|source| EvalError::frame_io(&set.name, &f.id, source))?;
    }
    Ok(())
}
