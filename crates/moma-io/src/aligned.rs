//! `aligned.json`: the index `moma align` writes into its output folder, so that a depth map it
//! wrote carries where it came from when it is scored later (`moma metrics`): a depth aligned
//! from SIMULATED predictions, or by a calibration fitted on them, is labelled SIMULATED.
//!
//! ```json
//! {"format": "moma-aligned", "version": 1,
//!  "frames": [{"name": "clutter_1", "simulated": true, "calibration": "calib.json",
//!              "method": "ssra", "input": "preds/clutter_1.npy"}]}
//! ```
//!
//! A frame `NAME` is the files `NAME.depth.png` and `NAME.depth.npy` beside the index (the maps
//! in metres; its σ map, colour map and point cloud are not depths to score). A later `moma align`
//! into the same folder replaces the entries of the frames it writes and keeps the others. The
//! index is written just before the first frame's files, so that a run that fails part way
//! leaves no unlabelled frame.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{IoError, Result};

/// File name of the index in an output folder of `moma align`.
pub const ALIGNED_INDEX_FILE: &str = "aligned.json";
/// Value of its `format` field.
pub const ALIGNED_FORMAT: &str = "moma-aligned";
/// Value of its `version` field; a newer version is refused.
pub const ALIGNED_VERSION: u32 = 1;
/// The depth files of a frame `NAME`: `NAME.<suffix>`.
const DEPTH_SUFFIXES: [&str; 2] = ["depth.png", "depth.npy"];

/// One aligned frame: where its depth came from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AlignedFrame {
    /// The frame's output name (its files are `NAME.depth.png`, `NAME.depth.npy`, ...).
    pub name: String,
    /// `true` when the prediction, or the predictions the calibration was fitted on, came from
    /// the simulator: the depth is not a depth model's.
    pub simulated: bool,
    /// The calibration file, as given to `moma align`.
    pub calibration: String,
    /// The alignment method of the calibration.
    pub method: String,
    /// The prediction (or image) the frame was aligned from, as given.
    pub input: String,
}

/// The index of one output folder.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AlignedIndex {
    /// [`ALIGNED_FORMAT`].
    pub format: String,
    /// [`ALIGNED_VERSION`].
    pub version: u32,
    /// The frames, in the order they were first written.
    pub frames: Vec<AlignedFrame>,
}

impl Default for AlignedIndex {
    fn default() -> Self {
        Self {
            format: ALIGNED_FORMAT.into(),
            version: ALIGNED_VERSION,
            frames: Vec::new(),
        }
    }
}

impl AlignedIndex {
    /// The entry of the frame whose depth file is `file` (`NAME.depth.png` or `NAME.depth.npy`).
    pub fn frame_of(&self, file: &Path) -> Option<&AlignedFrame> {
        let file_name = file.file_name()?.to_str()?;
        self.frames.iter().find(|f| {
            DEPTH_SUFFIXES
                .iter()
                .any(|s| file_name == format!("{}.{s}", f.name))
        })
    }

    /// Adds `frames`, replacing the entries of the same names.
    pub fn merge(&mut self, frames: Vec<AlignedFrame>) {
        for frame in frames {
            match self.frames.iter_mut().find(|f| f.name == frame.name) {
                Some(old) => *old = frame,
                None => self.frames.push(frame),
            }
        }
    }
}

/// The path of the index in `dir`.
pub fn aligned_index_path(dir: &Path) -> PathBuf {
    dir.join(ALIGNED_INDEX_FILE)
}

/// Reads the index of the output folder `dir`; `Ok(None)` when it has none.
///
/// # Errors
/// [`IoError::Json`] / [`IoError::Invalid`] for a file that exists but is not such an index (a
/// corrupt index is never ignored: it may be what labels a depth SIMULATED).
pub fn read_aligned_index(dir: &Path) -> Result<Option<AlignedIndex>> {
    let path = aligned_index_path(dir);
    if !path.is_file() {
        return Ok(None);
    }
    let text = crate::json_files::read_json_text(&path, "aligned-depth index")?;
    let value: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| IoError::json(&path, &e))?;
    if value["format"] != ALIGNED_FORMAT {
        return Err(IoError::invalid(
            &path,
            format!(
                "format is {}, expected '{ALIGNED_FORMAT}' (not the index `moma align` writes)",
                value["format"]
            ),
        ));
    }
    match value["version"].as_u64() {
        Some(v) if (1..=u64::from(ALIGNED_VERSION)).contains(&v) => {}
        v => {
            return Err(IoError::invalid(
                &path,
                format!(
                    "version {}: this moma reads aligned-depth indexes of version 1 to \
                     {ALIGNED_VERSION} (a newer moma wrote it?)",
                    v.map_or_else(|| value["version"].to_string(), |v| v.to_string())
                ),
            ));
        }
    }
    serde_json::from_value(value)
        .map(Some)
        .map_err(|e| IoError::json(&path, &e))
}

/// The entry for the depth file `file` in the index of its folder, if any.
///
/// # Errors
/// As [`read_aligned_index`].
pub fn aligned_frame_for(file: &Path) -> Result<Option<AlignedFrame>> {
    let dir = match file.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    Ok(read_aligned_index(dir)?.and_then(|i| i.frame_of(file).cloned()))
}

/// Adds `frames` to the index of `dir` (created when absent), written atomically.
///
/// # Errors
/// An existing file that is not such an index (see [`read_aligned_index`]; it is left as it
/// is), or a write failure.
pub fn record_aligned_frames(dir: &Path, frames: Vec<AlignedFrame>) -> Result<()> {
    let mut index = read_aligned_index(dir)?.unwrap_or_default();
    index.version = ALIGNED_VERSION;
    index.merge(frames);
    crate::json_files::write_json(aligned_index_path(dir), &index)
}
