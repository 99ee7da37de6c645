//! The one error type of `moma-io`: every message names the file and the problem.

use std::path::{Path, PathBuf};

use moma_core::{CoreError, ImageSize};

/// Errors reading or writing MOMA files.
///
/// Every variant carries the path of the file (or directory) concerned, and its message names
/// it, so a user can act on the message alone.
#[derive(Debug, thiserror::Error)]
pub enum IoError {
    /// The operating system refused an operation (missing file, permission, full disk...).
    #[error("{}: cannot {action}", path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// What was attempted, e.g. `"read"`, `"create a temporary file next to it"`.
        action: &'static str,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// The file exists but its content is not a valid file of the expected format
    /// (truncated or corrupt PNG / npy / PFM / PLY data).
    #[error("{}: not a valid {format} file: {reason}", path.display())]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// Expected format, e.g. `"PNG"`, `"npy"`.
        format: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// A well-formed file that holds something this reader does not accept
    /// (wrong dtype, wrong PNG colour type, unknown extension...).
    #[error("{}: unsupported {what} '{found}' (expected {expected})", path.display())]
    Unsupported {
        /// The file.
        path: PathBuf,
        /// The property, e.g. `"npy dtype"`, `"PNG pixel type"`, `"file extension"`.
        what: &'static str,
        /// What the file holds.
        found: String,
        /// What is accepted.
        expected: String,
    },
    /// Invalid JSON: a syntax error, a truncated file or a missing/mistyped field.
    #[error("{}: invalid JSON at line {line}, column {column}: {message}", path.display())]
    Json {
        /// The file.
        path: PathBuf,
        /// 1-based line of the problem (0 when unknown).
        line: usize,
        /// 1-based column of the problem (0 when unknown).
        column: usize,
        /// What is wrong.
        message: String,
    },
    /// A calibration file of another format or version.
    #[error(
        "{}: unsupported calibration file: format '{format}', version {version} \
         (this moma reads format 'moma-calibration' versions 1 to {supported})",
        path.display()
    )]
    CalibrationVersion {
        /// The file.
        path: PathBuf,
        /// The `format` field found (`<missing>` when absent).
        format: String,
        /// The `version` field found (`<missing>` when absent).
        version: String,
        /// The version this build reads.
        supported: u32,
    },
    /// An image whose size differs from the size it must have (e.g. camera.json's).
    #[error("{}: image is {got}, expected {expected}", path.display())]
    SizeMismatch {
        /// The file.
        path: PathBuf,
        /// Required size.
        expected: ImageSize,
        /// Size found.
        got: ImageSize,
    },
    /// Content that parses but is not acceptable (camera.json with a non-positive focal length,
    /// a moma set without frames, a frame without depth, an output that would mislabel units...).
    #[error("{}: {message}", path.display())]
    Invalid {
        /// The file or directory.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A `moma-core` check failed on data read from or destined for this file (the message
    /// names the file; the check's own message is the source).
    #[error("{}", path.display())]
    Core {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: CoreError,
    },
    /// A header claims an image larger than this build accepts ([`crate::MAX_IMAGE_PIXELS`],
    /// [`crate::MAX_IMAGE_SIDE_PX`]); refused before anything is allocated for it.
    #[error(
        "{}: {format} header claims {width}x{height} pixels, over the limit of {limit}",
        path.display()
    )]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// The format, e.g. `"PNG"`, `"npy"`, `"PFM"`.
        format: &'static str,
        /// Claimed width, pixels (npy: the product of all dimensions but the first).
        width: u64,
        /// Claimed height, pixels.
        height: u64,
        /// The limit exceeded, e.g. `"67108864 pixels"`.
        limit: String,
    },
}

impl IoError {
    /// The file or directory the error is about.
    pub fn path(&self) -> &Path {
        match self {
            Self::Io { path, .. }
            | Self::Corrupt { path, .. }
            | Self::Unsupported { path, .. }
            | Self::Json { path, .. }
            | Self::CalibrationVersion { path, .. }
            | Self::SizeMismatch { path, .. }
            | Self::Invalid { path, .. }
            | Self::Core { path, .. }
            | Self::TooLarge { path, .. } => path,
        }
    }

    pub(crate) fn io(path: &Path, action: &'static str, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_path_buf(),
            action,
            source,
        }
    }

    pub(crate) fn corrupt(path: &Path, format: &'static str, reason: impl Into<String>) -> Self {
        Self::Corrupt {
            path: path.to_path_buf(),
            format,
            reason: reason.into(),
        }
    }

    pub(crate) fn invalid(path: &Path, message: impl Into<String>) -> Self {
        Self::Invalid {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }

    pub(crate) fn unsupported(
        path: &Path,
        what: &'static str,
        found: impl Into<String>,
        expected: impl Into<String>,
    ) -> Self {
        Self::Unsupported {
            path: path.to_path_buf(),
            what,
            found: found.into(),
            expected: expected.into(),
        }
    }

    pub(crate) fn core(path: &Path, source: CoreError) -> Self {
        Self::Core {
            path: path.to_path_buf(),
            source,
        }
    }

    pub(crate) fn json(path: &Path, err: &serde_json::Error) -> Self {
        // serde_json appends " at line L column C" to its Display; keep only the message.
        let full = err.to_string();
        let message = match full.rfind(" at line ") {
            Some(i) if err.line() > 0 => full[..i].to_string(),
            _ => full,
        };
        let message = if err.is_eof() {
            format!("{message} (file truncated?)")
        } else {
            message
        };
        Self::Json {
            path: path.to_path_buf(),
            line: err.line(),
            column: err.column(),
            message,
        }
    }

    /// Checks `got == expected`, else [`IoError::SizeMismatch`] for `path`.
    pub(crate) fn expect_size(path: &Path, expected: ImageSize, got: ImageSize) -> Result<()> {
        if expected == got {
            Ok(())
        } else {
            Err(Self::SizeMismatch {
                path: path.to_path_buf(),
                expected,
                got,
            })
        }
    }
}

/// Result alias of `moma-io`.
pub type Result<T, E = IoError> = std::result::Result<T, E>;
