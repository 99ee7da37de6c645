//! The one error type of `moma-eval`.

use std::path::PathBuf;

/// Errors of the evaluation layer. Every variant names the set / frame / file it is about.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// A file could not be read or written (the message names the file; the cause is the source).
    #[error("{}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// A MOMA file could not be read or written (`moma-io`; the message names the file).
    #[error(transparent)]
    MomaIo(Box<moma_io::IoError>),
    /// A file of one frame could not be read or written: the message names set and frame, the
    /// source (which names the file) says what went wrong.
    #[error("set '{set}', frame '{frame}'")]
    FrameIo {
        /// Set name.
        set: String,
        /// Frame id.
        frame: String,
        /// The cause (names the file).
        #[source]
        error: Box<moma_io::IoError>,
    },
    /// A file's content is malformed (bad JSON...).
    #[error("{path}: {message}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The set cannot be evaluated as asked (one frame, unknown calibration frame, ...).
    #[error("set '{set}': {message}")]
    Set {
        /// Set name.
        set: String,
        /// What is wrong.
        message: String,
    },
    /// The grasp evaluation found no object region large enough to be a trial in the set's
    /// evaluated frames; an evaluation of several sets notes it and goes on.
    #[error(
        "set '{set}': no object region of at least {min_object_px} px in the {frames} evaluated \
         frame(s): nothing to grasp (lower --min-object-px)"
    )]
    NoGraspTrials {
        /// Set name.
        set: String,
        /// The smallest object region that counts, pixels.
        min_object_px: usize,
        /// Evaluated frames.
        frames: usize,
    },
    /// The set has too few frames for what was asked (e.g. few-shot calibration on K frames
    /// needs K + 1); an evaluation of several sets notes it and goes on.
    #[error("set '{set}': too few frames: {frames}, needs at least {needed} ({why})")]
    TooFewFrames {
        /// Set name.
        set: String,
        /// Frames the set has.
        frames: usize,
        /// Frames needed.
        needed: usize,
        /// What they are needed for.
        why: String,
    },
    /// A problem with one frame of a set (missing prediction, size mismatch, no valid pixel...).
    #[error("set '{set}', frame '{frame}': {message}")]
    Frame {
        /// Set name.
        set: String,
        /// Frame id.
        frame: String,
        /// What is wrong.
        message: String,
    },
    /// An error of the maths layer, with context.
    #[error("{context}")]
    Core {
        /// Where it happened (set, frame, method).
        context: String,
        /// The cause.
        #[source]
        source: moma_core::CoreError,
    },
    /// A parameter is outside its meaningful range.
    #[error("invalid parameter: {0}")]
    InvalidParameter(String),
    /// Plotting failed.
    #[error("plot {path}: {message}")]
    Plot {
        /// Output file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
}

/// Result alias of `moma-eval`.
pub type Result<T, E = EvalError> = std::result::Result<T, E>;

impl EvalError {
    /// Wraps an I/O error with its path.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Self::Io {
            path: path.into(),
            source,
        }
    }
    /// A frame-level error.
    pub fn frame(set: &str, frame: &str, message: impl Into<String>) -> Self {
        Self::Frame {
            set: set.to_string(),
            frame: frame.to_string(),
            message: message.into(),
        }
    }
    /// A `moma-io` error on a file of one frame.
    pub fn frame_io(set: &str, frame: &str, source: moma_io::IoError) -> Self {
        Self::FrameIo {
            set: set.to_string(),
            frame: frame.to_string(),
            error: Box::new(source),
        }
    }
    /// A core error with context.
    pub fn core(context: impl Into<String>, source: moma_core::CoreError) -> Self {
        Self::Core {
            context: context.into(),
            source,
        }
    }
}

impl From<moma_io::IoError> for EvalError {
    fn from(e: moma_io::IoError) -> Self {
        Self::MomaIo(Box::new(e))
    }
}
