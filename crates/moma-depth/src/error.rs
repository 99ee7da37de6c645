//! The one error type of `moma-depth`.

/// Errors of the depth-model layer.
#[derive(Debug, thiserror::Error)]
pub enum DepthError {
    /// An input array or image has the wrong shape.
    #[error("bad input shape: {0}")]
    Shape(String),
    /// Weights could not be loaded (missing/unexpected keys, shape mismatches, corrupt file).
    #[error("cannot load weights from {path}: {reason}")]
    Weights { path: String, reason: String },
    /// A model configuration file is unreadable or inconsistent.
    #[error("bad model configuration {path}: {reason}")]
    Config { path: String, reason: String },
    /// The backend failed while running.
    #[error("backend error: {0}")]
    Backend(String),
    /// A backend was asked for that this build does not contain, or its runtime is missing.
    #[error("backend unavailable: {0}")]
    Unavailable(String),
}

/// Result alias of `moma-depth`.
pub type Result<T, E = DepthError> = std::result::Result<T, E>;
