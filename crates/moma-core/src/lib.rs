//! # moma-core — the pure maths of MOMA
//!
//! Monocular one-shot metric-depth alignment: a depth model's prediction is normalised
//! ([`normalise`]), sparse calibration samples are drawn from one RGB-D frame ([`sampling`]),
//! an alignment is fitted on them ([`align`]: SSRA, GSSA, LWLR, RAW) and applied to every later
//! prediction; [`metrics`] scores the result. No file I/O and no ML runtime live here.
//!
//! Data flow, one function per step:
//! `Prediction` → [`normalise::normalise`] → [`sampling::sample_pixels`] + [`align::SampleSet::gather`]
//! → [`align::Method::fit`] → [`align::AlignmentModel::apply`] → [`metrics::DepthMetrics::compute`].
//! [`pipeline`] chains them for the common case.

pub mod align;
pub mod camera;
pub mod error;
pub mod error_model;
mod fused;
pub mod image;
mod kernels;
pub mod metrics;
mod names;
pub mod normalise;
pub mod pipeline;
pub mod policy;
pub mod realign;
pub mod sampling;
pub mod shapes;

pub use camera::{CameraPoint, Intrinsics, depth_to_points};
pub use error::{CoreError, Result};
pub use error_model::DepthErrorModel;
pub use image::{ImageSize, Mask, MetricDepth, Prediction, PredictionKind, is_valid_depth};
pub use normalise::{AlignSpace, Normalisation, NormalisationConfig};
pub use pipeline::{
    AlignOptions, Aligned, Calibration, CalibrationConfig, CalibrationFrame, Workspace, calibrate,
    calibrate_frames,
};
