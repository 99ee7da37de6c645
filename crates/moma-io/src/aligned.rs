//! `aligned.json`: the index a command that writes aligned depth keeps in the folder it writes
//! to (`moma align`, `moma grasp -o`, `moma demo`), so that a depth map carries where it came
//! from when it is scored later (`moma metrics`): a depth aligned from SIMULATED predictions, or
//! by a calibration fitted on them, is labelled SIMULATED.
//!
//! ```json
//! {"format": "moma-aligned", "version": 1,
//!  "files": [{"file": "clutter_1.depth.npy", "simulated": true, "written_by": "moma align",
//!             "calibration": "/cell/calib.json", "method": "ssra",
//!             "input": "/cell/preds/clutter_1.npy"}]}
//! ```
//!
//! Entries are file names in the index's folder. A writer records each file before it writes it
//! ([`record_before_writing`]: a SIMULATED label of the file it replaces is kept until the write
//! is done) and again once written ([`record_aligned_files`]), replacing an earlier entry of the
//! same name and keeping the others; every update holds the index's lock file
//! ([`ALIGNED_LOCK_FILE`]), so that runs writing into one folder at once lose no entry. A copy or
//! a link of a depth map elsewhere is not listed: its provenance is unknown.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{IoError, Result};

/// File name of the index.
pub const ALIGNED_INDEX_FILE: &str = "aligned.json";
/// Value of its `format` field.
pub const ALIGNED_FORMAT: &str = "moma-aligned";
/// Value of its `version` field; a newer version is refused.
pub const ALIGNED_VERSION: u32 = 1;

/// One depth file: where it came from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AlignedFile {
    /// The file's name in the index's folder.
    pub file: String,
    /// `true` when the prediction, or the predictions the calibration was fitted on, came from
    /// the simulator: the depth is not a depth model's.
    pub simulated: bool,
    /// The command that wrote it (`moma align`, ...).
    pub written_by: String,
    /// The calibration file, as an absolute path ([`recorded_path`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<String>,
    /// The alignment method.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<String>,
    /// The prediction (or image, or depth) it was made from, as an absolute path
    /// ([`recorded_path`]); a label where it was made in memory (`moma demo`'s predictions).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input: Option<String>,
}

/// The index of one folder.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AlignedIndex {
    /// [`ALIGNED_FORMAT`].
    pub format: String,
    /// [`ALIGNED_VERSION`].
    pub version: u32,
    /// The files, in the order they were first recorded.
    pub files: Vec<AlignedFile>,
}

impl Default for AlignedIndex {
    fn default() -> Self {
        Self {
            format: ALIGNED_FORMAT.into(),
            version: ALIGNED_VERSION,
            files: Vec::new(),
        }
    }
}

impl AlignedIndex {
    /// The entry of the file named `file_name`.
    pub fn entry(&self, file_name: &str) -> Option<&AlignedFile> {
        self.files.iter().find(|f| f.file == file_name)
    }

    /// Adds `files`, replacing the entries of the same names.
    pub fn merge(&mut self, files: Vec<AlignedFile>) {
        for file in files {
            match self.files.iter_mut().find(|f| f.file == file.file) {
                Some(old) => *old = file,
                None => self.files.push(file),
            }
        }
    }
}

/// What the folder of a depth file says about it ([`provenance_of`]).
#[derive(Debug, Clone, PartialEq)]
pub enum Provenance {
    /// The folder's index lists it.
    Listed {
        /// The index.
        index: PathBuf,
        /// Its entry.
        entry: AlignedFile,
    },
    /// No index, or one that does not list it.
    Unlisted,
    /// A file named like the index that is not moma's (another tool's `aligned.json`): it says
    /// nothing about the depth.
    ForeignIndex(PathBuf),
}

/// How an index records a file it names: an absolute path (made so against the current
/// directory, without resolving links), so that the entry means the same file whatever folder
/// it is read from. A path that cannot be made absolute is kept as given.
pub fn recorded_path(path: &Path) -> String {
    std::path::absolute(path)
        .unwrap_or_else(|_| path.to_path_buf())
        .display()
        .to_string()
}

/// The path of the index in `dir`.
pub fn aligned_index_path(dir: &Path) -> PathBuf {
    dir.join(ALIGNED_INDEX_FILE)
}

/// What a folder's file of the index's name holds.
enum Found {
    /// moma's index.
    Ours(AlignedIndex),
    /// Another tool's JSON file (its `format` is not moma's index's).
    Foreign,
}

/// Reads the file of the index's name at `path`; `Ok(None)` when there is none.
///
/// # Errors
/// Something of that name that is not a file, not JSON, or moma's index of a newer version or
/// broken.
fn read_at(path: &Path) -> Result<Option<Found>> {
    if std::fs::symlink_metadata(path).is_err() {
        return Ok(None);
    }
    if !path.is_file() {
        return Err(IoError::invalid(
            path,
            "is not a file (moma keeps its aligned-depth index under this name)",
        ));
    }
    let text = crate::json_files::read_json_text(path, "aligned-depth index")?;
    let value: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| IoError::json(path, &e))?;
    if value.get("format").and_then(|f| f.as_str()) != Some(ALIGNED_FORMAT) {
        return Ok(Some(Found::Foreign));
    }
    match value.get("version").and_then(serde_json::Value::as_u64) {
        Some(v) if (1..=u64::from(ALIGNED_VERSION)).contains(&v) => {}
        _ => {
            return Err(IoError::invalid(
                path,
                format!(
                    "version {}: this moma reads aligned-depth indexes of version 1 to \
                     {ALIGNED_VERSION} (a newer moma wrote it?)",
                    value.get("version").unwrap_or(&serde_json::Value::Null)
                ),
            ));
        }
    }
    serde_json::from_value(value)
        .map(|index| Some(Found::Ours(index)))
        .map_err(|e| IoError::invalid(path, format!("not a valid aligned-depth index: {e}")))
}

/// Reads the index of `dir`; `Ok(None)` when it has none.
///
/// # Errors
/// [`IoError::Invalid`] / [`IoError::Json`] for a file of that name that cannot be read as moma's
/// index, whether another tool's or a corrupt or newer one.
pub fn read_aligned_index(dir: &Path) -> Result<Option<AlignedIndex>> {
    let path = aligned_index_path(dir);
    match read_at(&path)? {
        None => Ok(None),
        Some(Found::Ours(index)) => Ok(Some(index)),
        Some(Found::Foreign) => Err(IoError::invalid(
            &path,
            format!(
                "format is not '{ALIGNED_FORMAT}': another tool's file; moma keeps its \
                 aligned-depth index under this name"
            ),
        )),
    }
}

/// What the index of `file`'s folder says about it.
///
/// # Errors
/// A file named like the index that is moma's but cannot be read (corrupt, newer version, not a
/// file): a SIMULATED label is never dropped silently.
pub fn provenance_of(file: &Path) -> Result<Provenance> {
    let path = aligned_index_path(crate::atomic::folder_of(file));
    let index = match read_at(&path)? {
        None => return Ok(Provenance::Unlisted),
        Some(Found::Foreign) => return Ok(Provenance::ForeignIndex(path)),
        Some(Found::Ours(index)) => index,
    };
    let name = file.file_name().and_then(|n| n.to_str()).unwrap_or("");
    Ok(match index.entry(name) {
        Some(entry) => Provenance::Listed {
            index: path,
            entry: entry.clone(),
        },
        None => Provenance::Unlisted,
    })
}

/// File name of the lock beside the index: writers into one folder take it in turn.
pub const ALIGNED_LOCK_FILE: &str = ".aligned.json.lock";

/// The advisory lock of `dir`'s index (flock on Unix, LockFileEx on Windows): a file beside the
/// index opened for writing, so that a folder that can be written but not read is locked too.
///
/// # Errors
/// The lock file cannot be created, or the platform cannot lock it: two writers could then lose
/// each other's entries, which this refuses rather than risks.
fn lock_index(dir: &Path) -> Result<std::fs::File> {
    let path = dir.join(ALIGNED_LOCK_FILE);
    let file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&path)
        .map_err(|e| IoError::io(&path, "create the aligned-depth index lock", e))?;
    file.lock().map_err(|e| {
        IoError::io(
            &path,
            "lock the aligned-depth index (a file system without locks: write to a local \
                 folder)",
            e,
        )
    })?;
    Ok(file)
}

/// Updates the index of `dir` with `files` while it is locked.
fn update(dir: &Path, files: Vec<AlignedFile>, keep_simulated: bool) -> Result<()> {
    let lock = lock_index(dir)?;
    let mut index = read_aligned_index(dir)?.unwrap_or_default();
    index.version = ALIGNED_VERSION;
    let files = files
        .into_iter()
        .map(|mut f| {
            if keep_simulated {
                f.simulated |= index.entry(&f.file).is_some_and(|old| old.simulated);
            }
            f
        })
        .collect();
    index.merge(files);
    let written = crate::json_files::write_json(aligned_index_path(dir), &index);
    drop(lock);
    written
}

/// Records `files` as they will be once written, before they are: an entry that says SIMULATED
/// keeps saying so (`simulated` of the old and the new entry), so that a write that fails, or a
/// run killed before it, never leaves an old SIMULATED file under a new label. Call
/// [`record_aligned_files`] with the same entries once they are written.
///
/// # Errors
/// As [`record_aligned_files`].
pub fn record_before_writing(dir: &Path, files: Vec<AlignedFile>) -> Result<()> {
    update(dir, files, true)
}

/// Adds `files` to the index of `dir` (created when absent), replacing the entries of the same
/// names, written atomically while the folder's index is locked ([`ALIGNED_LOCK_FILE`]): writers
/// into one folder, threads and processes alike, lose no entry.
///
/// # Errors
/// A file of the index's name that is not moma's index or cannot be read (left as it is), a lock
/// that cannot be taken, or a write failure.
pub fn record_aligned_files(dir: &Path, files: Vec<AlignedFile>) -> Result<()> {
    update(dir, files, false)
}
