//! The one error type of `moma-core`.

use crate::image::ImageSize;

/// Errors of the pure-maths layer: bad input shapes, degenerate data, failed fits.
///
/// Every variant says what was wrong in words a user can act on; callers in
/// `moma-io` / `moma-cli` add the file name.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CoreError {
    /// Two maps that must be pixel-aligned have different sizes.
    #[error("size mismatch: {what} is {got}, expected {expected}")]
    SizeMismatch {
        what: &'static str,
        expected: ImageSize,
        got: ImageSize,
    },
    /// A buffer's length does not match the image size it claims.
    #[error("buffer of {len} values does not match {size} ({expected} values)")]
    BufferLength {
        len: usize,
        size: ImageSize,
        expected: usize,
    },
    /// A prediction map holds NaN or infinite values.
    #[error(
        "prediction holds {count} non-finite value(s) (NaN/inf), first at pixel (u={u}, v={v}) \
         ({})",
        if *metric_depth {
            "a metric-depth prediction marks a pixel without a value by 0 or a negative number"
        } else {
            "a relative prediction has a value at every pixel: NaN or inf is a broken output"
        }
    )]
    NonFinitePrediction {
        count: usize,
        u: usize,
        v: usize,
        /// Whether the prediction is `metric-depth` (which says what the hint is).
        metric_depth: bool,
    },
    /// No valid pixel where one is needed (all-invalid ground truth, empty mask, ...).
    #[error("no valid pixel: {0}")]
    NoValidPixels(String),
    /// Fewer valid samples than the method needs.
    #[error("too few valid samples for {method}: {got}, need at least {need}")]
    TooFewSamples {
        method: &'static str,
        got: usize,
        need: usize,
    },
    /// The data cannot determine the quantity (constant map, collinear samples, singular system...).
    #[error("degenerate input: {0}")]
    Degenerate(String),
    /// A parameter is outside its meaningful range.
    #[error("invalid parameter: {0}")]
    InvalidParameter(String),
    /// A calibration sample holds a non-finite prediction or an invalid ground-truth depth.
    #[error("invalid calibration sample #{index}: {reason}")]
    InvalidSample { index: usize, reason: String },
    /// A prediction of one kind was given to a calibration fitted on another kind.
    #[error("prediction kind mismatch: calibration was fitted on '{expected}', got '{got}'")]
    KindMismatch {
        expected: crate::image::PredictionKind,
        got: crate::image::PredictionKind,
    },
}

/// Result alias of `moma-core`.
pub type Result<T, E = CoreError> = std::result::Result<T, E>;
