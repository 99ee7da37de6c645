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
//! [`pipeline`] chains them for the common case: calibrate once, align every later frame.
//!
//! ```
//! use moma_core::align::Method;
//! use moma_core::sampling::SamplingConfig;
//! use moma_core::{
//!     AlignOptions, CalibrationConfig, CalibrationFrame, MetricDepth, Prediction, PredictionKind,
//!     calibrate, policy,
//! };
//! use ndarray::Array2;
//!
//! // The calibration frame: the true depth (a table tilting away, metres) and a depth model's
//! // prediction of it, right only up to a scale and a shift.
//! let truth = Array2::from_shape_fn((48, 64), |(v, u)| 0.6 + 0.004 * v as f32 + 0.001 * u as f32);
//! let pred = Prediction::new(truth.mapv(|z| 2.0 * z + 0.1), PredictionKind::MetricDepth);
//! let method = Method::Gssa;
//! let config = CalibrationConfig {
//!     // the defaults every front end shares: the kind's normalisation (minmax-unit for a
//!     // metric depth), in the prediction's own space
//!     normalisation: policy::normalisation(&method, None, None, pred.kind),
//!     method,
//!     sampling: SamplingConfig { n: 100, seed: 0, ..Default::default() },
//!     robust: None,
//!     workspace: None,
//! };
//! let gt = MetricDepth::new(truth.clone());
//! let calibration = calibrate(&[CalibrationFrame::new(&pred, &gt)], &config)?;
//! // every later frame of the same camera: prediction → metres
//! let depth = calibration.aligned(&pred, &AlignOptions::default())?.depth;
//! assert!((depth.depth_m[[10, 20]] - truth[[10, 20]]).abs() < 1e-4);
//! # Ok::<(), moma_core::CoreError>(())
//! ```

pub mod align;
pub mod camera;
pub mod error;
pub mod error_model;
mod fused;
pub mod height;
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
pub use image::{
    ImageSize, MILLIMETRE_MEDIAN_M, Mask, MetricDepth, NEAR_MEDIAN_M, Prediction, PredictionKind,
    UnitMistake, is_valid_depth, millimetre_median, unit_mistake, valid_median_m,
};
pub use normalise::{AlignSpace, Normalisation, NormalisationConfig};
pub use pipeline::{
    AlignOptions, Aligned, Calibration, CalibrationConfig, CalibrationFrame, FrameReport,
    PredictionInput, Workspace, calibrate,
};
