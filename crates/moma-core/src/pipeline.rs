//! The one path from calibration to metric depth: what `moma calibrate` / `moma align` run,
//! what `moma eval` measures and what a robot program calls.
//!
//! - [`calibrate`]: from one RGB-D frame or several of the same camera ([`CalibrationFrame`]):
//!   normalise each prediction (over the workspace, if any), sample its ground truth, fit the
//!   alignment in the chosen [`AlignSpace`]; the returned [`Calibration`] owns everything needed
//!   later, including the workspace mask.
//! - [`Calibration::align`]: any later prediction of the same camera to metric depth (metres)
//!   in a caller's buffer, optionally re-aligned on static anchors ([`AlignOptions`]), with the
//!   frame's error model; [`Calibration::aligned`] is the same into a new map, with the σ map.
//!
//! Both take a [`PredictionInput`]: a `&Prediction`, a borrowed view (e.g. a NumPy buffer; not
//! copied), or a prediction already normalised by [`Calibration::normalise`] (the evaluation
//! normalises each frame once and fits many times).
//!
//! # A robot loop (calibrate once, align every frame from memory, no files)
//! ```
//! use moma_core::align::Method;
//! use moma_core::normalise::{Normalisation, NormalisationConfig};
//! use moma_core::sampling::SamplingConfig;
//! use moma_core::{
//!     AlignOptions, CalibrationConfig, CalibrationFrame, MetricDepth, Prediction, PredictionKind,
//!     calibrate,
//! };
//! use ndarray::Array2;
//!
//! // Set-up, once: one RGB-D frame. Here a synthetic 64×48 scene: z = 0.6 m + 1 mm per row,
//! // and a depth model whose output is a disparity with unknown scale and shift.
//! let gt = MetricDepth::new(Array2::from_shape_fn((48, 64), |(v, _)| 0.6 + 0.001 * v as f32));
//! let model_output = |z: &MetricDepth| {
//!     Prediction::new(z.depth_m.mapv(|z| 3.0 / z - 1.5), PredictionKind::RelativeDisparity)
//! };
//! let config = CalibrationConfig {
//!     method: Method::Gssa,
//!     normalisation: NormalisationConfig::native(Normalisation::Minmax, PredictionKind::RelativeDisparity),
//!     sampling: SamplingConfig { n: 100, seed: 0, ..Default::default() },
//!     robust: None,
//!     workspace: None,
//! };
//! let pred = model_output(&gt);
//! let calibration = calibrate(&[CalibrationFrame::new(&pred, &gt)], &config)?;
//!
//! // Every frame: RGB → depth model → metric depth, into a buffer allocated once.
//! let mut depth_m = Array2::<f32>::zeros((48, 64));
//! for _frame in 0..3 {
//!     let pred = model_output(&gt); // the depth model's output for this frame
//!     calibration.align(&pred, &AlignOptions::default(), &mut depth_m.view_mut())?;
//!     assert!((depth_m[[10, 5]] - 0.61).abs() < 1e-4); // metres
//! }
//! # Ok::<(), moma_core::CoreError>(())
//! ```

use std::borrow::Cow;
use std::sync::Arc;

use ndarray::{Array2, ArrayView2, ArrayViewMut2};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::align::robust::Robust;
use crate::align::{AlignmentModel, FitReport, Method, Sample, SampleSet};
use crate::error::{CoreError, Result};
use crate::error_model::{DepthErrorModel, ResidualFrame};
use crate::image::median_in_place;
use crate::image::{ImageSize, Mask, MetricDepth, Prediction, PredictionKind};
use crate::normalise::{
    AlignSpace, Normalisation, NormalisationConfig, NormalisedMap, normalise_view,
};
use crate::realign::{
    AnchorStore, CorrectionModel, GreyHalf, RealignConfig, RealignReport, realign_in_place,
    realign_prediction_affine,
};
use crate::sampling::{SamplingConfig, SamplingStrategy, sample_pixels};

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
    /// The region the predictions are normalised over, at calibration and at run time (the
    /// calibration keeps it); `None`: the whole map.
    pub workspace: Option<Arc<Workspace>>,
}

impl CalibrationConfig {
    /// The same settings, normalising over `mask` (`None`: the whole map).
    ///
    /// # Errors
    /// [`CoreError::NoValidPixels`] for an empty mask.
    pub fn with_workspace(self, mask: Option<&Mask>) -> Result<Self> {
        let workspace = mask
            .map(|m| Workspace::new(m.clone()).map(Arc::new))
            .transpose()?;
        Ok(Self { workspace, ..self })
    }

    /// Checks the combination for predictions of `kind`: a robust fit needs valid settings and a
    /// method that supports it ([`Robust::check_method`]); RAW uses the prediction as metric depth,
    /// so it needs a `metric-depth` prediction, `none` normalisation and depth space.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] explaining the conflict.
    pub fn check(&self, kind: PredictionKind) -> Result<()> {
        if let Some(r) = &self.robust {
            r.validate()?;
            r.check_method(&self.method)?;
        }
        if self.method == Method::Raw {
            if !kind.is_metric() {
                return Err(CoreError::InvalidParameter(format!(
                    "method raw uses the prediction as metres, but the prediction is '{kind}': \
                     raw needs a metric depth model's output (kind 'metric-depth'; the old name \
                     'depth' reads as 'relative-depth' unless its writer recorded a metric model)"
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

/// Largest factor between the median depth a frame aligns to and the median ground truth its
/// calibration was fitted on ([`Calibration::align`] refuses beyond it): no frame of a fixed
/// camera's scene is a hundred times nearer or farther, and a unit mistake is a thousand.
pub const PLAUSIBLE_OUTPUT_FACTOR: f64 = 100.0;

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
    /// The calibration frame's grey and ground truth for per-frame re-alignment on static
    /// anchors ([`crate::realign`]); absent unless added with [`Calibration::with_anchors`].
    /// Not serialised here: the calibration file (`moma_io`) writes it as `anchors`, next to
    /// the other fields, and reads it back.
    #[serde(skip)]
    pub anchors: Option<Arc<AnchorStore>>,
    /// The error model of this calibration's aligned depth ([`crate::error_model`]), fitted
    /// from the calibration frames; absent in files written before it existed, or when the
    /// calibration frames hold no pixel with both an aligned and a true depth (then grasps get
    /// no success probability unless a uniform σ is given).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error_model: Option<DepthErrorModel>,
    /// Notes on the calibration frames' normalisation: a min-max normalisation that hangs on a
    /// few isolated pixels of a frame ([`crate::normalise::isolated_extremes`]), which the fit
    /// then learns, so that every later frame without them is off. Front ends print them when
    /// they calibrate; not stored in the calibration file.
    #[serde(skip)]
    pub normalisation_notes: Vec<String>,
}

/// A depth model's output for one frame, as [`calibrate`] and [`Calibration::align`] take it.
///
/// `&Prediction` converts into it; a borrowed view (e.g. a NumPy buffer, any strides) is
/// [`PredictionInput::view`], so nothing is copied.
#[derive(Debug, Clone, Copy)]
pub enum PredictionInput<'a> {
    /// The raw output of the depth model, of kind `kind`.
    Raw {
        /// `(height, width)` values.
        values: ArrayView2<'a, f32>,
        /// What the values are.
        kind: PredictionKind,
    },
    /// The raw output of kind `kind` already normalised with the calibration's normalisation
    /// over its workspace ([`Calibration::normalise`]): the evaluation normalises each frame
    /// once and fits or aligns it many times.
    Normalised {
        /// The normalised map.
        map: &'a NormalisedMap,
        /// The kind of the raw output it was normalised from.
        kind: PredictionKind,
    },
}

impl<'a> From<&'a Prediction> for PredictionInput<'a> {
    fn from(pred: &'a Prediction) -> Self {
        Self::view(pred.values.view(), pred.kind)
    }
}

impl<'a> PredictionInput<'a> {
    /// A raw output read through a view.
    pub fn view(values: ArrayView2<'a, f32>, kind: PredictionKind) -> Self {
        Self::Raw { values, kind }
    }

    /// A raw output already normalised ([`PredictionInput::Normalised`]).
    pub fn normalised(map: &'a NormalisedMap, kind: PredictionKind) -> Self {
        Self::Normalised { map, kind }
    }

    /// The kind of the raw output.
    pub fn kind(&self) -> PredictionKind {
        match *self {
            Self::Raw { kind, .. } | Self::Normalised { kind, .. } => kind,
        }
    }

    /// The image size, pixels.
    pub fn size(&self) -> ImageSize {
        match self {
            Self::Raw { values, .. } => ImageSize::of(values),
            Self::Normalised { map, .. } => ImageSize::of(&map.values.view()),
        }
    }
}

/// One frame of a calibration: the depth model's prediction, the ground truth of the same frame,
/// and where its samples may be drawn (`None`: anywhere with valid ground truth).
#[derive(Debug, Clone, Copy)]
pub struct CalibrationFrame<'a> {
    /// The depth model's output for the frame.
    pub pred: PredictionInput<'a>,
    /// Ground-truth depth of the same frame, metres.
    pub gt: &'a MetricDepth,
    /// Draw this frame's samples only inside this mask.
    pub sample_region: Option<&'a Mask>,
}

impl<'a> CalibrationFrame<'a> {
    /// A frame whose samples may be drawn anywhere with valid ground truth.
    pub fn new(pred: impl Into<PredictionInput<'a>>, gt: &'a MetricDepth) -> Self {
        Self {
            pred: pred.into(),
            gt,
            sample_region: None,
        }
    }

    /// The same frame with its samples drawn only inside `region` (`None`: anywhere).
    pub fn sampled_in(self, region: Option<&'a Mask>) -> Self {
        Self {
            sample_region: region,
            ..self
        }
    }
}

/// The sampling seed of calibration frame `index`: `seed` for frame 0 (so that the first frame
/// of several draws what it draws alone), `seed + index · 0x9E37_79B9_7F4A_7C15` (wrapping) for
/// the others, so that frames of the same size do not draw the same pixel positions.
pub fn frame_seed(seed: u64, index: usize) -> u64 {
    seed.wrapping_add((index as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
}

/// RAW uses a metric prediction as metres: one whose median is above
/// [`crate::MILLIMETRE_MEDIAN_M`] holds millimetres (a uint16 PNG, or a model's output
/// scaled), and would write kilometres (a median of 2 km and σ maps of 70 m, exit 0).
fn check_raw_metres(values: ArrayView2<'_, f32>) -> Result<()> {
    match crate::millimetre_median(values) {
        Some(median) => Err(CoreError::InvalidParameter(format!(
            "method raw uses the prediction as metres, but its median is {median} m: it looks \
             like millimetres (divide it by 1000, or calibrate with a fitted method)"
        ))),
        None => Ok(()),
    }
}

/// Calibrates from one frame (`&[frame]`) or several of the same camera (few-shot): what
/// `moma calibrate`, `moma eval` and Python run.
///
/// Each frame's prediction is normalised on its own (same formula and space, over
/// `config.workspace` when given), `config.sampling.n` samples are drawn **per frame** (frame `i`
/// with seed [`frame_seed`]`(seed, i)`, inside its own `sample_region`), and one model is fitted
/// on the union in `config.normalisation.space`. [`Calibration::samples`] holds every frame's
/// samples, frame after frame.
///
/// Averaging over frames reduces what changes from frame to frame in the depth model's output
/// (docs/method.md §6: the per-frame fluctuation of scale and shift); it cannot remove what every
/// frame shares.
///
/// # Errors
/// No frame; frames of different sizes or prediction kinds (naming the frame, counted from 0);
/// [`CalibrationConfig::check`] failures (RAW on a relative prediction or with normalisation);
/// size mismatches between inputs; sampling and fitting errors, naming the frame when there
/// are several.
pub fn calibrate(
    frames: &[CalibrationFrame<'_>],
    config: &CalibrationConfig,
) -> Result<Calibration> {
    let (kind, size) = check_frames(frames.iter().map(|f| (f.pred.kind(), f.pred.size())))?;
    config.check(kind)?;
    if config.method == Method::Raw {
        for (i, f) in frames.iter().enumerate() {
            if let PredictionInput::Raw { values, .. } = f.pred {
                check_raw_metres(values).map_err(|e| in_frame(frames.len(), i, e))?;
            }
        }
    }
    if let Some(w) = &config.workspace {
        size.expect_eq("workspace mask", w.mask().size())?;
    }
    let workspace = config.workspace.as_deref().map(Workspace::mask);
    let normalised = frames
        .iter()
        .enumerate()
        .map(|(i, f)| match f.pred {
            PredictionInput::Raw { values, kind } => {
                normalise_view(values, kind, &config.normalisation, workspace)
                    .map(Cow::Owned)
                    .map_err(|e| in_frame(frames.len(), i, e))
            }
            PredictionInput::Normalised { map, .. } => Ok(Cow::Borrowed(map)),
        })
        .collect::<Result<Vec<Cow<'_, NormalisedMap>>>>()?;
    for (i, f) in frames.iter().enumerate() {
        if i == 0 {
            size.expect_eq("ground truth", f.gt.size())?;
        } else if f.gt.size() != size {
            return Err(CoreError::InvalidParameter(format!(
                "calibration frame {i}: the ground truth is {}, but the predictions are {size}",
                f.gt.size()
            )));
        }
        check_ground_truth_metres(f.gt).map_err(|e| in_frame(frames.len(), i, e))?;
    }
    // the limit holds for the samples fitted and cross-validated together: every frame's
    let total = config.sampling.n.saturating_mul(frames.len());
    if frames.len() > 1 && total > crate::sampling::MAX_SAMPLES {
        return Err(CoreError::InvalidParameter(format!(
            "{} frames × {} samples = {total} calibration samples together exceed the limit of \
             {} (the calibration's cross-validation grows as n²): give fewer samples per frame",
            frames.len(),
            config.sampling.n,
            crate::sampling::MAX_SAMPLES
        )));
    }
    let mut samples = SampleSet {
        space: crate::normalise::AlignSpace::Depth,
        image_size: size,
        samples: Vec::new(),
    };
    // each frame's samples in `samples`, for the error model's height part
    let mut frame_ranges = Vec::with_capacity(frames.len());
    for (i, (f, map)) in frames.iter().zip(&normalised).enumerate() {
        let sampling = SamplingConfig {
            seed: frame_seed(config.sampling.seed, i),
            ..config.sampling
        };
        let pixels = sample_pixels(f.gt, &sampling, f.sample_region)
            .map_err(|e| in_frame(frames.len(), i, e))?;
        let frame_samples = SampleSet::gather(map, f.gt, &pixels)?;
        let start = samples.samples.len();
        samples.samples.extend(frame_samples.samples);
        frame_ranges.push(start..samples.samples.len());
    }
    let space = config.normalisation.space;
    let asked = config.sampling.n.saturating_mul(frames.len());
    let fit = |targets: &SampleSet| {
        match &config.robust {
            None => config.method.fit(targets),
            Some(r) => r.fit(&config.method, targets, space),
        }
        .map_err(|e| explain_few_samples(e, &config.sampling, asked))
    };
    let (model, report) = match space {
        AlignSpace::Depth => fit(&samples)?,
        AlignSpace::Inverse => {
            let (model, mut report) = fit(&samples.in_space(space))?;
            report.rms_residual_m = rms_residual_m(&model, space, &samples.samples);
            (model, report)
        }
    };
    let mut calibration = Calibration {
        normalisation: config.normalisation,
        prediction_kind: kind,
        model,
        report,
        samples,
        workspace: config.workspace.clone(),
        anchors: None,
        error_model: None,
        normalisation_notes: frames
            .iter()
            .enumerate()
            .filter_map(|(i, f)| {
                normalisation_note(f.pred, &config.normalisation, workspace).map(
                    |note| match frames.len() {
                        1 => format!("the calibration frame: {note}"),
                        _ => format!("calibration frame {i}: {note}"),
                    },
                )
            })
            .collect(),
    };
    // absent (no success probabilities later) when the calibration frames give no pixel with
    // both an aligned and a true depth to learn it from; the fit itself stands
    let maps: Vec<&NormalisedMap> = normalised.iter().map(|m| m.as_ref()).collect();
    let truths: Vec<(std::ops::Range<usize>, &MetricDepth)> = frame_ranges
        .into_iter()
        .zip(frames.iter().map(|f| f.gt))
        .collect();
    calibration.error_model = fit_error_model(&calibration, &maps, &truths, config).ok();
    Ok(calibration)
}

/// Depths in metres that a ground truth can hold: no sensor measures under 0.1 mm or beyond
/// 10 km. Outside them a value is a placeholder for missing depth (`f32::MAX`, 65 535 read as
/// metres) or not metres at all (a subnormal), and one sampled such pixel makes the fit absurd
/// (a scale of 1e37, exit 0).
pub const PLAUSIBLE_DEPTH_M: std::ops::RangeInclusive<f32> = 1.0e-4..=1.0e4;

/// Refuses a ground truth with a valid pixel ([`crate::is_valid_depth`]) outside
/// [`PLAUSIBLE_DEPTH_M`], naming how many, the first and its pixel.
fn check_ground_truth_metres(gt: &MetricDepth) -> Result<()> {
    let implausible = |z: f32| crate::is_valid_depth(z) && !PLAUSIBLE_DEPTH_M.contains(&z);
    let count = gt.depth_m.iter().filter(|&&z| implausible(z)).count();
    if count == 0 {
        return Ok(());
    }
    let ((v, u), z) = gt
        .depth_m
        .indexed_iter()
        .find(|(_, z)| implausible(**z))
        .map(|(i, z)| (i, *z))
        .unwrap_or(((0, 0), f32::NAN));
    Err(CoreError::InvalidParameter(format!(
        "the ground truth holds {count} pixel(s) outside {}–{} m (the first {z:e} m at u = {u}, \
         v = {v}): a placeholder for missing depth, or not metres; mark missing depth as 0 or NaN",
        PLAUSIBLE_DEPTH_M.start(),
        PLAUSIBLE_DEPTH_M.end()
    )))
}

/// Checks that there is at least one frame and that every frame's prediction has the kind and
/// size of frame 0's; returns them.
fn check_frames(
    frames: impl Iterator<Item = (PredictionKind, ImageSize)>,
) -> Result<(PredictionKind, ImageSize)> {
    let mut first: Option<(PredictionKind, ImageSize)> = None;
    for (i, (kind, pred_size)) in frames.enumerate() {
        let (kind0, size0) = *first.get_or_insert((kind, pred_size));
        if kind != kind0 {
            return Err(CoreError::InvalidParameter(format!(
                "calibration frame {i}: the prediction is '{kind}', but frame 0's is '{kind0}'; \
                 all calibration frames must come from the same depth model"
            )));
        }
        if pred_size != size0 {
            return Err(CoreError::InvalidParameter(format!(
                "calibration frame {i}: the prediction is {pred_size}, but frame 0's is {size0}; \
                 all calibration frames must have the same size (one camera)"
            )));
        }
    }
    first.ok_or_else(|| {
        CoreError::InvalidParameter("calibration needs at least one frame, got none".into())
    })
}

/// Names frame `i` in an error of a several-frame calibration (one frame: unchanged).
fn in_frame(n_frames: usize, i: usize, e: CoreError) -> CoreError {
    if n_frames <= 1 {
        return e;
    }
    match e {
        CoreError::InvalidParameter(m) => {
            CoreError::InvalidParameter(format!("calibration frame {i}: {m}"))
        }
        CoreError::NoValidPixels(m) => {
            CoreError::NoValidPixels(format!("calibration frame {i}: {m}"))
        }
        CoreError::Degenerate(m) => CoreError::Degenerate(format!("calibration frame {i}: {m}")),
        other => other,
    }
}

/// Folds of the cross-validation that measures the fit's optimism at its samples (the error
/// model's flat σ).
const ERROR_MODEL_FOLDS: usize = 5;

/// What `moma calibrate` and Python's `calibrate` warn when a calibration has no error model
/// (its fit found too little to measure on the calibration frames): what the user then lacks.
pub const NO_ERROR_MODEL_WARNING: &str = "the calibration has no error model (its fit found too \
     little to measure on these frames): `moma align --sigma-map` is refused, and grasps planned \
     with it carry no success_prob (null) and are ranked nominal; calibrate on a frame with more \
     valid ground truth";

/// The error model of a fitted calibration ([`DepthErrorModel::fit`]): the dense residuals of
/// its result on each calibration frame, and, for the global fits (GSSA, SSRA: cheap to refit),
/// the fit's optimism at its samples (each sample's residual out of a 5-fold refit against its
/// residual in the fit), which grows the flat σ's dense level; the other methods rest on the dense
/// residuals alone. Folds are seeded by the sampling seed. The
/// height part ([`crate::height`]): the folds' spread of the fit's slope (GSSA, SSRA) and, for a
/// least-squares GSSA, SSRA or LWLR calibration, its objects' pull (`truths`: each calibration
/// frame's range in the samples and its ground truth).
fn fit_error_model(
    calibration: &Calibration,
    normalised: &[&NormalisedMap],
    truths: &[(std::ops::Range<usize>, &MetricDepth)],
    config: &CalibrationConfig,
) -> Result<DepthErrorModel> {
    let aligned = normalised
        .iter()
        .map(|map| calibration.align_normalised(map))
        .collect::<Result<Vec<_>>>()?;
    let residual_frames: Vec<ResidualFrame<'_>> = aligned
        .iter()
        .zip(truths)
        .map(|(a, (_, gt))| ResidualFrame {
            aligned_m: a.depth_m.view(),
            truth_m: gt.depth_m.view(),
        })
        .collect();
    let space = calibration.space();
    let cv = match &config.method {
        Method::Gssa | Method::Ssra(_) => cross_validate(
            &config.method,
            &calibration.model,
            space,
            &calibration.samples,
            config.sampling.seed,
        ),
        _ => CrossValidated::default(),
    };
    let exponent = match space {
        AlignSpace::Depth => 0.0,
        AlignSpace::Inverse => 2.0,
    };
    // where the samples reach only part of the image, the distance part (fit step 5)
    let gts: Vec<&MetricDepth> = truths.iter().map(|(_, gt)| *gt).collect();
    let partial = crate::sampling::sample_reach_over(&calibration.samples, &gts)
        .is_some_and(|r| r.is_partial());
    let distance = if partial {
        sample_distance(calibration)
    } else {
        None
    };
    let mut model = DepthErrorModel::fit_with_sample_distance(
        &residual_frames,
        &cv.residuals,
        exponent,
        distance.as_ref().map(|d| d.view()),
    )?;
    // the objects' pull for a least-squares fit (a robust fit's refits would not be least
    // squares): each frame's samples grouped by that frame's objects
    let pull = match &config.robust {
        None => crate::height::object_scale_pull(
            &config.method,
            &calibration.model,
            space,
            &calibration.samples,
            truths,
        ),
        Some(_) => 0.0,
    };
    model.height_sigma = crate::height::height_sigma(pull, cv.slope_sd);
    // the calibration keeps the gain, not the map (as its file does: a calibration equals the
    // one read back); `Calibration::frame_error_model` attaches the map to each frame's model
    model.sample_distance_px = None;
    Ok(model)
}

/// The distance (pixels) from every pixel of `calibration`'s image to its nearest sample (of
/// any frame: the frames share one camera), for the error model's distance part; `None`
/// without samples.
fn sample_distance(calibration: &Calibration) -> Option<Array2<f32>> {
    let uv = calibration.samples.pixels_uv();
    if uv.is_empty() {
        return None;
    }
    let size = calibration.image_size();
    Some(crate::sampling::sample_distance_map(
        size.height,
        size.width,
        &uv,
    ))
}

/// What the K-fold refits of [`cross_validate`] give.
#[derive(Debug, Default)]
struct CrossValidated {
    /// Every sample's residual held out of a fold's refit and in the full fit, with its true
    /// depth.
    residuals: Vec<crate::error_model::HeldOutResidual>,
    /// The refits' grouped-jackknife relative standard deviation of the fit's slope at the
    /// samples ([`crate::height::jackknife_relative_sd`]; 0 with fewer than two refits).
    slope_sd: f64,
}

/// K-fold cross-validation of `method` on `samples` (`full`: its fit on all of them): each
/// sample's residual held out and in `full`, and how the refits' slope varies; folds that cannot be fitted (too few
/// samples) are left out.
fn cross_validate(
    method: &Method,
    full: &AlignmentModel,
    space: AlignSpace,
    samples: &SampleSet,
    seed: u64,
) -> CrossValidated {
    use rand::seq::SliceRandom;
    let n = samples.samples.len();
    let mut order: Vec<usize> = (0..n).collect();
    order.shuffle(
        &mut <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(
            seed ^ 0x6572_726f_725f_6d64,
        ),
    );
    let mut out = Vec::with_capacity(n);
    let mut fold_slopes = Vec::with_capacity(ERROR_MODEL_FOLDS);
    for k in 0..ERROR_MODEL_FOLDS {
        let held: Vec<usize> = order
            .iter()
            .copied()
            .skip(k)
            .step_by(ERROR_MODEL_FOLDS)
            .collect();
        let train = SampleSet {
            space: samples.space,
            image_size: samples.image_size,
            samples: order
                .iter()
                .enumerate()
                .filter(|(j, _)| j % ERROR_MODEL_FOLDS != k)
                .map(|(_, &i)| samples.samples[i])
                .collect(),
        };
        let Ok((model, _)) = method.fit(&train.in_space(space)) else {
            continue;
        };
        fold_slopes.push(crate::height::slopes(&model, &samples.samples));
        for i in held {
            let s = &samples.samples[i];
            let z = space.depth_from_target(model.predict_at(s.u, s.v, s.pred));
            let z_in = space.depth_from_target(full.predict_at(s.u, s.v, s.pred));
            if z.is_finite() && z_in.is_finite() {
                out.push(crate::error_model::HeldOutResidual {
                    held_out_m: s.target - z,
                    in_sample_m: s.target - z_in,
                    depth_m: s.target,
                });
            }
        }
    }
    let reference = crate::height::slopes(full, &samples.samples);
    CrossValidated {
        residuals: out,
        slope_sd: crate::height::jackknife_relative_sd(&reference, &fold_slopes).unwrap_or(0.0),
    }
}

/// A fit with too few samples, when the edge margin drew fewer than the `asked` ones: says so,
/// since the margin is what the user can change ([`SamplingConfig::edge_margin_px`]).
fn explain_few_samples(e: CoreError, sampling: &SamplingConfig, asked: usize) -> CoreError {
    let edge_margin_px = sampling.edge_margin_px;
    match e {
        CoreError::TooFewSamples { got, .. } if edge_margin_px > 0 && got < asked => {
            CoreError::NoValidPixels(format!(
                "{e}: only {got} ground-truth pixel(s) lie more than the edge margin of \
                 {edge_margin_px} px from a depth discontinuity ({asked} asked); lower the edge \
                 margin"
            ))
        }
        // grid nodes in a small region snap to the same few pixels: say why there are so few
        CoreError::TooFewSamples { got, .. }
            if sampling.strategy == SamplingStrategy::Grid && got < asked =>
        {
            CoreError::NoValidPixels(format!(
                "{e}: grid sampling found only {got} distinct pixel(s) with ground truth for \
                 {asked} grid nodes (nodes outside the sample region snap to the same nearest \
                 pixels); sample at random, or give a larger region"
            ))
        }
        e => e,
    }
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
                z - s.target
            } else {
                s.target
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
        if !size.is_within_limits() {
            return Err(CoreError::InvalidParameter(format!(
                "calibration image size {size} is empty or too large"
            )));
        }
        // Sizes first: a model's own checks build its grid, which a crafted size could make huge.
        if let Some(s) = self.model.image_size() {
            size.expect_eq("alignment model", s)?;
        }
        self.model.validate()?;
        self.samples.validate()?;
        // the report describes these samples: an edited file whose parts disagree is refused
        if self.report.n_used != self.samples.len() {
            return Err(CoreError::InvalidParameter(format!(
                "the fit report says {} samples were used, but the calibration holds {}",
                self.report.n_used,
                self.samples.len()
            )));
        }
        for (what, x) in [
            ("rms_residual_m", self.report.rms_residual_m),
            ("fit_time_s", self.report.fit_time_s),
        ] {
            if !(x.is_finite() && x >= 0.0) {
                return Err(CoreError::InvalidParameter(format!(
                    "the fit report's {what} is {x}, must be finite and ≥ 0"
                )));
            }
        }
        if let Some(w) = &self.workspace {
            size.expect_eq("workspace mask", w.mask().size())?;
        }
        if let Some(a) = &self.anchors {
            a.validate()?;
            size.expect_eq("anchor store", a.image_size())?;
        }
        let method = crate::align::MethodName::from(&self.model);
        if method != self.report.method {
            return Err(CoreError::InvalidParameter(format!(
                "the model is {method} but the fit report says {}",
                self.report.method
            )));
        }
        if let Some(r) = &self.report.robust {
            r.validate(self.report.n_used)?;
        }
        if let Some(m) = &self.error_model {
            m.validate()?;
        }
        if matches!(self.model, AlignmentModel::Raw) {
            CalibrationConfig {
                method: Method::Raw,
                normalisation: self.normalisation,
                sampling: SamplingConfig::default(),
                robust: None,
                workspace: None,
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
        self.normalise_view(pred.values.view(), pred.kind)
    }

    /// [`Calibration::normalise`] of a prediction read through a view (`pred` of kind `kind`).
    ///
    /// # Errors
    /// As [`Calibration::normalise`].
    pub fn normalise_view(
        &self,
        pred: ArrayView2<'_, f32>,
        kind: PredictionKind,
    ) -> Result<NormalisedMap> {
        self.check_prediction(PredictionInput::view(pred, kind))?;
        normalise_view(
            pred,
            kind,
            &self.normalisation,
            self.workspace.as_deref().map(Workspace::mask),
        )
    }

    /// Checks a prediction's kind ([`PredictionKind::accepts`]) and size against the
    /// calibration's.
    fn check_prediction(&self, pred: PredictionInput<'_>) -> Result<()> {
        if !self.prediction_kind.accepts(pred.kind()) {
            return Err(CoreError::KindMismatch {
                expected: self.prediction_kind,
                got: pred.kind(),
            });
        }
        self.image_size().expect_eq("prediction", pred.size())
    }

    /// A checked prediction as a normalised map: a raw one normalised ([`Calibration::normalise`]),
    /// a normalised one borrowed.
    fn normalised_input<'p>(&self, pred: PredictionInput<'p>) -> Result<Cow<'p, NormalisedMap>> {
        Ok(match pred {
            PredictionInput::Raw { values, kind } => Cow::Owned(self.normalise_view(values, kind)?),
            PredictionInput::Normalised { map, .. } => Cow::Borrowed(map),
        })
    }

    /// Turns a prediction into metric depth: the one path from a depth model's output to the
    /// metres that `moma align`, `moma grasp`, `moma eval` and Python use, written into `out`
    /// (the calibration's image size) without allocating.
    ///
    /// Metres; NaN where no depth follows (a non-positive prediction converted to another
    /// space, a non-positive fitted disparity). With [`AlignOptions::realign`], the frame is then
    /// re-aligned on static anchors found in its RGB ([`crate::realign`]; when the correction is
    /// rejected or too few anchors remain, `out` holds the one-shot result and the report says
    /// why). The returned [`FrameReport`] holds the re-alignment report and the frame's error
    /// model.
    ///
    /// For GSSA and SSRA (and `auto` choosing them) with min-max or no normalisation, a raw
    /// prediction is normalised, aligned and (inverse space) inverted fused in two passes over
    /// the image (see the `fused` module), identical bit for bit to normalising and then
    /// applying the model.
    ///
    /// # Errors
    /// Kind or size mismatch with the calibration (prediction or `out`), normalisation errors;
    /// with re-alignment: no anchor store ([`Calibration::anchor_store`]), an RGB of another
    /// size.
    pub fn align<'p>(
        &self,
        pred: impl Into<PredictionInput<'p>>,
        options: &AlignOptions<'_>,
        out: &mut ArrayViewMut2<'_, f32>,
    ) -> Result<FrameReport> {
        let pred = pred.into();
        self.check_prediction(pred)?;
        self.image_size()
            .expect_eq("output buffer", ImageSize::of(&out.view()))?;
        let realign = match options.realign {
            None => {
                self.one_shot_into(pred, out)?;
                None
            }
            Some((grey, config)) => Some(self.realigned_into(pred, grey, config, out)?),
        };
        self.check_plausible_output(&out.view())?;
        let normalisation_note = normalisation_note(
            pred,
            &self.normalisation,
            self.workspace.as_deref().map(Workspace::mask),
        );
        Ok(FrameReport {
            error_model: self.frame_error_model(realign.as_ref()),
            realign,
            normalisation_note,
        })
    }

    /// Refuses an aligned map that no frame of the calibration's scene can be: no pixel with a
    /// depth, or a median more than [`PLAUSIBLE_OUTPUT_FACTOR`] times off the median ground truth
    /// the calibration was fitted on (a metric model's millimetres aligned by a calibration fitted
    /// on its metres are 1 000 × too deep; the reverse gives no depth at all). The median is of
    /// an even stride of about 1 000 pixels (a few µs).
    fn check_plausible_output(&self, out: &ArrayView2<'_, f32>) -> Result<()> {
        let stride = (out.len() / 1024).max(1);
        let mut sampled: Vec<f32> = out
            .iter()
            .step_by(stride)
            .copied()
            .filter(|&z| crate::is_valid_depth(z))
            .collect();
        let Some(out_median) = median_in_place(&mut sampled) else {
            // the stride may miss a small valid region: every pixel before refusing
            if out.iter().any(|&z| crate::is_valid_depth(z)) {
                return Ok(());
            }
            return Err(CoreError::NoValidPixels(
                "the aligned depth has no pixel with a positive depth: the prediction has no \
                 valid value, or is not in the units the calibration was fitted on (metres for \
                 millimetres?)"
                    .into(),
            ));
        };
        let mut truth: Vec<f32> = self
            .samples
            .samples
            .iter()
            .map(|s| s.target as f32)
            .filter(|&d| crate::is_valid_depth(d))
            .collect();
        let Some(truth_median) = median_in_place(&mut truth) else {
            return Ok(());
        };
        let ratio = f64::from(out_median) / f64::from(truth_median);
        if (1.0 / PLAUSIBLE_OUTPUT_FACTOR..=PLAUSIBLE_OUTPUT_FACTOR).contains(&ratio) {
            return Ok(());
        }
        Err(CoreError::Degenerate(format!(
            "the aligned depth's median, {out_median:.3} m, is {} the calibration's ground truth \
             ({truth_median:.3} m): the prediction is not in the units the calibration was \
             fitted on (millimetres for metres, or the reverse?), or not of its scene",
            if ratio > 1.0 {
                format!("{ratio:.0} × deeper than")
            } else {
                format!("1/{:.0} of", 1.0 / ratio)
            }
        )))
    }

    /// [`Calibration::align`] into a new map, with the σ map when [`AlignOptions::sigma_map`]
    /// asks for it.
    ///
    /// # Errors
    /// As [`Calibration::align`].
    pub fn aligned<'p>(
        &self,
        pred: impl Into<PredictionInput<'p>>,
        options: &AlignOptions<'_>,
    ) -> Result<Aligned> {
        let size = self.image_size();
        let mut depth = Array2::<f32>::zeros((size.height, size.width));
        let report = self.align(pred, options, &mut depth.view_mut())?;
        let depth = MetricDepth::new(depth);
        let sigma_m = match (options.sigma_map, &report.error_model) {
            (true, Some(m)) => Some(m.sigma_map(&depth)),
            _ => None,
        };
        Ok(Aligned {
            depth,
            realign: report.realign,
            error_model: report.error_model,
            sigma_m,
            normalisation_note: report.normalisation_note,
        })
    }

    /// The one-shot alignment of a checked prediction into a checked `out`.
    fn one_shot_into(
        &self,
        pred: PredictionInput<'_>,
        out: &mut ArrayViewMut2<'_, f32>,
    ) -> Result<()> {
        match pred {
            PredictionInput::Raw { values, kind } => {
                if matches!(self.model, AlignmentModel::Raw) {
                    check_raw_metres(values)?;
                }
                if let Some(pass) = self.fused_pass(values, kind)? {
                    crate::fused::apply(&pass, values, out);
                    return Ok(());
                }
                self.align_normalised_into(&self.normalise_view(values, kind)?, out)
            }
            PredictionInput::Normalised { map, .. } => self.align_normalised_into(map, out),
        }
    }

    /// Per-frame re-alignment of a checked prediction into a checked `out`, for every
    /// correction form: `prediction-affine` applies the model to the corrected normalised map;
    /// `scale-shift` and `planar` correct the one-shot metres
    /// ([`crate::realign::realign_in_place`]).
    fn realigned_into(
        &self,
        pred: PredictionInput<'_>,
        grey: &GreyHalf,
        config: &RealignConfig,
        out: &mut ArrayViewMut2<'_, f32>,
    ) -> Result<RealignReport> {
        let store = self.anchor_store()?; // no store: fail before aligning
        // nor an RGB of another size: `out` is left as it was when the call fails
        self.image_size().expect_eq("frame RGB", grey.size())?;
        if config.model != CorrectionModel::PredictionAffine {
            self.one_shot_into(pred, out)?;
            return realign_in_place(store, grey, self.space(), config, out);
        }
        let normalised = self.normalised_input(pred)?;
        let (report, ab) = realign_prediction_affine(
            store,
            grey,
            &self.model,
            self.space(),
            config,
            normalised.values.view(),
        )?;
        match ab {
            Some((a, b)) => {
                let corrected = NormalisedMap {
                    values: normalised.values.mapv(|x| a * x + b),
                    stats: normalised.stats,
                };
                self.align_normalised_into(&corrected, out)?;
            }
            None => self.align_normalised_into(&normalised, out)?,
        }
        Ok(report)
    }

    /// The fused path's statistics pass for a checked prediction of kind `kind` (the input's,
    /// as the unfused [`normalise_view`] takes it: a calibration may accept another kind),
    /// `None` where it does not apply.
    fn fused_pass(
        &self,
        pred: ArrayView2<'_, f32>,
        kind: PredictionKind,
    ) -> Result<Option<crate::fused::FusedPass>> {
        let size = self.image_size();
        let Some(terms) = crate::fused::ModelTerms::of(&self.model, size.width, size.height) else {
            return Ok(None);
        };
        let region = self.workspace.as_deref().map(Workspace::mask);
        if let Some(r) = region {
            size.expect_eq("normalisation region", r.size())?;
        }
        crate::fused::prepare(
            pred,
            AlignSpace::native(kind) != self.normalisation.space,
            kind == PredictionKind::MetricDepth,
            &self.normalisation,
            region,
            terms,
        )
    }

    /// The alignment of a prediction already normalised by [`Calibration::normalise`], into a
    /// new map (the anchors' own result, the error model's residuals).
    fn align_normalised(&self, normalised: &NormalisedMap) -> Result<MetricDepth> {
        let mut out = Array2::<f32>::zeros(normalised.values.raw_dim());
        self.align_normalised_into(normalised, &mut out.view_mut())?;
        Ok(MetricDepth::new(out))
    }

    /// [`Calibration::align_normalised`] into a caller's buffer.
    fn align_normalised_into(
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

/// How [`Calibration::align`] aligns one frame.
#[derive(Debug, Clone, Copy, Default)]
pub struct AlignOptions<'a> {
    /// Per-frame re-alignment on static anchors found in this frame's grey (from its RGB:
    /// `moma_io::grey_half`), with these settings (the calibration must hold an anchor store).
    pub realign: Option<(&'a GreyHalf, &'a RealignConfig)>,
    /// Also compute the per-pixel σ map of the result ([`Aligned::sigma_m`];
    /// [`Calibration::aligned`] only).
    pub sigma_map: bool,
}

impl<'a> AlignOptions<'a> {
    /// Re-alignment on static anchors found in the frame's grey `grey`, with `config`.
    pub fn realigned(grey: &'a GreyHalf, config: &'a RealignConfig) -> Self {
        Self {
            realign: Some((grey, config)),
            sigma_map: false,
        }
    }
}

/// The note on a raw prediction whose min-max normalisation hangs on a few isolated pixels
/// ([`crate::normalise::isolated_extremes`]); `None` for a map already normalised (its raw
/// values are not at hand). One rule for [`calibrate`] and [`Calibration::align`].
fn normalisation_note(
    pred: PredictionInput<'_>,
    config: &NormalisationConfig,
    region: Option<&Mask>,
) -> Option<String> {
    match pred {
        PredictionInput::Raw { values, kind } => {
            crate::normalise::isolated_extremes(values, kind, config, region)
        }
        PredictionInput::Normalised { .. } => None,
    }
}

/// What [`Calibration::align`] reports about one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameReport {
    /// The re-alignment report, when re-alignment was asked for.
    pub realign: Option<RealignReport>,
    /// The error model of this frame's depth ([`Calibration::frame_error_model`]); `None` when
    /// the calibration has none.
    pub error_model: Option<DepthErrorModel>,
    /// A note when the frame's min-max normalisation hangs on a few isolated pixels
    /// ([`crate::normalise::isolated_extremes`]); front ends print it.
    pub normalisation_note: Option<String>,
}

/// One aligned frame ([`Calibration::aligned`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Aligned {
    /// Metric depth, metres (NaN: no depth).
    pub depth: MetricDepth,
    /// The re-alignment report, when re-alignment was asked for.
    pub realign: Option<RealignReport>,
    /// The error model of this frame's depth ([`Calibration::frame_error_model`]); `None` when
    /// the calibration has none.
    pub error_model: Option<DepthErrorModel>,
    /// Per-pixel σ of the depth's error, metres (NaN where there is no depth), when asked for
    /// and an error model exists.
    pub sigma_m: Option<Array2<f32>>,
    /// As [`FrameReport::normalisation_note`].
    pub normalisation_note: Option<String>,
}

impl Calibration {
    /// The error model of one frame's aligned depth: the calibration's
    /// ([`Calibration::error_model`]); when the frame was re-aligned, its flat σ from the
    /// frame's own error on the unchanged background, the RMSE of the depth the frame got
    /// against the calibration frame's ground truth at anchors that no fit used
    /// ([`RealignReport::held_out_truth_rmse_m`], [`DepthErrorModel::for_frame_on_background`]).
    /// A report without it (written before the field existed) falls back to the held-out RMSE
    /// of the correction's target (after the correction when accepted, of the one-shot result
    /// otherwise): re-aligned onto the calibration's own output (the default target), that
    /// residual adds to the calibration frames' own error
    /// ([`DepthErrorModel::with_frame_drift`]); onto the calibration frame's ground truth, it
    /// replaces it (at least a quarter of the calibration's σ: [`DepthErrorModel::for_frame`]).
    /// A model with a distance part ([`DepthErrorModel::sample_distance_gain`]) gets its map
    /// from the calibration's samples (built on each call, about a millisecond at 640 × 480;
    /// only such calibrations pay it) and keeps it on re-aligned frames (the frame's level is
    /// measured over the background, near and far from the samples alike: conservative where
    /// re-alignment removed part of the extrapolation). `None` without a model.
    pub fn frame_error_model(&self, realign: Option<&RealignReport>) -> Option<DepthErrorModel> {
        let mut model = self.error_model.clone()?;
        if model.sample_distance_gain > 0.0 && model.sample_distance_px.is_none() {
            // the distance part's map, from the samples (a model read from a file has none)
            model.sample_distance_px = sample_distance(self).map(std::sync::Arc::new);
        }
        let Some(r) = realign else {
            return Some(model);
        };
        if let Some(rmse_m) = r.held_out_truth_rmse_m {
            return Some(
                model.for_frame_on_background(rmse_m, r.held_out_truth_inverse_rmse_per_m),
            );
        }
        let residual = if r.accepted {
            r.held_out_rmse_after_m
        } else {
            r.held_out_rmse_before_m
        };
        Some(match r.target {
            crate::realign::AnchorTarget::CalibrationOutput => model.with_frame_drift(residual),
            crate::realign::AnchorTarget::GroundTruth => model.for_frame(residual),
        })
    }
}

/// Why a workspace mask given at run time is not the calibration's own
/// ([`Calibration::check_workspace`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WorkspaceMismatch {
    /// The calibration embeds another workspace (SHA-256 of the mask differs).
    Differs,
    /// The calibration was fitted without a workspace.
    NoneRecorded,
}

impl Calibration {
    /// Checks that `given` is the workspace this calibration was fitted with (the calibration
    /// always normalises over its own embedded workspace; a different one at run time means
    /// the user expects something else).
    ///
    /// # Errors
    /// [`WorkspaceMismatch`] saying how they differ.
    pub fn check_workspace(&self, given: &Workspace) -> std::result::Result<(), WorkspaceMismatch> {
        match self.workspace.as_deref() {
            Some(own) if own.sha256() == given.sha256() => Ok(()),
            Some(_) => Err(WorkspaceMismatch::Differs),
            None => Err(WorkspaceMismatch::NoneRecorded),
        }
    }
}

impl Calibration {
    /// Adds the anchor store for per-frame re-alignment ([`crate::realign`]): the calibration
    /// frame's grey (from its RGB: `moma_io::grey_half`), its ground truth and its prediction
    /// (the frame the calibration was fitted on, or any frame of the same fixed camera with
    /// ground truth); the store keeps this calibration's own result on that prediction too.
    ///
    /// # Errors
    /// Size or kind mismatches with the calibration, no valid static ground-truth depth.
    pub fn with_anchors<'p>(
        self,
        grey: &GreyHalf,
        gt: &MetricDepth,
        pred: impl Into<PredictionInput<'p>>,
    ) -> Result<Self> {
        self.image_size()
            .expect_eq("anchor ground truth", gt.size())?;
        let store = AnchorStore::new(grey, gt)?;
        self.with_anchor_store(&store, pred)
    }

    /// [`Calibration::with_anchors`] from a store already built from the calibration frame's RGB
    /// and ground truth ([`AnchorStore::new`]), e.g. one store shared by several calibrations of
    /// the same frame: a copy of `store` gets this calibration's own result on `pred` (replacing
    /// any it held).
    ///
    /// # Errors
    /// A store of another image size; kind or size mismatches of `pred`.
    pub fn with_anchor_store<'p>(
        mut self,
        store: &AnchorStore,
        pred: impl Into<PredictionInput<'p>>,
    ) -> Result<Self> {
        self.image_size()
            .expect_eq("anchor store", store.image_size())?;
        let pred = pred.into();
        self.check_prediction(pred)?;
        let normalised = self.normalised_input(pred)?;
        let own = self.align_normalised(&normalised)?;
        self.anchors = Some(Arc::new(
            store
                .clone()
                .with_one_shot(&own)?
                .with_normalised(normalised.values.view())?,
        ));
        Ok(self)
    }

    /// The anchor store, or an error saying how to get one.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] when the calibration holds no anchor store.
    pub fn anchor_store(&self) -> Result<&AnchorStore> {
        self.anchors.as_deref().ok_or_else(|| {
            CoreError::InvalidParameter(
                "this calibration holds no anchor store, so it cannot re-align on static \
                 anchors: calibrate again with the calibration frame's RGB \
                 (`moma calibrate --rgb IMG --anchors`, or `Calibration::with_anchors`)"
                    .into(),
            )
        })
    }
}

impl Calibration {
    /// The error this calibration is expected to make away from its samples, estimated by
    /// cross-validation on its samples: AbsRel and RMS in metres. `auto` and the local
    /// corrections report the score of the model they kept (with their own cross-validation);
    /// GSSA, SSRA and LWLR are cross-validated with the folds of `protocol`
    /// ([`crate::policy::local_config`]: spatially buffered for a fixed camera, plain
    /// leave-one-out per frame); RAW (no fit) reports its error on the samples. `None` for a
    /// robust fit (its cross-validation is not the least-squares one) and for files written
    /// before local models recorded their scores.
    ///
    /// # Errors
    /// The refits' errors (degenerate samples).
    pub fn predicted_error(
        &self,
        protocol: crate::policy::Protocol,
    ) -> Result<Option<crate::align::local::CvScore>> {
        use crate::align::local::{self, CvScore};
        if self.report.robust.is_some() {
            return Ok(None);
        }
        let samples = self.samples.in_space(self.space());
        let plan = crate::policy::local_config(protocol);
        let method = match &self.model {
            AlignmentModel::Auto(m) => return Ok(m.chosen_cv()),
            AlignmentModel::Local(m) => return Ok(m.cv()),
            AlignmentModel::Raw => {
                let raw: Vec<f64> = samples.samples.iter().map(|s| s.pred).collect();
                return Ok(Some(CvScore::of(&samples, &raw)));
            }
            AlignmentModel::Gssa(_) => Method::Gssa,
            AlignmentModel::Ssra(_) => Method::Ssra(Default::default()),
            AlignmentModel::Lwlr(m) => Method::Lwlr(m.config),
        };
        local::cv_score(&samples, &method, &plan).map(Some)
    }

    /// The protocol whose folds [`Calibration::predicted_error`] uses when asked for `asked`:
    /// `auto` and the local corrections report their own cross-validation, made with the folds
    /// of the protocol they were calibrated for (spatially buffered: fixed camera; plain
    /// leave-one-out: per frame), whatever is asked; the other methods use `asked`'s. The label
    /// of the score (it was `asked` for every method).
    pub fn predicted_error_protocol(
        &self,
        asked: crate::policy::Protocol,
    ) -> crate::policy::Protocol {
        use crate::policy::Protocol;
        let buffered = match &self.model {
            AlignmentModel::Auto(m) => m.selection.as_ref().map(|s| s.buffer_px > 0.0),
            AlignmentModel::Local(m) => Some(m.config.cv_buffer_fraction > 0.0),
            _ => None,
        };
        match buffered {
            Some(true) => Protocol::FixedCamera,
            Some(false) => Protocol::PerFrame,
            None => asked,
        }
    }
}
