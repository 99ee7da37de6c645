//! The evaluation protocol of docs/method.md §4: calibrate on one frame, evaluate every other frame
//! inside its mask, over several sampling seeds.
//!
//! Per seed: the calibration frame's prediction is normalised, `samples` valid ground-truth pixels
//! are drawn with that seed, each method is fitted and applied to every other frame; each frame is
//! scored inside its mask (whole image when absent) with [`DepthMetrics::compute`]. Reported:
//! the per-image metrics averaged over frames ("per-image mean"), and the pixel-pooled metrics
//! over all evaluated pixels; both as mean ± standard deviation over seeds (population standard
//! deviation, ddof = 0).

use std::sync::{Arc, Mutex};

use moma_core::align::Method;
use moma_core::align::robust::Robust;
use moma_core::metrics::DepthMetrics;
use moma_core::normalise::{
    AlignSpace, Normalisation, NormalisationConfig, NormalisedMap, normalise,
};
use moma_core::pipeline::{
    AlignOptions, Calibration, CalibrationConfig, CalibrationFrame, PredictionInput, Workspace,
    calibrate,
};
use moma_core::sampling::{SamplingConfig, SamplingStrategy};
use moma_core::{Mask, MetricDepth, Prediction, PredictionKind, is_valid_depth};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::data::LoadedSet;
use crate::error::{EvalError, Result};

/// The methods evaluated by default for predictions of `kind`: SSRA, GSSA, LWLR, and RAW for
/// `metric-depth` predictions only (RAW uses the prediction as metres).
pub fn default_methods(kind: PredictionKind) -> Vec<Method> {
    let mut m = vec![
        Method::Ssra(Default::default()),
        Method::Gssa,
        Method::Lwlr(Default::default()),
    ];
    if kind.is_metric() {
        m.push(Method::Raw);
    }
    m
}

/// Settings of one evaluation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalConfig {
    /// Methods, in table order (SSRA's intrinsics are set from the set's camera).
    pub methods: Vec<Method>,
    /// Normalisations to evaluate (RAW is always evaluated once, without normalisation); none:
    /// the predictions' kind's default ([`moma_core::policy::default_normalisation`]:
    /// `minmax-unit`).
    pub norms: Vec<Normalisation>,
    /// Alignment space; `None`: the predictions' own ([`AlignSpace::native`]).
    pub space: Option<AlignSpace>,
    /// Number of calibration samples n.
    pub samples: usize,
    /// Number of sampling seeds.
    pub seeds: usize,
    /// First sampling seed; seed i uses `seed_base + i`.
    pub seed_base: u64,
    /// Calibration frame id (default: first id in sorted order).
    pub calib_frame: Option<String>,
    /// Sampling strategy.
    pub sampling: SamplingStrategy,
    /// Calibration samples more than this many pixels from depth discontinuities of the ground
    /// truth ([`moma_core::sampling::SamplingConfig::edge_margin_px`]); 0: off.
    #[serde(default)]
    pub edge_margin_px: u32,
    /// Only ground truth within `[min, max]` metres is sampled and scored.
    pub depth_range_m: Option<(f64, f64)>,
    /// Fixed workspace mask (set size): when given, the normalisation statistics of every
    /// frame's prediction (calibration and evaluated frames alike) are computed over this
    /// region only, as [`moma_core::pipeline::calibrate`] / `Calibration::align` do with their
    /// `workspace`. Sampling and scoring are unchanged. Not serialised.
    #[serde(skip)]
    pub workspace: Option<Mask>,
    /// Per-frame re-alignment on static anchors: when given, every (method, normalisation)
    /// also gets rows with `variant` `realign-anchors` ([`crate::realign`]).
    #[serde(default)]
    pub realign: Option<crate::realign::RealignEval>,
    /// Robust variants evaluated besides the one-shot least-squares fit: each gives rows with
    /// variant `robust-<kind>` for the methods that support robust fitting (gssa, ssra and
    /// their local variants; other methods get no robust row). RANSAC's seed is the sampling
    /// seed.
    #[serde(default)]
    pub robust: Vec<Robust>,
    /// SIMULATED sensor errors: this fraction of the calibration frame's valid ground-truth pixels
    /// is replaced by a wrong depth, truth ± U(0.1, 0.5) m (sign at random; `+` where `−` would
    /// leave less than 0.05 m), seeded per sampling seed ([`corrupt_ground_truth`]). Every variant
    /// calibrates on the same corrupted frame; scoring uses the true ground truth of the other
    /// frames. `None`: the ground truth as read.
    #[serde(default)]
    pub gt_outliers: Option<f64>,
    /// Which frames calibrate and which are scored ([`Protocol`]).
    #[serde(default)]
    pub protocol: Protocol,
    /// Only ground truth up to this depth (metres) is scored; unlike
    /// [`EvalConfig::depth_range_m`], sampling is unaffected. `None`: no cap.
    #[serde(default)]
    pub score_max_depth_m: Option<f64>,
}

/// Which frames calibrate and which are scored: [`Protocol::FixedCamera`] calibrates on one
/// frame (or the first K) and scores every other frame (docs/method.md §4); [`Protocol::PerFrame`]
/// calibrates each frame on its own n samples and scores its own dense ground truth
/// (sparse-to-dense, as BoostingDepth's demo does), for single frames or frames that do not share
/// a camera pose, and does not combine with re-alignment or few-shot calibration. The methods'
/// cross-validation follows the protocol when they are built with
/// [`moma_core::policy::method`], as `moma eval` does.
pub use moma_core::policy::Protocol;

/// The `calib_frame` of per-frame rows: every frame calibrates on itself.
pub const PER_FRAME_CALIB: &str = "each";

impl Default for EvalConfig {
    fn default() -> Self {
        Self {
            methods: default_methods(PredictionKind::MetricDepth),
            norms: Vec::new(),
            space: None,
            samples: 100,
            seeds: 10,
            seed_base: 0,
            calib_frame: None,
            sampling: SamplingStrategy::Random,
            edge_margin_px: 0,
            depth_range_m: None,
            workspace: None,
            realign: None,
            robust: Vec::new(),
            gt_outliers: None,
            protocol: Protocol::FixedCamera,
            score_max_depth_m: None,
        }
    }
}

impl EvalConfig {
    /// Checks the sample and seed counts (also before anything is built, e.g. `moma demo`'s
    /// scene).
    ///
    /// # Errors
    /// [`EvalError::InvalidParameter`]: no sample or seed, or more seeds than [`MAX_SEEDS`].
    pub fn check_counts(&self) -> Result<()> {
        if self.samples == 0 || self.seeds == 0 {
            return Err(EvalError::InvalidParameter(
                "--samples and --seeds must be at least 1".into(),
            ));
        }
        if self.seeds > MAX_SEEDS {
            return Err(EvalError::InvalidParameter(format!(
                "--seeds {} is more than the limit of {MAX_SEEDS} (each seed is a full \
                 calibration of every method)",
                self.seeds
            )));
        }
        Ok(())
    }
}

/// Most sampling seeds an evaluation takes: a typo (`--seeds 1000000000000`) is refused rather
/// than allocating per seed and aborting.
pub const MAX_SEEDS: usize = 10_000;

/// Mean and standard deviation (over seeds).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Stat {
    /// Mean.
    pub mean: f64,
    /// Population standard deviation.
    pub std: f64,
}

impl Stat {
    /// Mean and population standard deviation of `xs` (NaN for an empty slice).
    pub fn of(xs: &[f64]) -> Self {
        let n = xs.len() as f64;
        let mean = xs.iter().sum::<f64>() / n;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
        Self {
            mean,
            std: var.sqrt(),
        }
    }
}

/// The six metrics as mean ± std over seeds. RMSE and MAE in metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MetricSummary {
    /// δ < 1.05.
    pub d105: Stat,
    /// δ < 1.10.
    pub d110: Stat,
    /// δ < 1.25.
    pub d125: Stat,
    /// REL.
    pub rel: Stat,
    /// RMSE, metres.
    pub rmse: Stat,
    /// MAE, metres.
    pub mae: Stat,
}

impl MetricSummary {
    /// Summarises one [`DepthMetrics`] per seed.
    pub fn over_seeds(per_seed: &[DepthMetrics]) -> Self {
        let f = |g: fn(&DepthMetrics) -> f64| Stat::of(&per_seed.iter().map(g).collect::<Vec<_>>());
        Self {
            d105: f(|m| m.d105),
            d110: f(|m| m.d110),
            d125: f(|m| m.d125),
            rel: f(|m| m.rel),
            rmse: f(|m| m.rmse),
            mae: f(|m| m.mae),
        }
    }
}

/// Metrics of one evaluated frame, one entry per seed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameResult {
    /// Frame id.
    pub frame: String,
    /// Metrics per seed (seed order).
    pub per_seed: Vec<DepthMetrics>,
}

/// The result of one (set, method, normalisation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalResult {
    /// Set name.
    pub set: String,
    /// Prediction source label.
    pub source: String,
    /// Whether the predictions are simulated (not a trained model).
    pub simulated: bool,
    /// Kind of the predictions.
    pub pred_kind: PredictionKind,
    /// Method name.
    pub method: String,
    /// Which frames calibrated and which were scored.
    #[serde(default)]
    pub protocol: Protocol,
    /// Calibration variant: `one-shot` (one calibration frame, least squares: the paper's
    /// protocol), `few-shot-K` (K frames, [`evaluate_few_shot`]), `robust-<kind>` (a robust fit,
    /// [`EvalConfig::robust`]) or `realign-anchors` (one-shot plus per-frame re-alignment on static
    /// anchors; `realign-anchors-bX.XX` with test-frame brightness ×X.XX).
    pub variant: String,
    /// Normalisation name (`none` for RAW).
    pub norm: String,
    /// Alignment space.
    pub space: AlignSpace,
    /// Calibration samples n asked for.
    pub samples: usize,
    /// Calibration samples were drawn more than this many pixels from depth discontinuities of
    /// the ground truth ([`EvalConfig::edge_margin_px`]; 0: anywhere valid, MOMA's protocol).
    #[serde(default)]
    pub edge_margin_px: u32,
    /// Number of seeds.
    pub seeds: usize,
    /// Calibration frame id (several frames: their ids joined by `+`; [`PER_FRAME_CALIB`] in the
    /// per-frame protocol).
    pub calib_frame: String,
    /// Evaluated frames.
    pub eval_frames: usize,
    /// Per-image mean, mean ± std over seeds.
    pub per_image: MetricSummary,
    /// Pixel-pooled, mean ± std over seeds.
    pub pooled: MetricSummary,
    /// Median fit time over seeds, seconds.
    pub fit_time_median_s: f64,
    /// Mean RMS residual on the calibration samples over seeds, metres.
    pub fit_rms_residual_m: f64,
    /// Per-frame detail.
    pub frames: Vec<FrameResult>,
    /// Re-alignment statistics (variant `realign-anchors` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub realign: Option<crate::realign::RealignStats>,
}

/// The `--json` contract: one object per (set, method, norm) with exactly these keys.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JsonRow {
    /// Set name.
    pub set: String,
    /// Method.
    pub method: String,
    /// Protocol: `fixed-camera` (calibrate on one frame, score the others) or `per-frame`.
    pub protocol: Protocol,
    /// Calibration variant (`one-shot`, `few-shot-K`, `robust-huber`, `realign-anchors`, ...).
    pub variant: String,
    /// Normalisation.
    pub norm: String,
    /// n.
    pub samples: usize,
    /// Number of seeds.
    pub seeds: usize,
    /// Calibration frame.
    pub calib_frame: String,
    /// Per-image mean metrics, mean ± std over seeds (RMSE/MAE in metres).
    #[serde(flatten)]
    pub metrics: MetricSummary,
}

impl From<&EvalResult> for JsonRow {
    fn from(r: &EvalResult) -> Self {
        Self {
            set: r.set.clone(),
            method: r.method.clone(),
            protocol: r.protocol,
            variant: r.variant.clone(),
            norm: r.norm.clone(),
            samples: r.samples,
            seeds: r.seeds,
            calib_frame: r.calib_frame.clone(),
            metrics: r.per_image,
        }
    }
}

/// A set (or variant) that could not be evaluated as asked, shown as a row of the table instead
/// of stopping the evaluation of the other sets.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct EvalNote {
    /// Set name.
    pub set: String,
    /// The variant(s) concerned (e.g. `few-shot`).
    pub variant: String,
    /// What happened, short (e.g. "too few frames: 3, needs at least 4").
    pub note: String,
}

impl EvalNote {
    /// The note for an error that only concerns its own set ([`EvalError::TooFewFrames`]);
    /// `None` for any other error (which should stop the evaluation).
    pub fn from_error(e: &EvalError, variant: &str) -> Option<Self> {
        match e {
            EvalError::TooFewFrames {
                set,
                frames,
                needed,
                why,
            } => Some(Self {
                set: set.clone(),
                variant: variant.to_string(),
                note: format!("too few frames: {frames}, needs at least {needed} ({why})"),
            }),
            _ => None,
        }
    }
}

/// Predictions for every frame of a set (same order as `set.frames`), with their provenance.
#[derive(Debug, Clone)]
pub struct PredictionSet {
    /// Label (e.g. "SIMULATED relative-disparity", a model name).
    pub label: String,
    /// Whether simulated.
    pub simulated: bool,
    /// One prediction per frame.
    pub maps: Vec<Prediction>,
}

impl PredictionSet {
    /// Reads `<dir>/<frame-id>.npy` for every frame. The kind and the label come from the
    /// folder's `predictions.json` (written by `moma predict` / `moma simulate`) and `kind`
    /// (`--pred-kind`): at least one must state it, and they must agree.
    ///
    /// # Errors
    /// Unknown or contradicting kind; a missing file or a size mismatch, naming the frame.
    pub fn read(
        set: &LoadedSet,
        dir: &std::path::Path,
        kind: Option<PredictionKind>,
    ) -> Result<Self> {
        let index = moma_io::read_prediction_index(dir)?;
        let index_what = index
            .as_ref()
            .map(|i| i.path.display().to_string())
            .unwrap_or_default();
        let kind = moma_io::resolve_prediction_kind(
            &[
                ("--pred-kind", kind),
                (index_what.as_str(), index.as_ref().map(|i| i.kind)),
            ],
            None,
        )
        .map_err(|m| {
            EvalError::InvalidParameter(format!("predictions in {}: {m}", dir.display()))
        })?;
        let mut maps = Vec::with_capacity(set.frames.len());
        for f in &set.frames {
            // a map the index does not list was not written by the run the index describes
            // (a folder written into twice): its kind is not known, so it is not read as one
            // (a missing file is reported as missing, below; an entry may name the map, its
            // file or a path to it)
            let map = dir.join(format!("{}.npy", f.id));
            if let Some(i) = index.as_ref().filter(|i| i.disowns(&map))
                && map.is_file()
            {
                return Err(EvalError::frame(
                    &set.name,
                    &f.id,
                    format!(
                        "{} is not listed in {} ({} frames): a file left by another run? \
                         Write the predictions into a folder of their own",
                        map.display(),
                        i.path.display(),
                        i.frames.len()
                    ),
                ));
            }
            let values = crate::data::read_prediction(dir, &set.name, &f.id)?;
            maps.push(Prediction::new(values, kind));
        }
        let simulated = index.as_ref().is_some_and(|i| i.simulated);
        let label = match &index {
            Some(i) if i.simulated => format!("SIMULATED {kind}"),
            Some(i) => format!("{kind}: {}", i.source),
            None => format!("{kind} predictions from {}", dir.display()),
        };
        Ok(Self {
            label,
            simulated,
            maps,
        })
    }

    /// Kind of the maps (of the first; all share it).
    ///
    /// # Errors
    /// An empty set of predictions.
    pub fn kind(&self) -> Result<PredictionKind> {
        self.maps
            .first()
            .map(|p| p.kind)
            .ok_or_else(|| EvalError::InvalidParameter("no prediction".into()))
    }
}

/// A set with its predictions, checked and ready to evaluate.
pub struct Prepared<'a> {
    /// The set.
    pub set: &'a LoadedSet,
    /// Predictions.
    pub preds: &'a PredictionSet,
    /// Index of the calibration frame.
    pub calib: usize,
    /// Evaluation region per frame: mask ∧ valid ground truth ∧ depth range.
    pub eval_masks: Vec<Mask>,
    /// Sampling region on the calibration frame (depth range), if restricted.
    pub sample_region: Option<Mask>,
    /// The workspace every normalisation uses, as a calibration owns it.
    pub workspace: Option<Arc<Workspace>>,
    pub(crate) config: EvalConfig,
    /// Every frame's normalised prediction, one copy per (normalisation, space, brightness
    /// factor), shared by every method, variant and seed of the set ([`Prepared::cached_maps`]).
    maps_cache: Mutex<Vec<MapsEntry>>,
}

/// One entry of [`Prepared`]'s cache: the key (normalisation with its space, brightness factor
/// as bits) and the maps of every frame.
type MapsEntry = (NormalisationConfig, u64, Arc<Vec<NormalisedMap>>);

fn in_range(z: f32, range: Option<(f64, f64)>) -> bool {
    is_valid_depth(z)
        && match range {
            Some((lo, hi)) => (z as f64) >= lo && (z as f64) <= hi,
            None => true,
        }
}

impl<'a> Prepared<'a> {
    /// Checks the inputs: at least two frames, known calibration frame, matching sizes, every
    /// evaluation mask holding valid ground truth.
    ///
    /// # Errors
    /// Each problem names the set and frame.
    pub fn new(set: &'a LoadedSet, preds: &'a PredictionSet, config: &EvalConfig) -> Result<Self> {
        let set_err = |message: String| EvalError::Set {
            set: set.name.clone(),
            message,
        };
        match config.protocol {
            Protocol::FixedCamera if set.frames.len() < 2 => {
                return Err(set_err(format!(
                    "has {} frame(s); the fixed-camera protocol needs one calibration frame and \
                     at least one frame to evaluate (--protocol per-frame scores single frames)",
                    set.frames.len()
                )));
            }
            Protocol::PerFrame if set.frames.is_empty() => {
                return Err(set_err("has no frame".into()));
            }
            Protocol::PerFrame if config.calib_frame.is_some() => {
                return Err(EvalError::InvalidParameter(
                    "a calibration frame does not combine with the per-frame protocol (every \
                     frame calibrates on its own samples)"
                        .into(),
                ));
            }
            Protocol::PerFrame if config.realign.is_some() => {
                return Err(EvalError::InvalidParameter(
                    "re-alignment needs the fixed-camera protocol (the calibration frame's \
                     background is the anchor store); the per-frame protocol does not combine \
                     with it"
                        .into(),
                ));
            }
            _ => {}
        }
        if let Some(cap) = config.score_max_depth_m
            && !(cap.is_finite() && cap > 0.0)
        {
            return Err(EvalError::InvalidParameter(format!(
                "the scoring depth cap must be finite and > 0 m, got {cap}"
            )));
        }
        if preds.maps.len() != set.frames.len() {
            return Err(set_err(format!(
                "{} predictions for {} frames",
                preds.maps.len(),
                set.frames.len()
            )));
        }
        config.check_counts()?;
        let calib = match &config.calib_frame {
            Some(id) => set.frame_index(id).ok_or_else(|| {
                set_err(format!(
                    "calibration frame '{id}' not found (frames: {})",
                    set.frames
                        .iter()
                        .map(|f| f.id.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ))
            })?,
            None => 0,
        };
        let size = set.size();
        if let Some(w) = &config.workspace {
            if w.size() != size {
                return Err(set_err(format!(
                    "workspace mask is {} but the set's images are {}",
                    w.size(),
                    size
                )));
            }
            if w.count() == 0 {
                return Err(set_err("the workspace mask is empty".into()));
            }
        }
        let mut eval_masks = Vec::with_capacity(set.frames.len());
        for (f, p) in set.frames.iter().zip(&preds.maps) {
            if p.size() != size {
                return Err(EvalError::frame(
                    &set.name,
                    &f.id,
                    format!(
                        "prediction is {} but the ground truth is {}",
                        p.size(),
                        size
                    ),
                ));
            }
            let cap = config.score_max_depth_m.unwrap_or(f64::INFINITY);
            let mut region =
                f.gt.depth_m
                    .mapv(|z| in_range(z, config.depth_range_m) && f64::from(z) <= cap);
            if let Some(m) = &f.mask {
                ndarray::Zip::from(&mut region)
                    .and(m.data())
                    .for_each(|r, &inside| *r = *r && inside);
            }
            let region = Mask::new(region);
            if region.count() == 0 {
                if f.mask.as_ref().is_some_and(|m| m.count() == 0) {
                    // a frame with nothing in it (every object picked): nothing to score or grasp
                    return Err(EvalError::frame(
                        &set.name,
                        &f.id,
                        "its mask is empty (no object in the frame): it cannot be scored; leave \
                         the frame out of the set"
                            .to_string(),
                    ));
                }
                let what = if f.mask.is_some() {
                    "its mask"
                } else {
                    "the image"
                };
                let (lo, hi) = config.depth_range_m.unwrap_or((0.0, f64::INFINITY));
                let hi = hi.min(cap);
                let range = if lo > 0.0 || hi.is_finite() {
                    format!(" within {lo}–{hi} m")
                } else {
                    String::new()
                };
                return Err(EvalError::frame(
                    &set.name,
                    &f.id,
                    format!("{what} holds no pixel with valid ground truth{range}"),
                ));
            }
            eval_masks.push(region);
        }
        let sample_region = config
            .depth_range_m
            .map(|r| Mask::new(set.frames[calib].gt.depth_m.mapv(|z| in_range(z, Some(r)))));
        let workspace = config
            .workspace
            .clone()
            .map(|w| Workspace::new(w).map(Arc::new))
            .transpose()
            .map_err(|e| EvalError::core(format!("set '{}': workspace mask", set.name), e))?;
        Ok(Self {
            set,
            preds,
            calib,
            eval_masks,
            sample_region,
            workspace,
            config: config.clone(),
            maps_cache: Mutex::new(Vec::new()),
        })
    }

    /// Calibration frame id.
    pub fn calib_id(&self) -> &str {
        &self.set.frames[self.calib].id
    }

    /// Indices of the evaluated frames: all but the calibration frame (fixed camera), every
    /// frame (per frame).
    pub fn eval_indices(&self) -> Vec<usize> {
        (0..self.set.frames.len())
            .filter(|&i| i != self.calib || self.config.protocol == Protocol::PerFrame)
            .collect()
    }

    /// The protocol of this evaluation.
    pub fn protocol(&self) -> Protocol {
        self.config.protocol
    }

    /// Refuses the per-frame protocol for `what`, which calibrates once and scores other frames.
    ///
    /// # Errors
    /// [`EvalError::InvalidParameter`] naming `what`.
    pub fn require_fixed_camera(&self, what: &str) -> Result<()> {
        require_fixed_camera(self.config.protocol, what)
    }

    /// Normalises the prediction of frame `i` with `norm` over the workspace (when given), as
    /// [`Calibration::normalise`] does; cached by the evaluation across seeds.
    ///
    /// # Errors
    /// Normalisation errors, naming the frame.
    pub fn normalised(&self, i: usize, norm: &NormalisationConfig) -> Result<NormalisedMap> {
        normalise(
            &self.preds.maps[i],
            norm,
            self.workspace.as_deref().map(Workspace::mask),
        )
        .map_err(|e| {
            EvalError::core(
                format!(
                    "set '{}', frame '{}': normalising the prediction",
                    self.set.name, self.set.frames[i].id
                ),
                e,
            )
        })
    }

    /// Every frame's prediction normalised with `norm` ([`Prepared::normalised`]), in frame
    /// order: computed once per (normalisation, space) and shared by every method, variant and
    /// seed evaluated on this set.
    ///
    /// # Errors
    /// As [`Prepared::normalised`].
    pub fn normalised_all(&self, norm: &NormalisationConfig) -> Result<Arc<Vec<NormalisedMap>>> {
        self.cached_maps(norm, 1.0, |i| self.normalised(i, norm))
    }

    /// The maps of every frame under the key (`norm`, `brightness`), made by `make(frame index)`
    /// (in parallel) on the first request and shared afterwards. Brightness 1 is
    /// [`Prepared::normalised_all`]; re-alignment rows with another factor use their own key.
    pub(crate) fn cached_maps(
        &self,
        norm: &NormalisationConfig,
        brightness: f64,
        make: impl Fn(usize) -> Result<NormalisedMap> + Sync + Send,
    ) -> Result<Arc<Vec<NormalisedMap>>> {
        let key = brightness.to_bits();
        let lookup = || {
            self.maps_cache
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .iter()
                .find(|(n, b, _)| n == norm && *b == key)
                .map(|(_, _, maps)| Arc::clone(maps))
        };
        if let Some(maps) = lookup() {
            return Ok(maps);
        }
        let maps: Vec<NormalisedMap> = (0..self.set.frames.len())
            .into_par_iter()
            .map(make)
            .collect::<Result<_>>()?;
        let maps = Arc::new(maps);
        self.maps_cache
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .push((*norm, key, Arc::clone(&maps)));
        Ok(maps)
    }

    /// Calibrates `method` on the calibration frame (normalised as `calib_map`) with sampling
    /// seed `seed`: [`moma_core::calibrate`], the library path of `moma calibrate`.
    ///
    /// # Errors
    /// Sampling or fitting errors, naming the frame.
    pub fn calibrate(
        &self,
        method: &Method,
        norm: &NormalisationConfig,
        calib_map: &NormalisedMap,
        n: usize,
        seed: u64,
    ) -> Result<Calibration> {
        self.calibrate_on(
            method,
            norm,
            &[(self.calib, calib_map, self.sample_region.as_ref())],
            n,
            seed,
            None,
        )
    }

    /// Where frame `i`'s calibration samples may be drawn: its ground truth within the depth
    /// range (`None`: no range, anywhere with valid ground truth).
    pub fn sample_region_of(&self, i: usize) -> Option<Mask> {
        self.config
            .depth_range_m
            .map(|r| Mask::new(self.set.frames[i].gt.depth_m.mapv(|z| in_range(z, Some(r)))))
    }

    /// The sample regions of the calibration frames `calib` (the calibration frame's own, or
    /// [`Prepared::sample_region_of`]), in order.
    pub fn sample_regions(&self, calib: &[usize]) -> Vec<Option<Mask>> {
        calib
            .iter()
            .map(|&i| {
                if i == self.calib {
                    self.sample_region.clone()
                } else {
                    self.sample_region_of(i)
                }
            })
            .collect()
    }

    /// Calibrates `method` on several frames `(index, normalised map, sample region)` with
    /// sampling seed `seed` and `n` samples per frame: [`moma_core::calibrate`], the
    /// library path of `moma calibrate` with several frames. One frame is [`Prepared::calibrate`].
    /// With `robust`, the fit is robust (RANSAC seeded with `seed`); with
    /// [`EvalConfig::gt_outliers`], each calibration frame's ground truth is corrupted first
    /// (SIMULATED; frame k of the list with seed `seed + k`).
    ///
    /// # Errors
    /// Sampling or fitting errors, naming the frames.
    pub fn calibrate_on(
        &self,
        method: &Method,
        norm: &NormalisationConfig,
        frames: &[(usize, &NormalisedMap, Option<&Mask>)],
        n: usize,
        seed: u64,
        robust: Option<&Robust>,
    ) -> Result<Calibration> {
        let config = CalibrationConfig {
            method: method.clone(),
            normalisation: *norm,
            sampling: SamplingConfig {
                strategy: self.config.sampling,
                n,
                seed,
                edge_margin_px: self.config.edge_margin_px,
            },
            robust: robust.map(|r| r.with_seed(seed)),
            workspace: self.workspace.clone(),
        };
        let corrupted: Vec<Option<MetricDepth>> = frames
            .iter()
            .enumerate()
            .map(|(k, &(i, _, _))| {
                self.config.gt_outliers.map(|frac| {
                    corrupt_ground_truth(&self.set.frames[i].gt, frac, seed.wrapping_add(k as u64))
                })
            })
            .collect();
        let kind = self.kind();
        let inputs: Vec<CalibrationFrame<'_>> = frames
            .iter()
            .enumerate()
            .map(|(k, &(i, normalised, sample_region))| {
                CalibrationFrame::new(
                    PredictionInput::normalised(normalised, kind),
                    corrupted[k].as_ref().unwrap_or(&self.set.frames[i].gt),
                )
                .sampled_in(sample_region)
            })
            .collect();
        calibrate(&inputs, &config).map_err(|e| {
            let ids = frames
                .iter()
                .map(|&(i, _, _)| format!("'{}'", self.set.frames[i].id))
                .collect::<Vec<_>>()
                .join(", ");
            let what = if frames.len() == 1 {
                "calibration frame"
            } else {
                "calibration frames"
            };
            EvalError::core(
                format!("set '{}', {what} {ids}, method {method}", self.set.name),
                e,
            )
        })
    }

    /// The kind of the set's predictions.
    pub fn kind(&self) -> PredictionKind {
        self.preds.maps[self.calib].kind
    }

    /// Aligns frame `i` (normalised as `map`) with [`Calibration::aligned`] and scores
    /// it inside its evaluation region.
    ///
    /// # Errors
    /// Apply or metric errors, naming the frame.
    pub fn score(
        &self,
        calibration: &Calibration,
        map: &NormalisedMap,
        i: usize,
    ) -> Result<(MetricDepth, DepthMetrics)> {
        let aligned = self.aligned(calibration, map, i)?;
        let f = &self.set.frames[i];
        let m = DepthMetrics::compute(&aligned, &f.gt, Some(&self.eval_masks[i])).map_err(|e| {
            EvalError::core(format!("set '{}', frame '{}'", self.set.name, f.id), e)
        })?;
        Ok((aligned, m))
    }

    /// Frame `i`'s normalised prediction `map` aligned one-shot by `calibration` (metres).
    ///
    /// # Errors
    /// The alignment's, naming the set and frame.
    pub fn aligned(
        &self,
        calibration: &Calibration,
        map: &NormalisedMap,
        i: usize,
    ) -> Result<MetricDepth> {
        calibration
            .aligned(
                PredictionInput::normalised(map, self.kind()),
                &AlignOptions::default(),
            )
            .map(|a| a.depth)
            .map_err(|e| {
                let id = &self.set.frames[i].id;
                EvalError::core(format!("set '{}', frame '{id}'", self.set.name), e)
            })
    }

    /// The normalisations to evaluate: those of the configuration, or when it names none the
    /// predictions' kind's default ([`moma_core::policy::default_normalisation`]), as `moma
    /// calibrate` would take.
    pub fn norms(&self) -> Vec<Normalisation> {
        if self.config.norms.is_empty() {
            vec![moma_core::policy::default_normalisation(self.kind())]
        } else {
            self.config.norms.clone()
        }
    }

    /// The first of [`Prepared::norms`]: the one normalisation a grasp evaluation plans with and
    /// the demo's figures show.
    pub fn first_norm(&self) -> Normalisation {
        // never empty: the configuration's, or the default
        self.norms()[0]
    }

    /// The normalisation a method is evaluated with: RAW always `none` in depth space, the
    /// others `norm` in the configured space (default: the predictions' own).
    pub fn normalisation_for(&self, method: &Method, norm: Normalisation) -> NormalisationConfig {
        moma_core::policy::evaluation_normalisation(
            method,
            norm,
            self.config.space,
            self.preds.maps[self.calib].kind,
        )
    }

    /// `method` with the set's intrinsics (SSRA reports canonical parameters with them).
    pub fn method(&self, method: &Method) -> Method {
        method.clone().with_intrinsics(Some(self.set.intrinsics))
    }
}

/// Evaluates one set: every (method, normalisation) over every seed.
///
/// # Errors
/// Bad input (see [`Prepared::new`]) or any failure of a step, naming the frame.
pub fn evaluate(
    set: &LoadedSet,
    preds: &PredictionSet,
    config: &EvalConfig,
) -> Result<Vec<EvalResult>> {
    let prep = Prepared::new(set, preds, config)?;
    let jobs = jobs(&prep, config);
    let mut results = Vec::new();
    for (m, norm) in &jobs {
        results.push(evaluate_one(&prep, m, norm, config.samples)?);
        for r in &config.robust {
            if r.check_method(m).is_ok() {
                results.push(evaluate_variant(
                    &prep,
                    m,
                    norm,
                    config.samples,
                    Variant {
                        name: &variant_name(Some(r)),
                        calib: &[prep.calib],
                        eval_idx: &prep.eval_indices(),
                        robust: Some(r),
                    },
                )?);
            }
        }
    }
    if let Some(r) = &config.realign {
        for (m, norm) in &jobs {
            for &b in &r.brightness {
                results.push(crate::realign::evaluate_realign(
                    &prep,
                    m,
                    norm,
                    config.samples,
                    r,
                    b,
                )?);
            }
        }
    }
    Ok(results)
}

/// The distinct (method, effective normalisation) pairs of `config`, in table order.
fn jobs(prep: &Prepared<'_>, config: &EvalConfig) -> Vec<(Method, NormalisationConfig)> {
    let mut jobs: Vec<(Method, NormalisationConfig)> = Vec::new();
    for m in &config.methods {
        let m = prep.method(m);
        for n in prep.norms() {
            let eff = prep.normalisation_for(&m, n);
            if !jobs.iter().any(|(jm, jn)| *jm == m && *jn == eff) {
                jobs.push((m.clone(), eff));
            }
        }
    }
    jobs
}

/// Few-shot evaluation (`moma eval --calib-frames K1,K2,...`): for every K, every (method,
/// normalisation) is calibrated on the first K frames in sorted frame-id order (one fit over
/// `config.samples` samples per frame, [`moma_core::calibrate`]) and scored on
/// the **same** frames for every K: those after the largest K. Rows are labelled
/// [`few_shot_variant`] (`one-shot` for K = 1, `few-shot-K` otherwise), K in the order given,
/// then method and normalisation as in [`evaluate`].
///
/// # Errors
/// [`EvalError::TooFewFrames`] when the set has no frame left to score after the largest K
/// (the caller may note it and go on with other sets); an empty list, K = 0,
/// `config.calib_frame`, robust variants or re-alignment given as well
/// ([`EvalError::InvalidParameter`]); otherwise as
/// [`evaluate`].
pub fn evaluate_few_shot(
    set: &LoadedSet,
    preds: &PredictionSet,
    config: &EvalConfig,
    ks: &[usize],
) -> Result<Vec<EvalResult>> {
    let k_max = check_calib_frame_counts(ks)?;
    check_few_shot(set, config, k_max)?;
    let prep = Prepared::new(set, preds, config)?;
    let eval_idx: Vec<usize> = (k_max..set.frames.len()).collect();
    let jobs = jobs(&prep, config);
    let mut out = Vec::with_capacity(ks.len() * jobs.len());
    for &k in ks {
        let calib: Vec<usize> = (0..k).collect();
        for (m, norm) in &jobs {
            out.push(evaluate_variant(
                &prep,
                m,
                norm,
                config.samples,
                Variant {
                    name: &few_shot_variant(k),
                    calib: &calib,
                    eval_idx: &eval_idx,
                    robust: None,
                },
            )?);
        }
    }
    Ok(out)
}

/// Checks that few-shot evaluation on the first `k_max` frames can run on `set` with `config`
/// (the checks of [`evaluate_few_shot`]).
///
/// # Errors
/// `config.calib_frame`, robust variants or re-alignment given ([`EvalError::InvalidParameter`]);
/// no frame left to score after the first `k_max` ([`EvalError::TooFewFrames`]).
pub fn check_few_shot(set: &LoadedSet, config: &EvalConfig, k_max: usize) -> Result<()> {
    if config.protocol == Protocol::PerFrame {
        return Err(EvalError::InvalidParameter(
            "few-shot calibration (calibration frame counts) needs the fixed-camera protocol; \
             the per-frame protocol calibrates every frame on its own samples"
                .into(),
        ));
    }
    if let Some(id) = &config.calib_frame {
        return Err(EvalError::InvalidParameter(format!(
            "a calibration frame ('{id}') and calibration frame counts cannot both be given: \
             --calib-frames calibrates on the first K frames in sorted order"
        )));
    }
    if !config.robust.is_empty() || config.realign.is_some() {
        return Err(EvalError::InvalidParameter(
            "few-shot evaluation (calibration frame counts) does not combine with robust or \
             re-alignment variants: evaluate those one-shot, in a separate run"
                .into(),
        ));
    }
    if set.frames.len() <= k_max {
        return Err(EvalError::TooFewFrames {
            set: set.name.clone(),
            frames: set.frames.len(),
            needed: k_max + 1,
            why: format!("{k_max} to calibrate on and at least 1 to score"),
        });
    }
    Ok(())
}

/// Checks the K values of `--calib-frames` (at least one, each ≥ 1, no repeats); returns the
/// largest.
///
/// # Errors
/// [`EvalError::InvalidParameter`] naming the problem.
pub fn check_calib_frame_counts(ks: &[usize]) -> Result<usize> {
    if ks.contains(&0) {
        return Err(EvalError::InvalidParameter(
            "calibration frame counts must be at least 1, got 0".into(),
        ));
    }
    for (i, k) in ks.iter().enumerate() {
        if ks[..i].contains(k) {
            return Err(EvalError::InvalidParameter(format!(
                "calibration frame count {k} is given twice"
            )));
        }
    }
    ks.iter().copied().max().ok_or_else(|| {
        EvalError::InvalidParameter("give at least one calibration frame count".into())
    })
}

/// The `variant` of rows fitted with `robust` (`one-shot` without).
pub fn variant_name(robust: Option<&Robust>) -> String {
    match robust {
        None => "one-shot".into(),
        Some(r) => format!("robust-{}", r.kind),
    }
}

/// SIMULATED gross ground-truth errors (sensor edges, glass): a copy of `gt` where each valid
/// pixel, with probability `fraction`, becomes truth ± U(0.1, 0.5) m (sign at random; `+` where
/// `−` would leave less than 0.05 m). Seeded: `ChaCha8Rng::seed_from_u64(seed ^ 0x6f75_746c)`.
pub fn corrupt_ground_truth(gt: &MetricDepth, fraction: f64, seed: u64) -> MetricDepth {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x6f75_746c);
    MetricDepth::new(gt.depth_m.mapv(|z| {
        if !is_valid_depth(z) || !rng.random_bool(fraction.clamp(0.0, 1.0)) {
            return z;
        }
        let d: f32 = rng.random_range(0.1..0.5);
        if rng.random::<bool>() && z - d >= 0.05 {
            z - d
        } else {
            z + d
        }
    }))
}

/// Evaluates one (method, normalisation) with `n` samples over all seeds.
///
/// # Errors
/// As [`evaluate`].
pub fn evaluate_one(
    prep: &Prepared<'_>,
    method: &Method,
    norm: &NormalisationConfig,
    n: usize,
) -> Result<EvalResult> {
    evaluate_variant(
        prep,
        method,
        norm,
        n,
        Variant {
            name: ONE_SHOT,
            calib: &[prep.calib],
            eval_idx: &prep.eval_indices(),
            robust: None,
        },
    )
}

/// The variant name of the paper's protocol (one calibration frame).
pub const ONE_SHOT: &str = "one-shot";

/// The variant name of calibration on `k` frames: `one-shot` for 1, else `few-shot-K`.
pub fn few_shot_variant(k: usize) -> String {
    if k == 1 {
        ONE_SHOT.to_string()
    } else {
        format!("few-shot-{k}")
    }
}

/// What a row of the evaluation varies besides method and normalisation.
#[derive(Debug, Clone, Copy)]
pub struct Variant<'a> {
    /// Row label (`one-shot`, `few-shot-K`, `robust-<kind>`, ...).
    pub name: &'a str,
    /// Frames calibrated on (one fit; one frame is the paper's protocol).
    pub calib: &'a [usize],
    /// Frames scored.
    pub eval_idx: &'a [usize],
    /// Robust fit, if any.
    pub robust: Option<&'a Robust>,
}

/// Evaluates one (method, normalisation) with `n` samples per calibration frame over all
/// seeds: calibrates on the frames `variant.calib`, scores the frames `variant.eval_idx`,
/// labels the row `variant.name`; with `variant.robust`, the fit is robust.
///
/// # Errors
/// As [`evaluate`], and a method that does not support robust fitting.
pub fn evaluate_variant(
    prep: &Prepared<'_>,
    method: &Method,
    norm: &NormalisationConfig,
    n: usize,
    spec: Variant<'_>,
) -> Result<EvalResult> {
    let Variant {
        calib,
        eval_idx,
        robust,
        ..
    } = spec;
    let set = prep.set;
    let config = &prep.config;
    let method = prep.method(method);
    CalibrationConfig {
        method: method.clone(),
        normalisation: *norm,
        sampling: SamplingConfig::default(),
        robust: robust.copied(),
        workspace: None,
    }
    .check(prep.kind())
    .map_err(|e| EvalError::core(format!("set '{}', method {method}", set.name), e))?;
    let maps = prep.normalised_all(norm)?;
    let regions = prep.sample_regions(calib);
    let calib_inputs: Vec<(usize, &NormalisedMap, Option<&Mask>)> = calib
        .iter()
        .zip(&regions)
        .map(|(&i, r)| (i, &maps[i], r.as_ref()))
        .collect();
    let seeds: Vec<u64> = (0..config.seeds as u64)
        .map(|s| config.seed_base + s)
        .collect();
    let per_seed: Vec<(moma_core::align::FitReport, Vec<DepthMetrics>)> = seeds
        .par_iter()
        .map(|&seed| -> Result<_> {
            if prep.protocol() == Protocol::PerFrame {
                // each frame on its own samples; the row's report is the first frame's
                let mut report = None;
                let ms = eval_idx
                    .iter()
                    .map(|&i| {
                        let region = prep.sample_regions(&[i]).pop().flatten();
                        let own = [(i, &maps[i], region.as_ref())];
                        let cal = prep.calibrate_on(&method, norm, &own, n, seed, robust)?;
                        let m = prep.score(&cal, &maps[i], i).map(|(_, m)| m)?;
                        report.get_or_insert(cal.report);
                        Ok(m)
                    })
                    .collect::<Result<Vec<_>>>()?;
                let report = report.ok_or_else(|| {
                    EvalError::InvalidParameter("the per-frame protocol has no frame".into())
                })?;
                return Ok((report, ms));
            }
            let cal = prep.calibrate_on(&method, norm, &calib_inputs, n, seed, robust)?;
            let ms = eval_idx
                .iter()
                .map(|&i| prep.score(&cal, &maps[i], i).map(|(_, m)| m))
                .collect::<Result<Vec<_>>>()?;
            Ok((cal.report, ms))
        })
        .collect::<Result<_>>()?;
    summarise(prep, &method, norm, n, spec, &per_seed)
}

/// The row of one (method, normalisation, variant) from its per-seed fit reports and the metrics
/// of the frames `spec.eval_idx` (per seed, in that order): per-image means and pixel-pooled metrics
/// over seeds, the median fit time, the mean fit residual, the per-frame results.
/// `realign` is `None`; re-alignment rows fill it in.
///
/// # Errors
/// Metric aggregation errors, naming the set.
pub(crate) fn summarise(
    prep: &Prepared<'_>,
    method: &Method,
    norm: &NormalisationConfig,
    n: usize,
    spec: Variant<'_>,
    per_seed: &[(moma_core::align::FitReport, Vec<DepthMetrics>)],
) -> Result<EvalResult> {
    let set = prep.set;
    let Variant {
        name: variant,
        calib,
        eval_idx,
        ..
    } = spec;
    let aggregate = |f: fn(&[DepthMetrics]) -> moma_core::Result<DepthMetrics>| {
        per_seed
            .iter()
            .map(|(_, ms)| {
                f(ms).map_err(|e| {
                    EvalError::core(format!("set '{}', aggregating metrics", prep.set.name), e)
                })
            })
            .collect::<Result<Vec<DepthMetrics>>>()
    };
    let image_means = aggregate(DepthMetrics::mean)?;
    let pooled_ = aggregate(DepthMetrics::pooled)?;
    let mut times: Vec<f64> = per_seed.iter().map(|(r, _)| r.fit_time_s).collect();
    times.sort_by(f64::total_cmp);
    let median = if times.len() % 2 == 1 {
        times[times.len() / 2]
    } else {
        0.5 * (times[times.len() / 2 - 1] + times[times.len() / 2])
    };
    let resid = per_seed.iter().map(|(r, _)| r.rms_residual_m).sum::<f64>() / per_seed.len() as f64;
    let frames = eval_idx
        .iter()
        .enumerate()
        .map(|(k, &i)| FrameResult {
            frame: set.frames[i].id.clone(),
            per_seed: per_seed.iter().map(|(_, ms)| ms[k]).collect(),
        })
        .collect();
    Ok(EvalResult {
        set: set.name.clone(),
        source: prep.preds.label.clone(),
        simulated: prep.preds.simulated,
        pred_kind: prep.preds.maps[0].kind,
        method: method.to_string(),
        protocol: prep.protocol(),
        variant: variant.to_string(),
        norm: norm.method.to_string(),
        space: norm.space,
        samples: n,
        edge_margin_px: prep.config.edge_margin_px,
        seeds: per_seed.len(),
        calib_frame: match prep.protocol() {
            Protocol::PerFrame => PER_FRAME_CALIB.to_string(),
            Protocol::FixedCamera => calib
                .iter()
                .map(|&i| set.frames[i].id.as_str())
                .collect::<Vec<_>>()
                .join("+"),
        },
        eval_frames: eval_idx.len(),
        per_image: MetricSummary::over_seeds(&image_means),
        pooled: MetricSummary::over_seeds(&pooled_),
        fit_time_median_s: median,
        fit_rms_residual_m: resid,
        frames,
        realign: None,
    })
}

/// Aligned depth of every frame for one (method, normalisation, seed): used for figures and
/// exports. The calibration frame is aligned too.
///
/// # Errors
/// As [`evaluate`].
pub fn aligned_maps(
    prep: &Prepared<'_>,
    method: &Method,
    norm: &NormalisationConfig,
    n: usize,
    seed: u64,
) -> Result<(Calibration, Vec<MetricDepth>)> {
    let method = prep.method(method);
    let maps: Vec<NormalisedMap> = (0..prep.set.frames.len())
        .map(|i| prep.normalised(i, norm))
        .collect::<Result<_>>()?;
    let cal = prep.calibrate(&method, norm, &maps[prep.calib], n, seed)?;
    let aligned = maps
        .iter()
        .enumerate()
        .map(|(i, m)| {
            cal.aligned(
                PredictionInput::normalised(m, prep.kind()),
                &AlignOptions::default(),
            )
            .map(|a| a.depth)
            .map_err(|e| {
                EvalError::core(
                    format!("set '{}', frame '{}'", prep.set.name, prep.set.frames[i].id),
                    e,
                )
            })
        })
        .collect::<Result<_>>()?;
    Ok((cal, aligned))
}

/// Refuses the per-frame protocol for `what`, which calibrates once and scores other frames.
///
/// # Errors
/// [`EvalError::InvalidParameter`] naming `what`.
pub fn require_fixed_camera(protocol: Protocol, what: &str) -> Result<()> {
    if protocol == Protocol::PerFrame {
        return Err(EvalError::InvalidParameter(format!(
            "{what} needs the fixed-camera protocol (one calibration, other frames scored), \
             not per-frame"
        )));
    }
    Ok(())
}
