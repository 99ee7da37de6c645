//! The common path in one place: calibrate from one frame, align later frames.
//!

use serde::{Deserialize, Serialize};

use crate::align::{AlignmentModel, FitReport, Method, SampleSet};
use crate::error::{CoreError, Result};
use crate::image::{Mask, MetricDepth, Prediction, PredictionKind};
use crate::normalise::{NormalisationConfig, normalise};
use crate::sampling::{SamplingConfig, sample_pixels};

/// Everything a calibration decides.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationConfig {
    /// Alignment method with its settings.
    pub method: Method,
    /// Normalisation of predictions.
    pub normalisation: NormalisationConfig,
    /// Calibration-pixel sampling.
    pub sampling: SamplingConfig,
}

/// A fitted calibration: apply it to any later prediction of the same camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    /// Normalisation used at calibration; the same is applied at run time.
    pub normalisation: NormalisationConfig,
    /// Kind of prediction the calibration was fitted on; run-time predictions must match.
    pub prediction_kind: PredictionKind,
    /// The fitted alignment.
    pub model: AlignmentModel,
    /// The fit report.
    pub report: FitReport,
    /// The samples the fit used.
    pub samples: SampleSet,
}

/// Calibrates from one frame: normalise `pred` (over `workspace` if given), sample ground truth
/// (restricted to `sample_region` if given), fit.
///
/// # Errors
/// Any error of the steps, and size mismatches between inputs.
pub fn calibrate(
    pred: &Prediction,
    gt: &MetricDepth,
    config: &CalibrationConfig,
    workspace: Option<&Mask>,
    sample_region: Option<&Mask>,
) -> Result<Calibration> {
    let size = pred.size();
    size.expect_eq("ground truth", gt.size())?;
    let normalised = normalise(pred, &config.normalisation, workspace)?;
    let pixels = sample_pixels(gt, &config.sampling, sample_region)?;
    let samples = SampleSet::gather(&normalised, gt, &pixels)?;
    let (model, report) = config.method.fit(&samples)?;
    Ok(Calibration {
        normalisation: config.normalisation,
        prediction_kind: pred.kind,
        model,
        report,
        samples,
    })
}

impl Calibration {
    /// Turns a later prediction into metric depth (metres).
    ///
    /// # Errors
    /// Kind or size mismatch with the calibration, normalisation errors.
    pub fn align(&self, pred: &Prediction, workspace: Option<&Mask>) -> Result<MetricDepth> {
        if pred.kind != self.prediction_kind {
            return Err(CoreError::KindMismatch {
                expected: self.prediction_kind,
                got: pred.kind,
            });
        }
        self.samples
            .image_size
            .expect_eq("prediction", pred.size())?;
        let normalised = normalise(pred, &self.normalisation, workspace)?;
        self.model.apply(normalised.values.view())
    }
}
