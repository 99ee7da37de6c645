//! The one error type of `moma-depth`.
//!
//! Errors of the backends' libraries (candle, ONNX Runtime) are kept as typed sources, not
//! flattened into strings; each message names only its own context, so printing the error and
//! its [`std::error::Error::source`] chain shows every part once.

/// Errors of the depth-model layer.
#[derive(Debug, thiserror::Error)]
pub enum DepthError {
    /// An input array or image has the wrong shape.
    #[error("bad input shape: {0}")]
    Shape(String),
    /// Weights could not be loaded (missing/unexpected keys, shape mismatches, corrupt file).
    #[error("cannot load weights from {path}: {reason}")]
    Weights {
        /// The weight file.
        path: String,
        /// What is wrong.
        reason: String,
    },
    /// A model configuration file is unreadable or inconsistent.
    #[error("bad model configuration {path}: {reason}")]
    Config {
        /// The configuration file.
        path: String,
        /// What is wrong.
        reason: String,
    },
    /// The backend failed while running, for a reason of this crate's own.
    #[error("backend error: {0}")]
    Backend(String),
    /// candle failed; `context` says what was being done (e.g. loading weights from a file).
    #[cfg(feature = "candle")]
    #[error("candle: {context}")]
    Candle {
        /// What was being done.
        context: String,
        /// candle's error.
        #[source]
        source: candle_core::Error,
    },
    /// ONNX Runtime failed; `context` says what was being done.
    #[cfg(feature = "onnx")]
    #[error("ONNX Runtime: {context}")]
    Onnx {
        /// What was being done.
        context: String,
        /// ONNX Runtime's error.
        #[source]
        source: ort::Error,
    },
    /// A backend was asked for that this build does not contain, or its runtime is missing.
    #[error("backend unavailable: {0}")]
    Unavailable(String),
}

/// Result alias of `moma-depth`.
pub type Result<T, E = DepthError> = std::result::Result<T, E>;
