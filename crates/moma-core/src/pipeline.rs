//! The one path from calibration to metric depth: what `moma calibrate` / `moma align` run,
//! what `moma eval` measures and what a robot program calls.
//!
//! - [`calibrate`]: normalise one frame's prediction (over the workspace, if any), sample its
//!   ground truth, fit the alignment in the chosen [`AlignSpace`]; the returned [`Calibration`]
//!   owns everything needed later, including the workspace mask.
//! - [`Calibration::align`] / [`Calibration::align_into`]: any later prediction of the same
//!   camera to metric depth (metres), the latter without allocating.
//!
//! The evaluation caches normalised maps and calls the same steps through
//! [`calibrate_normalised`] and [`Calibration::align_normalised`], which [`calibrate`] and
//! [`Calibration::align`] are built from.
//!
//! # A robot loop (calibrate once, align every frame from memory, no files)
//! ```
//! use moma_core::align::Method;
//! use moma_core::normalise::{Normalisation, NormalisationConfig};
//! use moma_core::sampling::SamplingConfig;
//! use moma_core::{CalibrationConfig, MetricDepth, Prediction, PredictionKind, calibrate};
//! use ndarray::Array2;
//!
//! // Set-up, once: one RGB-D frame. Here a synthetic 64×48 scene: z = 0.6 m + 1 mm per row,
//! // and a depth model whose output is a disparity with unknown scale and shift.
//! let gt = MetricDepth::new(Array2::from_shape_fn((48, 64), |(v, _)| 0.6 + 0.001 * v as f32));
//! let model_output = |z: &MetricDepth| {
//!     Prediction::new(z.depth_m.mapv(|z| 3.0 / z - 1.5), PredictionKind::InverseDepth)
//! };
//! let config = CalibrationConfig {
//!     method: Method::Gssa,
//!     normalisation: NormalisationConfig::native(Normalisation::Minmax, PredictionKind::InverseDepth),
//!     sampling: SamplingConfig { n: 100, seed: 0, ..Default::default() },
//!     robust: None,
//! };
//! let calibration = calibrate(&model_output(&gt), &gt, &config, None, None)?;
//!
//! // Every frame: RGB → depth model → metric depth, into a buffer allocated once.
//! let mut depth_m = Array2::<f32>::zeros((48, 64));
//! for _frame in 0..3 {
//!     let pred = model_output(&gt); // the depth model's output for this frame
//!     calibration.align_into(&pred, &mut depth_m.view_mut())?;
//!     assert!((depth_m[[10, 5]] - 0.61).abs() < 1e-4); // metres
//! }
//! # Ok::<(), moma_core::CoreError>(())
//! ```

use std::sync::Arc;

use ndarray::{Array2, ArrayViewMut2};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::align::robust::Robust;
use crate::align::{AlignmentModel, FitReport, Method, Sample, SampleSet};
use crate::error::{CoreError, Result};
use crate::image::{ImageSize, Mask, MetricDepth, Prediction, PredictionKind};
use crate::normalise::{AlignSpace, Normalisation, NormalisationConfig, NormalisedMap, normalise};
use crate::sampling::{SamplingConfig, sample_pixels};

/// Everything a calibration decides.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationConfig {
    /// Alignment method with its settings.
    pub method: Method,
    /// Normalisation of predictions, and the space they are aligned in.
    pub normalisation: NormalisationConfig,
    /// Calibration-pixel sampling.
    pub sampling: SamplingConfig,
    /// Robust fit (Huber, Tukey, RANSAC; gssa, ssra and their local variants only); `None`:
    /// least squares.
    pub robust: Option<Robust>,
}

impl CalibrationConfig {
    /// Checks the combination for predictions of `kind`: a robust fit needs valid settings and a
    /// method that supports it ([`Robust::check_method`]); RAW uses the prediction as metric depth,
    /// so it needs a metric `depth` prediction, `none` normalisation and depth space.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] explaining the conflict.
    pub fn check(&self, kind: PredictionKind) -> Result<()> {
        if let Some(r) = &self.robust {
            r.validate()?;
            r.check_method(&self.method)?;
        }
        if self.method == Method::Raw {
            if kind != PredictionKind::Depth {
                return Err(CoreError::InvalidParameter(format!(
                    "method raw uses the prediction as metric depth, but the prediction is \
                     '{kind}': raw needs a metric depth model's output (kind 'depth')"
                )));
            }
            if self.normalisation.method != Normalisation::None {
                return Err(CoreError::InvalidParameter(format!(
                    "method raw uses the prediction as metric depth and needs normalisation \
                     'none', got '{}' (which would write normalised values as metres)",
                    self.normalisation.method
                )));
            }
            if self.normalisation.space != AlignSpace::Depth {
                return Err(CoreError::InvalidParameter(
                    "method raw needs alignment space 'depth'".into(),
                ));
            }
        }
        Ok(())
    }
}

/// A workspace mask owned by a calibration: the region over which predictions are normalised,
/// identical at calibration and at run time.
///
/// Serialised inside the calibration file as run lengths (row-major, alternating runs of
/// outside / inside pixels, the first run "outside", possibly 0) with the SHA-256 of the mask
/// (`width`, `height` as little-endian u64, then one byte 0/1 per pixel); reading checks the size,
/// the run total and the hash.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "WorkspaceRle", into = "WorkspaceRle")]
pub struct Workspace {
    mask: Mask,
    sha256: String,
}

/// The serialised form of a [`Workspace`].
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct WorkspaceRle {
    width: usize,
    height: usize,
    /// Pixels inside.
    inside_px: usize,
    /// Alternating run lengths, starting with an outside run.
    runs: Vec<usize>,
    sha256: String,
}

impl Workspace {
    /// Wraps a mask.
    ///
    /// # Errors
    /// [`CoreError::NoValidPixels`] for an empty mask.
    pub fn new(mask: Mask) -> Result<Self> {
        if mask.count() == 0 {
            return Err(CoreError::NoValidPixels(
                "the workspace mask holds no pixel".into(),
            ));
        }
        let sha256 = mask_sha256(&mask);
        Ok(Self { mask, sha256 })
    }

    /// The mask.
    pub fn mask(&self) -> &Mask {
        &self.mask
    }

    /// Hex SHA-256 of the mask (see the type's documentation for what is hashed).
    pub fn sha256(&self) -> &str {
        &self.sha256
    }
}

fn mask_sha256(mask: &Mask) -> String {
    let size = mask.size();
    let mut h = Sha256::new();
    h.update((size.width as u64).to_le_bytes());
    h.update((size.height as u64).to_le_bytes());
    let bytes: Vec<u8> = mask.data().iter().map(|&b| u8::from(b)).collect();
    h.update(&bytes);
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

impl From<Workspace> for WorkspaceRle {
    fn from(w: Workspace) -> Self {
        let size = w.mask.size();
        let mut runs = Vec::new();
        let mut current = false;
        let mut len = 0usize;
        for &b in w.mask.data().iter() {
            if b == current {
                len += 1;
            } else {
                runs.push(len);
                current = b;
                len = 1;
            }
        }
        runs.push(len);
        Self {
            width: size.width,
            height: size.height,
            inside_px: w.mask.count(),
            runs,
            sha256: w.sha256,
        }
    }
}

impl TryFrom<WorkspaceRle> for Workspace {
    type Error = String;
    fn try_from(r: WorkspaceRle) -> std::result::Result<Self, String> {
        let size = ImageSize::new(r.width, r.height);
        let pixels = r
            .width
            .checked_mul(r.height)
            .filter(|&p| p > 0 && p <= crate::image::MAX_IMAGE_PIXELS)
            .ok_or_else(|| format!("workspace size {size} is empty or too large"))?;
        let total = r
            .runs
            .iter()
            .try_fold(0usize, |acc, &x| acc.checked_add(x))
            .ok_or("workspace run lengths overflow")?;
        if total != pixels {
            return Err(format!(
                "workspace run lengths add up to {total} pixels, but {size} has {pixels}"
            ));
        }
        let mut data = Vec::with_capacity(pixels);
        for (i, &len) in r.runs.iter().enumerate() {
            data.extend(std::iter::repeat_n(i % 2 == 1, len));
        }
        let mask = Mask::from_vec(size, data).map_err(|e| e.to_string())?;
        if mask.count() != r.inside_px {
            return Err(format!(
                "workspace holds {} pixels inside, but inside_px says {}",
                mask.count(),
                r.inside_px
            ));
        }
        let w = Workspace::new(mask).map_err(|e| e.to_string())?;
        if w.sha256 != r.sha256 {
            return Err(format!(
                "workspace content hash mismatch: stored sha256 {}, content gives {}",
                r.sha256, w.sha256
            ));
        }
        Ok(w)
    }
}

/// A fitted calibration: apply it to any later prediction of the same camera.
///
/// It owns what run time needs: the normalisation (formula and [`AlignSpace`]), the prediction
/// kind, the fitted model, and the workspace mask the normalisation statistics are computed over.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Calibration {
    /// Normalisation used at calibration (and its space); the same is applied at run time.
    pub normalisation: NormalisationConfig,
    /// Kind of prediction the calibration was fitted on; run-time predictions must match.
    pub prediction_kind: PredictionKind,
    /// The fitted alignment, in the space of `normalisation.space` (its output is metres in
    /// depth space, 1/m in inverse space).
    pub model: AlignmentModel,
    /// The fit report (`rms_residual_m` in metres whatever the space).
    pub report: FitReport,
    /// The samples the fit used: normalised prediction and ground-truth depth in metres.
    pub samples: SampleSet,
    /// The workspace the normalisation statistics are computed over (`None`: the whole map).
    #[serde(default)]
    pub workspace: Option<Arc<Workspace>>,
}

/// Calibrates from one frame: normalise `pred` (over `workspace` if given), sample ground truth
/// (restricted to `sample_region` if given), fit in `config.normalisation.space`.
///
/// # Errors
/// [`CalibrationConfig::check`] failures (RAW on inverse depth or with normalisation), any error
/// of the steps, size mismatches between inputs, an empty workspace.
pub fn calibrate(
    pred: &Prediction,
    gt: &MetricDepth,
    config: &CalibrationConfig,
    workspace: Option<&Mask>,
    sample_region: Option<&Mask>,
) -> Result<Calibration> {
    config.check(pred.kind)?;
    let workspace = workspace
        .map(|m| Workspace::new(m.clone()).map(Arc::new))
        .transpose()?;
    let normalised = normalise(
        pred,
        &config.normalisation,
        workspace.as_ref().map(|w| w.mask()),
    )?;
    calibrate_normalised(&normalised, pred.kind, gt, config, workspace, sample_region)
}

/// [`calibrate`] from a prediction already normalised with `config.normalisation` over
/// `workspace` (the evaluation normalises each frame once and fits many times).
///
/// # Errors
/// As [`calibrate`].
pub fn calibrate_normalised(
    normalised: &NormalisedMap,
    kind: PredictionKind,
    gt: &MetricDepth,
    config: &CalibrationConfig,
    workspace: Option<Arc<Workspace>>,
    sample_region: Option<&Mask>,
) -> Result<Calibration> {
    config.check(kind)?;
    let size = ImageSize::of(&normalised.values.view());
    size.expect_eq("ground truth", gt.size())?;
    if let Some(w) = &workspace {
        size.expect_eq("workspace mask", w.mask().size())?;
    }
    let pixels = sample_pixels(gt, &config.sampling, sample_region)?;
    let samples = SampleSet::gather(normalised, gt, &pixels)?;
    let space = config.normalisation.space;
    let fit = |targets: &SampleSet| match &config.robust {
        None => config.method.fit(targets),
        Some(r) => r.fit(&config.method, targets, space),
    };
    let (model, report) = match space {
        AlignSpace::Depth => fit(&samples)?,
        AlignSpace::Inverse => {
            let targets = SampleSet {
                image_size: samples.image_size,
                samples: samples
                    .samples
                    .iter()
                    .map(|s| Sample {
                        depth_m: space.target_from_depth(s.depth_m),
                        ..*s
                    })
                    .collect(),
            };
            let (model, mut report) = fit(&targets)?;
            report.rms_residual_m = rms_residual_m(&model, space, &samples.samples);
            (model, report)
        }
    };
    Ok(Calibration {
        normalisation: config.normalisation,
        prediction_kind: kind,
        model,
        report,
        samples,
        workspace,
    })
}

/// RMS of (aligned − ground truth) over `samples`, metres; a sample whose fitted disparity is
/// ≤ 0 (no depth) counts with its full ground-truth depth as error.
fn rms_residual_m(model: &AlignmentModel, space: AlignSpace, samples: &[Sample]) -> f64 {
    if samples.is_empty() {
        return 0.0;
    }
    let ss: f64 = samples
        .iter()
        .map(|s| {
            let z = space.depth_from_target(model.predict_at(s.u, s.v, s.pred));
            let r = if z.is_finite() {
                z - s.depth_m
            } else {
                s.depth_m
            };
            r * r
        })
        .sum();
    (ss / samples.len() as f64).sqrt()
}

impl Calibration {
    /// The image size the calibration is for, pixels.
    pub fn image_size(&self) -> ImageSize {
        self.samples.image_size
    }

    /// The alignment space.
    pub fn space(&self) -> AlignSpace {
        self.normalisation.space
    }

    /// Checks a calibration read from a file: the model ([`AlignmentModel::validate`]), the
    /// samples, RAW's constraints, and the sizes of the model and workspace against the image.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] / [`CoreError::InvalidSample`] / [`CoreError::SizeMismatch`]
    /// naming the problem.
    pub fn validate(&self) -> Result<()> {
        let size = self.image_size();
        if size.pixels() == 0 || size.pixels() > crate::image::MAX_IMAGE_PIXELS {
            return Err(CoreError::InvalidParameter(format!(
                "calibration image size {size} is empty or too large"
            )));
        }
        self.model.validate()?;
        self.samples.validate()?;
        if let Some(s) = self.model.image_size() {
            size.expect_eq("alignment model", s)?;
        }
        if let Some(w) = &self.workspace {
            size.expect_eq("workspace mask", w.mask().size())?;
        }
        let method = self.model.name();
        if method != self.report.method {
            return Err(CoreError::InvalidParameter(format!(
                "the model is {method} but the fit report says {}",
                self.report.method
            )));
        }
        if let Some(r) = &self.report.robust {
            r.validate(self.report.n_used)?;
        }
        if matches!(self.model, AlignmentModel::Raw) {
            CalibrationConfig {
                method: Method::Raw,
                normalisation: self.normalisation,
                sampling: SamplingConfig::default(),
                robust: None,
            }
            .check(self.prediction_kind)?;
        }
        Ok(())
    }

    /// Normalises a run-time prediction exactly as at calibration (same formula, space and
    /// workspace).
    ///
    /// # Errors
    /// Kind or size mismatch with the calibration, normalisation errors.
    pub fn normalise(&self, pred: &Prediction) -> Result<NormalisedMap> {
        if pred.kind != self.prediction_kind {
            return Err(CoreError::KindMismatch {
                expected: self.prediction_kind,
                got: pred.kind,
            });
        }
        self.image_size().expect_eq("prediction", pred.size())?;
        normalise(
            pred,
            &self.normalisation,
            self.workspace.as_deref().map(Workspace::mask),
        )
    }

    /// Turns a later prediction into metric depth (metres; NaN where no depth follows: a
    /// non-positive prediction converted to another space, a non-positive fitted disparity).
    ///
    /// # Errors
    /// Kind or size mismatch with the calibration, normalisation errors.
    pub fn align(&self, pred: &Prediction) -> Result<MetricDepth> {
        let normalised = self.normalise(pred)?;
        self.align_normalised(&normalised)
    }

    /// [`Calibration::align`] writing metres into `out` (the calibration's image size), for
    /// per-frame use without allocating the output.
    ///
    /// # Errors
    /// As [`Calibration::align`], and a size mismatch of `out`.
    pub fn align_into(&self, pred: &Prediction, out: &mut ArrayViewMut2<'_, f32>) -> Result<()> {
        let normalised = self.normalise(pred)?;
        self.align_normalised_into(&normalised, out)
    }

    /// The alignment of a prediction already normalised by [`Calibration::normalise`].
    ///
    /// # Errors
    /// Size mismatch with the calibration image.
    pub fn align_normalised(&self, normalised: &NormalisedMap) -> Result<MetricDepth> {
        let mut out = Array2::<f32>::zeros(normalised.values.raw_dim());
        self.align_normalised_into(normalised, &mut out.view_mut())?;
        Ok(MetricDepth::new(out))
    }

    /// [`Calibration::align_normalised`] into a caller's buffer.
    ///
    /// # Errors
    /// Size mismatch with the calibration image or between `normalised` and `out`.
    pub fn align_normalised_into(
        &self,
        normalised: &NormalisedMap,
        out: &mut ArrayViewMut2<'_, f32>,
    ) -> Result<()> {
        self.image_size()
            .expect_eq("normalised map", ImageSize::of(&normalised.values.view()))?;
        self.model.apply_into(normalised.values.view(), out)?;
        if self.space() == AlignSpace::Inverse {
            crate::kernels::reciprocal_positive(out);
        }
        Ok(())
    }
}
