//! The evaluation protocol of METHOD.md §4: calibrate on one frame, evaluate every other frame
//! inside its mask, over several sampling seeds.
//!
//! Per seed: the calibration frame's prediction is normalised, `samples` valid ground-truth pixels
//! are drawn with that seed, each method is fitted and applied to every other frame; each frame is
//! scored inside its mask (whole image when absent) with [`DepthMetrics::compute`]. Reported:
//! the per-image metrics averaged over frames ("per-image mean"), and the pixel-pooled metrics
//! over all evaluated pixels; both as mean ± standard deviation over seeds (population standard
//! deviation, ddof = 0).

use std::time::Instant;

use moma_core::align::lwlr::LwlrConfig;
use moma_core::align::ssra::SsraConfig;
use moma_core::align::{AlignmentModel, FitReport, Method, SampleSet};
use moma_core::metrics::DepthMetrics;
use moma_core::normalise::Normalisation;
use moma_core::normalise::{NormalisationConfig, NormalisedMap, normalise};
use moma_core::sampling::{SamplingConfig, SamplingStrategy, sample_pixels};
use moma_core::{Intrinsics, Mask, MetricDepth, Prediction, PredictionKind, is_valid_depth};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::data::MomaSet;
use crate::error::{EvalError, Result};

/// Method names understood by [`method_from_name`].
pub const METHOD_NAMES: &[&str] = &["ssra", "gssa", "lwlr", "raw"];

/// Further method names: `lwlr-exact` (per-pixel LWLR solve with BoostingDepth's other
/// choices) and `lwlr-bare` (the bare published formula, exact solve).
pub const EXTRA_METHOD_NAMES: &[&str] = &["lwlr-exact", "lwlr-bare"];

/// Builds a core [`Method`] from its command-line name; SSRA reports its canonical parameters
/// with the set's intrinsics.
///
/// # Errors
/// Unknown name.
pub fn method_from_name(name: &str, intrinsics: &Intrinsics) -> Result<Method> {
    match name {
        "ssra" => Ok(Method::Ssra(SsraConfig {
            intrinsics: Some(*intrinsics),
        })),
        "gssa" => Ok(Method::Gssa),
        "lwlr" => Ok(Method::Lwlr(LwlrConfig::default())),
        "lwlr-exact" => Ok(Method::Lwlr(LwlrConfig::exact())),
        "lwlr-bare" => Ok(Method::Lwlr(LwlrConfig::bare_exact())),
        "raw" => Ok(Method::Raw),
        other => Err(EvalError::InvalidParameter(format!(
            "unknown method '{other}' (expected one of {}, {})",
            METHOD_NAMES.join(", "),
            EXTRA_METHOD_NAMES.join(", ")
        ))),
    }
}

/// Command-line name of a normalisation.
pub fn norm_name(n: Normalisation) -> &'static str {
    match n {
        Normalisation::Minmax => "minmax",
        Normalisation::MinmaxUnit => "minmax-unit",
        Normalisation::Median => "median",
        Normalisation::None => "none",
    }
}

/// Parses a normalisation name (`minmax`, `minmax-unit`, `median`, `none`).
///
/// # Errors
/// Unknown name.
pub fn parse_norm(s: &str) -> Result<Normalisation> {
    match s {
        "minmax" => Ok(Normalisation::Minmax),
        "minmax-unit" => Ok(Normalisation::MinmaxUnit),
        "median" => Ok(Normalisation::Median),
        "none" => Ok(Normalisation::None),
        other => Err(EvalError::InvalidParameter(format!(
            "unknown normalisation '{other}' (expected minmax, minmax-unit, median or none)"
        ))),
    }
}

/// Settings of one evaluation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalConfig {
    /// Method names (see [`METHOD_NAMES`]), in table order.
    pub methods: Vec<String>,
    /// Normalisations to evaluate (RAW is always evaluated once, without normalisation).
    pub norms: Vec<Normalisation>,
    /// For inverse-depth predictions: align in inverse space.
    pub inverse_space: bool,
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
    /// Only ground truth within `[min, max]` metres is sampled and scored.
    pub depth_range_m: Option<(f64, f64)>,
    /// Fixed workspace mask (set size): when given, the normalisation statistics of every
    /// frame's prediction (calibration and evaluated frames alike) are computed over this
    /// region only, as [`moma_core::pipeline::calibrate`] / `Calibration::align` do with their
    /// `workspace`. Sampling and scoring are unchanged. Not serialised.
    #[serde(skip)]
    pub workspace: Option<Mask>,
}

impl Default for EvalConfig {
    fn default() -> Self {
        Self {
            methods: METHOD_NAMES.iter().map(|s| s.to_string()).collect(),
            norms: vec![Normalisation::Minmax],
            inverse_space: false,
            samples: 100,
            seeds: 10,
            seed_base: 0,
            calib_frame: None,
            sampling: SamplingStrategy::Random,
            depth_range_m: None,
            workspace: None,
        }
    }
}

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
    /// Normalisation name (`none` for RAW).
    pub norm: String,
    /// Calibration samples n asked for.
    pub samples: usize,
    /// Number of seeds.
    pub seeds: usize,
    /// Calibration frame id.
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
}

/// The `--json` contract: one object per (set, method, norm) with exactly these keys.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JsonRow {
    /// Set name.
    pub set: String,
    /// Method.
    pub method: String,
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
            norm: r.norm.clone(),
            samples: r.samples,
            seeds: r.seeds,
            calib_frame: r.calib_frame.clone(),
            metrics: r.per_image,
        }
    }
}

/// Predictions for every frame of a set (same order as `set.frames`), with their provenance.
#[derive(Debug, Clone)]
pub struct PredictionSet {
    /// Label (e.g. "simulated inverse-depth", a model name).
    pub label: String,
    /// Whether simulated.
    pub simulated: bool,
    /// One prediction per frame.
    pub maps: Vec<Prediction>,
}

impl PredictionSet {
    /// Reads `<dir>/<frame-id>.npy` for every frame; `simulated` from `simulated.json`.
    ///
    /// # Errors
    /// A missing file or a size mismatch, naming the frame.
    pub fn read(set: &MomaSet, dir: &std::path::Path, kind: PredictionKind) -> Result<Self> {
        let meta = crate::simulate::read_simulated_meta(dir);
        if let Some(m) = &meta
            && m.kind != kind
        {
            return Err(EvalError::InvalidParameter(format!(
                "{}: simulated.json says the predictions are '{}' but --pred-kind is '{}'",
                dir.display(),
                m.kind,
                kind
            )));
        }
        let mut maps = Vec::with_capacity(set.frames.len());
        for f in &set.frames {
            let values = crate::data::read_prediction(dir, &set.name, &f.id)?;
            maps.push(Prediction::new(values, kind));
        }
        let label = match &meta {
            Some(m) => format!("simulated {kind} (seed {})", m.seed),
            None => format!("{kind} predictions"),
        };
        Ok(Self {
            label,
            simulated: meta.is_some(),
            maps,
        })
    }
}

/// A set with its predictions, checked and ready to evaluate.
pub struct Prepared<'a> {
    /// The set.
    pub set: &'a MomaSet,
    /// Predictions.
    pub preds: &'a PredictionSet,
    /// Index of the calibration frame.
    pub calib: usize,
    /// Evaluation region per frame: mask ∧ valid ground truth ∧ depth range.
    pub eval_masks: Vec<Mask>,
    /// Sampling region on the calibration frame (depth range), if restricted.
    pub sample_region: Option<Mask>,
    config: EvalConfig,
}

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
    pub fn new(set: &'a MomaSet, preds: &'a PredictionSet, config: &EvalConfig) -> Result<Self> {
        let set_err = |message: String| EvalError::Set {
            set: set.name.clone(),
            message,
        };
        if set.frames.len() < 2 {
            return Err(set_err(format!(
                "has {} frame(s); the protocol needs one calibration frame and at least one frame to evaluate",
                set.frames.len()
            )));
        }
        if preds.maps.len() != set.frames.len() {
            return Err(set_err(format!(
                "{} predictions for {} frames",
                preds.maps.len(),
                set.frames.len()
            )));
        }
        if config.samples == 0 || config.seeds == 0 {
            return Err(EvalError::InvalidParameter(
                "--samples and --seeds must be at least 1".into(),
            ));
        }
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
            let mut region = f.gt.depth_m.mapv(|z| in_range(z, config.depth_range_m));
            if let Some(m) = &f.mask {
                ndarray::Zip::from(&mut region)
                    .and(m.data())
                    .for_each(|r, &inside| *r = *r && inside);
            }
            let region = Mask::new(region);
            if region.count() == 0 {
                let what = if f.mask.is_some() {
                    "its mask"
                } else {
                    "the image"
                };
                let range = match config.depth_range_m {
                    Some((lo, hi)) => format!(" within {lo}–{hi} m"),
                    None => String::new(),
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
        Ok(Self {
            set,
            preds,
            calib,
            eval_masks,
            sample_region,
            config: config.clone(),
        })
    }

    /// Calibration frame id.
    pub fn calib_id(&self) -> &str {
        &self.set.frames[self.calib].id
    }

    /// Indices of the evaluated frames (all but the calibration frame).
    pub fn eval_indices(&self) -> Vec<usize> {
        (0..self.set.frames.len())
            .filter(|&i| i != self.calib)
            .collect()
    }

    /// Normalises the prediction of frame `i` (statistics over [`EvalConfig::workspace`] when
    /// given, else over the whole map).
    ///
    /// # Errors
    /// Normalisation errors, naming the frame.
    pub fn normalised(&self, i: usize, norm: &NormalisationConfig) -> Result<NormalisedMap> {
        normalise(&self.preds.maps[i], norm, self.config.workspace.as_ref()).map_err(|e| {
            EvalError::core(
                format!(
                    "set '{}', frame '{}': normalising the prediction",
                    self.set.name, self.set.frames[i].id
                ),
                e,
            )
        })
    }

    /// Calibrates `method` on the calibration frame with sampling seed `seed`.
    ///
    /// # Errors
    /// Sampling or fitting errors, naming the frame.
    pub fn calibrate(
        &self,
        method: &Method,
        calib_map: &NormalisedMap,
        n: usize,
        seed: u64,
    ) -> Result<(AlignmentModel, FitReport)> {
        let f = &self.set.frames[self.calib];
        let ctx = || {
            format!(
                "set '{}', calibration frame '{}', method {}",
                self.set.name,
                f.id,
                method.name()
            )
        };
        let sampling = SamplingConfig {
            strategy: self.config.sampling,
            n,
            seed,
        };
        let pixels = sample_pixels(&f.gt, &sampling, self.sample_region.as_ref())
            .map_err(|e| EvalError::core(ctx(), e))?;
        let samples =
            SampleSet::gather(calib_map, &f.gt, &pixels).map_err(|e| EvalError::core(ctx(), e))?;
        let t = Instant::now();
        let (model, mut report) = method
            .fit(&samples)
            .map_err(|e| EvalError::core(ctx(), e))?;
        if report.fit_time_s.is_nan() || report.fit_time_s <= 0.0 {
            report.fit_time_s = t.elapsed().as_secs_f64();
        }
        Ok((model, report))
    }

    /// Applies a fitted model to frame `i` and scores it inside its evaluation region.
    ///
    /// # Errors
    /// Apply or metric errors, naming the frame.
    pub fn score(
        &self,
        model: &AlignmentModel,
        map: &NormalisedMap,
        i: usize,
    ) -> Result<(MetricDepth, DepthMetrics)> {
        let f = &self.set.frames[i];
        let ctx = || format!("set '{}', frame '{}'", self.set.name, f.id);
        let aligned = model
            .apply(map.values.view())
            .map_err(|e| EvalError::core(ctx(), e))?;
        let m = DepthMetrics::compute(&aligned, &f.gt, Some(&self.eval_masks[i]))
            .map_err(|e| EvalError::core(ctx(), e))?;
        Ok((aligned, m))
    }
}

/// The normalisation actually used by a method (RAW: none).
pub fn effective_norm(
    method: &str,
    norm: Normalisation,
    inverse_space: bool,
) -> NormalisationConfig {
    if method == "raw" {
        NormalisationConfig {
            method: Normalisation::None,
            inverse_space: false,
        }
    } else {
        NormalisationConfig {
            method: norm,
            inverse_space,
        }
    }
}

/// Evaluates one set: every (method, normalisation) over every seed.
///
/// # Errors
/// Bad input (see [`Prepared::new`]) or any failure of a step, naming the frame.
pub fn evaluate(
    set: &MomaSet,
    preds: &PredictionSet,
    config: &EvalConfig,
) -> Result<Vec<EvalResult>> {
    let prep = Prepared::new(set, preds, config)?;
    let mut jobs: Vec<(String, NormalisationConfig)> = Vec::new();
    for m in &config.methods {
        method_from_name(m, &set.intrinsics)?;
        for &n in &config.norms {
            let eff = effective_norm(m, n, config.inverse_space);
            if !jobs.iter().any(|(jm, jn)| jm == m && *jn == eff) {
                jobs.push((m.clone(), eff));
            }
        }
    }
    jobs.iter()
        .map(|(m, norm)| evaluate_one(&prep, m, norm, config.samples))
        .collect()
}

/// Evaluates one (method, normalisation) with `n` samples over all seeds.
///
/// # Errors
/// As [`evaluate`].
pub fn evaluate_one(
    prep: &Prepared<'_>,
    method_name: &str,
    norm: &NormalisationConfig,
    n: usize,
) -> Result<EvalResult> {
    let set = prep.set;
    let config = &prep.config;
    let method = method_from_name(method_name, &set.intrinsics)?;
    let maps: Vec<NormalisedMap> = (0..set.frames.len())
        .into_par_iter()
        .map(|i| prep.normalised(i, norm))
        .collect::<Result<_>>()?;
    let eval_idx = prep.eval_indices();
    let seeds: Vec<u64> = (0..config.seeds as u64)
        .map(|s| config.seed_base + s)
        .collect();
    let per_seed: Vec<(FitReport, Vec<DepthMetrics>)> = seeds
        .par_iter()
        .map(|&seed| -> Result<_> {
            let (model, report) = prep.calibrate(&method, &maps[prep.calib], n, seed)?;
            let ms = eval_idx
                .iter()
                .map(|&i| prep.score(&model, &maps[i], i).map(|(_, m)| m))
                .collect::<Result<Vec<_>>>()?;
            Ok((report, ms))
        })
        .collect::<Result<_>>()?;
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
        method: method_name.to_string(),
        norm: norm_name(norm.method).to_string(),
        samples: n,
        seeds: seeds.len(),
        calib_frame: prep.calib_id().to_string(),
        eval_frames: eval_idx.len(),
        per_image: MetricSummary::over_seeds(&image_means),
        pooled: MetricSummary::over_seeds(&pooled_),
        fit_time_median_s: median,
        fit_rms_residual_m: resid,
        frames,
    })
}

/// Aligned depth of every frame for one (method, normalisation, seed): used for figures and
/// exports. The calibration frame is aligned too.
///
/// # Errors
/// As [`evaluate`].
pub fn aligned_maps(
    prep: &Prepared<'_>,
    method_name: &str,
    norm: &NormalisationConfig,
    n: usize,
    seed: u64,
) -> Result<(AlignmentModel, FitReport, Vec<MetricDepth>)> {
    let method = method_from_name(method_name, &prep.set.intrinsics)?;
    let maps: Vec<NormalisedMap> = (0..prep.set.frames.len())
        .map(|i| prep.normalised(i, norm))
        .collect::<Result<_>>()?;
    let (model, report) = prep.calibrate(&method, &maps[prep.calib], n, seed)?;
    let aligned = maps
        .iter()
        .enumerate()
        .map(|(i, m)| {
            model.apply(m.values.view()).map_err(|e| {
                EvalError::core(
                    format!("set '{}', frame '{}'", prep.set.name, prep.set.frames[i].id),
                    e,
                )
            })
        })
        .collect::<Result<_>>()?;
    Ok((model, report, aligned))
}
