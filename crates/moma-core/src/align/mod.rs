//! Alignment methods: fit on sparse samples, apply to whole normalised maps (METHOD.md §2).
//!
//! CONTRACT (implemented by the core work item): keep these public names and signatures; add
//! whatever else is needed. A new method is one new module + one variant in [`Method`] and
//! [`AlignmentModel`].

pub mod gssa;
pub mod lwlr;
pub mod ssra;

use ndarray::ArrayView2;
use serde::{Deserialize, Serialize};

use crate::error::Result;
use crate::image::{ImageSize, MetricDepth};
use crate::normalise::NormalisedMap;
use crate::sampling::Pixel;

/// One calibration sample.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    /// Column, pixels.
    pub u: f64,
    /// Row, pixels.
    pub v: f64,
    /// Normalised prediction ẑ (unitless).
    pub pred: f64,
    /// Ground-truth depth, metres.
    pub depth_m: f64,
}

/// The calibration samples of one frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SampleSet {
    /// Size of the image the samples come from.
    pub image_size: ImageSize,
    /// The samples.
    pub samples: Vec<Sample>,
}

impl SampleSet {
    /// Reads ẑ and ground truth at `pixels`; pixels whose ẑ or ground truth is invalid are skipped.
    ///
    /// # Errors
    /// Size mismatch between `normalised` and `gt`; a pixel outside the image.
    pub fn gather(normalised: &NormalisedMap, gt: &MetricDepth, pixels: &[Pixel]) -> Result<Self> {
        let _ = (normalised, gt, pixels);
        todo!("core work item")
    }
}

/// What a fit reports besides its parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FitReport {
    /// Method name (`ssra`, `gssa`, `lwlr`, `raw`).
    pub method: String,
    /// Samples used.
    pub n_used: usize,
    /// Root-mean-square residual on the calibration samples, metres.
    pub rms_residual_m: f64,
    /// Wall time of the fit, seconds.
    pub fit_time_s: f64,
}

/// An alignment method with its settings, not yet fitted.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "method", rename_all = "lowercase")]
pub enum Method {
    /// Identity: the prediction is used as metric depth.
    Raw,
    /// Global scale and shift.
    Gssa,
    /// Scale-shift-rotation (the paper's method).
    Ssra(ssra::SsraConfig),
    /// Locally weighted linear regression.
    Lwlr(lwlr::LwlrConfig),
}

/// A fitted alignment: everything needed to turn a normalised map into metres. Serialisable into a calibration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "method", rename_all = "lowercase")]
pub enum AlignmentModel {
    /// Identity.
    Raw,
    /// Global scale and shift.
    Gssa(gssa::GssaModel),
    /// Scale-shift-rotation.
    Ssra(ssra::SsraModel),
    /// Locally weighted linear regression.
    Lwlr(lwlr::LwlrModel),
}

impl Method {
    /// Method name as used on the command line.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Raw => "raw",
            Self::Gssa => "gssa",
            Self::Ssra(_) => "ssra",
            Self::Lwlr(_) => "lwlr",
        }
    }

    /// Fits on `samples`.
    ///
    /// # Errors
    /// Too few samples, degenerate geometry (e.g. collinear pixels for SSRA), non-finite samples.
    pub fn fit(&self, samples: &SampleSet) -> Result<(AlignmentModel, FitReport)> {
        let _ = samples;
        todo!("core work item")
    }
}

impl AlignmentModel {
    /// Applies the alignment to a whole normalised map; pixels with non-finite ẑ stay `NaN`.
    ///
    /// # Errors
    /// Size mismatch with the calibration image.
    pub fn apply(&self, normalised: ArrayView2<'_, f32>) -> Result<MetricDepth> {
        let _ = normalised;
        todo!("core work item")
    }
}
