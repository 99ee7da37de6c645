//! The one error type of `moma-grasp`.

use moma_core::{CoreError, ImageSize};

/// Bad input to the planners and the scorer. "No grasp found" is NOT an error (see
/// [`crate::PlanOutcome`]); these are inputs a caller must fix. Callers that read files
/// (`moma-cli`) add the file name.
#[derive(Debug, thiserror::Error)]
pub enum GraspError {
    /// The depth map has no usable value (all zero, negative or non-finite).
    #[error("the depth map has no valid depth value (all zero, negative or non-finite)")]
    AllInvalidDepth,
    /// The object mask selects pixels, but none of them has valid depth.
    #[error(
        "the object mask selects {masked_px} pixel(s) but none of them has valid depth{}",
        if *masked_px == 0 { " (the mask is empty)" } else { "" }
    )]
    MaskNoValidDepth {
        /// Pixels selected by the mask.
        masked_px: usize,
    },
    /// A map or the camera does not match the depth map's size.
    #[error("{what} is {got}, but the depth map is {expected}")]
    SizeMismatch {
        /// What did not match ("camera intrinsics", "mask").
        what: &'static str,
        /// Size of the depth map.
        expected: ImageSize,
        /// Size found.
        got: ImageSize,
    },
    /// The camera intrinsics are not usable.
    #[error("invalid camera intrinsics")]
    Intrinsics(#[source] CoreError),
    /// The calibration could not align the prediction it was asked to check
    /// ([`crate::calibration_frame_check`]).
    #[error("aligning the calibration frame")]
    Align(#[source] CoreError),
    /// The camera→base matrix is not a rigid transform.
    #[error("the camera-to-base matrix is not a rigid transform: {0}")]
    NonRigidExtrinsics(String),
    /// A gripper size is zero, negative or non-finite, or sizes contradict each other.
    #[error("invalid gripper configuration: {0}")]
    InvalidGripper(String),
    /// A gripper name that is neither `parallel` nor `suction`.
    #[error("unknown gripper '{0}' (expected 'parallel' or 'suction')")]
    UnknownGripper(String),
    /// A grasp handed to the scorer is malformed (zero or non-finite vectors, negative width).
    #[error("invalid grasp: {0}")]
    InvalidGrasp(String),
    /// A planner / scorer threshold is out of range.
    #[error("invalid configuration: {0}")]
    InvalidConfig(String),
}

/// Result alias of this crate.
pub type Result<T> = std::result::Result<T, GraspError>;

/// Checks `value` is finite and `> 0`, naming it otherwise.
pub(crate) fn positive(name: &str, value: f32, err: fn(String) -> GraspError) -> Result<()> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        // settings are f32: a value written below its smallest (about 1e-45) reads as 0
        let read_as = if value == 0.0 {
            " (0, or a value too small for single precision)"
        } else {
            ""
        };
        Err(err(format!(
            "{name} = {value}{read_as} must be a finite number > 0"
        )))
    }
}
