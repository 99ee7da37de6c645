//! Local correction on top of a global fit (`ssra-local`, `gssa-local`; docs/method.md §10) and
//! `auto`, the method chosen by cross-validation.
//!
//! The global model (SSRA or GSSA) gives `F(u, v, ẑ)` in the target space (metres in depth space,
//! 1/m in inverse space: the method works on whatever target the samples carry). At each node of a
//! coarse grid (LWLR's: every 32 px from 16 px) a scale/shift correction of `F` is fitted by
//! weighted least squares with Gaussian weights `w_k = exp(−d_k²/(2b²))` (`d_k` the pixel distance
//! node–sample, `b` the bandwidth in pixels) and a ridge pulling it towards the identity:
//!
//! `min_{δs,δt} Σ_k w_k (y_k − F_k − δs (F_k − c) − δt)² + λ (q δs² + δt²)`,
//!
//! with `c` the mean of `F_k` over the samples and `q` the mean of `(F_k − c)²` (so that both ridge
//! terms are in target units² per unit weight; `λ` is in units of weight, Σw ≤ n). The corrected
//! value is `s F + t` with `s = 1 + δs`, `t = δt − δs c`; `(s, t)` are stored at the grid nodes and
//! resized bilinearly to full size with LWLR's half-pixel-centre rule.
//!
//! `b` and `λ` are chosen by cross-validation on the calibration samples over
//! [`LocalConfig::bandwidth_fractions`] (× image diagonal, each raised to a floor) ×
//! [`LocalConfig::ridges`]. Three rules make the choice statistically sound rather than
//! optimistic (docs/evaluation.md: with plain leave-one-out and "lowest error wins", `ssra-local` was
//! worse than SSRA inside the objects of the shared sets on simulated predictions, because the
//! correction learnt structure of the calibration frame that other frames do not share):
//!
//! 1. **Spatially buffered cross-validation** ([`LocalConfig::cv_buffer_fraction`], default
//!    0.1 × diagonal): sample `k` is predicted by the models fitted without `k` *and without
//!    every sample within the buffer radius of it* (spatial leave-one-out with a buffer; Le Rest
//!    et al. 2014, Roberts et al. 2017). Residuals of a depth model are spatially correlated at
//!    the scale of scene content (objects, their blurred halo); plain leave-one-out then predicts a
//!    sample from neighbours that share its error and rewards corrections that copy that error.
//!    The buffer makes the score the error where no calibration sample is near — what a
//!    correction meets on a new frame.
//!    - global part: the normal equations minus the buffer's terms, solved (exact refits; with
//!      no neighbour in any buffer the closed-form hat-matrix LOO `y_k − r_k/(1 − h_kk)`; when
//!      some buffer leaves the global fit undetermined — samples clustered in a small region —
//!      plain leave-one-out is used for every model);
//!    - local part: the buffer's weights are dropped from the node sums of the (up to four) nodes
//!      around `k`, those 2×2 systems re-solved and interpolated, then applied to the global
//!      part's prediction. The remaining samples keep their full-fit `F` (an approximation: the
//!      global model has 2–4 parameters fitted on all n samples). As `λ → ∞` the local error
//!      tends to the global one exactly.
//! 2. **Bandwidth floor** ([`min_bandwidth_px`], [`LocalConfig::min_node_samples`] = 10): a
//!    candidate bandwidth is raised until a grid node sees on average 10 samples' worth of
//!    weight (five per local parameter) when the n samples cover the image uniformly,
//!    `n·2πb²/(W·H) ≥ 10` (35 px for 100 samples at 320×240, 70 px at 640×480, 121 px at
//!    1280×720); narrower kernels interpolate between one or two samples.
//! 3. **One-standard-error rule** ([`one_standard_error_choice`]) on the paired squared CV
//!    errors, models ordered from simplest to most complex: the global fit, then the candidates
//!    from the widest bandwidth and largest ridge to the narrowest and smallest. The kept model is
//!    the simplest whose mean error is within one standard error of the best's; in particular the
//!    correction is kept only when it beats the global fit by more than the noise of the
//!    comparison, else the model falls back to the global fit (`fallback: true`, no correction
//!    maps; `chosen` then records the candidate with the lowest CV error).
//!
//! `auto` scores gssa, ssra, gssa-local, ssra-local and lwlr ([`auto_candidates`], simplest
//! first) by the same buffered cross-validation (gssa, ssra: refits from the normal equations;
//! lwlr: exact refits; local variants: as above, the model each keeps) and applies the same
//! one-standard-error rule. The candidates' CV RMS are recorded.
//!
//! These three rules are [`LocalConfig::default`], the settings for a **fixed camera** (a
//! calibration applied to other frames). What the cross-validation scores and how much it must
//! win by are settings too ([`LocalConfig::cv_loss`]: squared error in target units, 1/m in
//! inverse space, as by default; squared error in metres; or relative error `|ẑ − z|/z`;
//! [`LocalConfig::cv_margin_se`]: the rule's margin in standard errors). For a calibration that
//! aligns **its own frame** (sparse-to-dense, a moving camera), [`crate::policy::local_config`]
//! gives plain leave-one-out, relative error and bandwidths down to ≈ 30 px: on real Depth
//! Anything 3 frames the buffered, metre-scored rules kept no correction where one lowers AbsRel
//! by 10–30 % below LWLR's, while on the simulated fixed-camera sets every such setting costs
//! 2–10 % MAE (docs/evaluation.md, "Real predictions"). The samples' [`SampleSet::space`] tells
//! the metre-based losses how to read the targets.

use ndarray::{Array2, ArrayView2, ArrayViewMut2};
use serde::{Deserialize, Serialize};

use super::grid::{
    self, MapCache, WeightTables, half_pixel_source, interpolate_nodes, resize_bilinear,
};
use super::gssa::{self, GssaModel};
use super::lwlr;
use super::ssra::{self, SsraConfig, SsraModel, solve_spd4};
use super::{AlignmentModel, Method, Sample, SampleSet};
use crate::error::{CoreError, Result};
use crate::image::ImageSize;
use crate::normalise::AlignSpace;

/// Fewest samples `gssa-local` needs (GSSA's 2, plus 2 so that leave-one-out is defined).
pub const GSSA_LOCAL_MIN_SAMPLES: usize = gssa::MIN_SAMPLES + 2;
/// Fewest samples `ssra-local` needs (SSRA's 4, plus 2 so that leave-one-out is defined).
pub const SSRA_LOCAL_MIN_SAMPLES: usize = ssra::MIN_SAMPLES + 2;
/// Fewest samples `auto` needs (GSSA with leave-one-out).
pub const AUTO_MIN_SAMPLES: usize = gssa::MIN_SAMPLES + 1;

/// A leverage `h_kk` closer than this to 1 makes leave-one-out undefined.
const LEVERAGE_MAX: f64 = 1.0 - 1e-9;

/// Which global model the correction sits on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LocalBase {
    /// Global scale and shift.
    Gssa,
    /// Scale-shift-rotation.
    Ssra,
}

/// Settings of the local correction. `Default`: b ∈ {0.05, 0.1, 0.2, 0.4} × image diagonal
/// (each raised to the floor of 10 samples per node), λ ∈ {0.1, 1, 10, 100}, grid every 32 px
/// from 16 px.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LocalConfig {
    /// Candidate bandwidths as fractions of the image diagonal (each > 0).
    pub bandwidth_fractions: Vec<f64>,
    /// Candidate ridges λ, units of weight (each > 0).
    pub ridges: Vec<f64>,
    /// Grid node spacing, pixels (≥ 1).
    pub grid_step_px: usize,
    /// Position of the first grid node, pixels.
    pub grid_offset_px: usize,
    /// Bandwidth floor: a candidate bandwidth is raised so that a grid node sees on average at
    /// least this many samples' worth of weight ([`min_bandwidth_px`]); 10 = five samples per
    /// local parameter (scale and shift). Must be ≥ 0.
    pub min_node_samples: f64,
    /// Spatial buffer of the cross-validation, as a fraction of the image diagonal: each
    /// sample is predicted without every sample within this radius of it (0: plain
    /// leave-one-out). Must be ≥ 0.
    pub cv_buffer_fraction: f64,
    /// What the cross-validation scores ([`CvLoss`]). Files written before it existed were
    /// fitted with [`CvLoss::Target`].
    #[serde(default = "legacy_cv_loss")]
    pub cv_loss: CvLoss,
    /// The selection rule: the simplest model whose mean CV loss is within this many standard
    /// errors (of the paired loss differences) of the best model's is kept ([`choose_within`]).
    /// 1 is the one-standard-error rule; 0 keeps the lowest CV loss. Must be ≥ 0. Files
    /// written before it existed were fitted with 1.
    #[serde(default = "legacy_cv_margin_se")]
    pub cv_margin_se: f64,
}

fn legacy_cv_loss() -> CvLoss {
    CvLoss::Target
}

fn legacy_cv_margin_se() -> f64 {
    1.0
}

/// What the cross-validation of the local corrections and of `auto` scores, per sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum CvLoss {
    /// Squared error in the fit's target units: metres in depth space, 1/m in inverse space
    /// (the least-squares objective itself; far samples dominate in depth space, near ones in
    /// inverse space).
    Target,
    /// Squared error in metres, after the reciprocal in inverse space.
    Abs,
    /// Absolute error relative to the true depth, `|ẑ − z| / z` (its mean is AbsRel).
    Rel,
}

impl CvLoss {
    /// Every loss name, in documentation order.
    pub const NAMES: [&'static str; 3] = ["target", "abs", "rel"];

    /// `target`, `abs` or `rel`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Target => "target",
            Self::Abs => "abs",
            Self::Rel => "rel",
        }
    }

    /// The loss of predicting `fitted` where the truth is `truth`, both in the target units of
    /// `space`. A fitted value without a depth (disparity ≤ 0 in inverse space) costs the whole
    /// depth: `z²` (abs) or 1 (rel).
    #[inline]
    pub fn of(self, space: AlignSpace, truth: f64, fitted: f64) -> f64 {
        match self {
            Self::Target => (truth - fitted).powi(2),
            Self::Abs | Self::Rel => {
                let z = space.depth_from_target(truth);
                let zf = space.depth_from_target(fitted);
                let err = if zf.is_finite() { (zf - z).abs() } else { z };
                match self {
                    Self::Abs => err * err,
                    _ => err / z,
                }
            }
        }
    }

    /// The summary of per-sample losses reported as "CV error": RMS for the squared losses
    /// (target units or metres), the mean for `rel` (AbsRel).
    pub fn summary(self, losses: &[f64]) -> f64 {
        match self {
            Self::Target | Self::Abs => mean_sqrt(losses),
            Self::Rel => losses.iter().sum::<f64>() / losses.len().max(1) as f64,
        }
    }
}

impl std::fmt::Display for CvLoss {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for CvLoss {
    type Err = CoreError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "target" => Ok(Self::Target),
            "abs" => Ok(Self::Abs),
            "rel" => Ok(Self::Rel),
            other => Err(CoreError::InvalidParameter(format!(
                "unknown cross-validation loss '{other}' (expected one of: {})",
                crate::names::join(Self::NAMES)
            ))),
        }
    }
}

/// A model's cross-validated error in metres and relative to depth, whatever loss chose it:
/// what a user can expect of it on pixels away from the calibration samples.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CvScore {
    /// RMS of the cross-validated errors, metres.
    pub rms_m: f64,
    /// Mean of `|ẑ − z| / z` over the samples (AbsRel).
    pub abs_rel: f64,
}

impl CvScore {
    /// The score of cross-validated predictions `cv` (target units) of `samples`.
    pub fn of(samples: &SampleSet, cv: &[f64]) -> Self {
        let sq: Vec<f64> = samples
            .samples
            .iter()
            .zip(cv)
            .map(|(p, &y)| CvLoss::Abs.of(samples.space, p.target, y))
            .collect();
        let rel: Vec<f64> = samples
            .samples
            .iter()
            .zip(cv)
            .map(|(p, &y)| CvLoss::Rel.of(samples.space, p.target, y))
            .collect();
        Self {
            rms_m: mean_sqrt(&sq),
            abs_rel: CvLoss::Rel.summary(&rel),
        }
    }

    fn is_valid(&self) -> bool {
        self.rms_m.is_finite()
            && self.rms_m >= 0.0
            && self.abs_rel.is_finite()
            && self.abs_rel >= 0.0
    }
}

/// Per-sample losses `loss` of the cross-validated predictions `cv` (target units).
fn losses_of(samples: &SampleSet, cv: &[f64], loss: CvLoss) -> Vec<f64> {
    samples
        .samples
        .iter()
        .zip(cv)
        .map(|(p, &y)| loss.of(samples.space, p.target, y))
        .collect()
}

impl Default for LocalConfig {
    fn default() -> Self {
        Self {
            bandwidth_fractions: vec![0.05, 0.1, 0.2, 0.4],
            ridges: vec![0.1, 1.0, 10.0, 100.0],
            grid_step_px: 32,
            grid_offset_px: 16,
            min_node_samples: 10.0,
            cv_buffer_fraction: 0.1,
            cv_loss: CvLoss::Target,
            cv_margin_se: 1.0,
        }
    }
}

impl LocalConfig {
    fn validate(&self) -> Result<()> {
        if self.bandwidth_fractions.is_empty() || self.ridges.is_empty() {
            return Err(CoreError::InvalidParameter(
                "local correction needs at least one candidate bandwidth and one ridge".into(),
            ));
        }
        for &f in &self.bandwidth_fractions {
            if !(f.is_finite() && f > 0.0) {
                return Err(CoreError::InvalidParameter(format!(
                    "local correction bandwidth fraction must be finite and > 0, got {f}"
                )));
            }
        }
        for &l in &self.ridges {
            if !(l.is_finite() && l > 0.0) {
                return Err(CoreError::InvalidParameter(format!(
                    "local correction ridge must be finite and > 0, got {l}"
                )));
            }
        }
        if self.grid_step_px == 0 {
            return Err(CoreError::InvalidParameter(
                "local correction grid step must be ≥ 1 px".into(),
            ));
        }
        if !(self.cv_buffer_fraction.is_finite() && self.cv_buffer_fraction >= 0.0) {
            return Err(CoreError::InvalidParameter(format!(
                "local correction cv_buffer_fraction must be finite and ≥ 0, got {}",
                self.cv_buffer_fraction
            )));
        }
        if !(self.cv_margin_se.is_finite() && self.cv_margin_se >= 0.0) {
            return Err(CoreError::InvalidParameter(format!(
                "cv_margin_se must be finite and ≥ 0 (standard errors), got {}",
                self.cv_margin_se
            )));
        }
        if !(self.min_node_samples.is_finite() && self.min_node_samples >= 0.0) {
            return Err(CoreError::InvalidParameter(format!(
                "local correction min_node_samples must be finite and ≥ 0, got {}",
                self.min_node_samples
            )));
        }
        Ok(())
    }

    /// Grid node positions (columns, rows), pixels: `offset + step·i` below the image size (at
    /// least one node per axis).
    pub fn grid_nodes(&self, size: ImageSize) -> (Vec<f64>, Vec<f64>) {
        grid::grid_nodes(self.grid_step_px, self.grid_offset_px, size)
    }
}

/// The global model under the correction.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "method", rename_all = "lowercase")]
pub enum GlobalFit {
    /// Global scale and shift.
    Gssa(GssaModel),
    /// Scale-shift-rotation.
    Ssra(SsraModel),
}

impl GlobalFit {
    /// The global model's value `F(u, v, ẑ)` (target units).
    #[inline]
    pub fn predict(&self, u: f64, v: f64, pred: f64) -> f64 {
        match self {
            Self::Gssa(m) => m.predict(pred),
            Self::Ssra(m) => m.predict(u, v, pred),
        }
    }

    /// `(g, T)` with `F = g(u, v)·ẑ + T`.
    #[inline]
    fn slope_offset(&self, u: f64, v: f64) -> (f64, f64) {
        match self {
            Self::Gssa(m) => (m.scale, m.shift),
            Self::Ssra(m) => (m.alpha_per_px * u + m.beta_per_px * v + m.gamma, m.t3),
        }
    }

    fn as_model(&self) -> AlignmentModel {
        match self {
            Self::Gssa(m) => AlignmentModel::Gssa(*m),
            Self::Ssra(m) => AlignmentModel::Ssra(*m),
        }
    }
}

/// One (bandwidth, ridge) candidate and its cross-validated RMS error.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocalCandidate {
    /// Bandwidth b, pixels.
    pub bandwidth_px: f64,
    /// Ridge λ, units of weight.
    pub ridge: f64,
    /// Cross-validated RMS error on the calibration samples (spatially buffered leave-one-out),
    /// in target units: metres in depth space, 1/m in inverse space (`loo_rms` in files before
    /// version 5); [`LocalCandidate::cv`] holds it in metres.
    #[serde(alias = "loo_rms")]
    pub loo_rms_target: f64,
    /// The same cross-validated errors in metres and relative to depth (absent in files
    /// written before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cv: Option<CvScore>,
}

/// Full-size folded maps: `z = scale ⊙ ẑ + shift`.
#[derive(Debug, Clone, PartialEq)]
struct LocalMaps {
    scale: Array2<f32>,
    shift: Array2<f32>,
}

/// Fitted local correction on a global model. Serialises the global fit, the candidates, the
/// chosen pair and the correction `(s, t)` at the grid nodes; full-size maps are computed on first
/// use and cached.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocalModel {
    /// Settings.
    pub config: LocalConfig,
    /// Calibration image size.
    pub image_size: ImageSize,
    /// The global fit.
    pub global: GlobalFit,
    /// Cross-validated RMS error of the global fit alone, target units (metres in depth space,
    /// 1/m in inverse space; `global_loo_rms` in files before version 5).
    #[serde(alias = "global_loo_rms")]
    pub global_loo_rms_target: f64,
    /// The global fit's cross-validated errors in metres and relative to depth (absent in
    /// files written before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub global_cv: Option<CvScore>,
    /// Every candidate in order (bandwidth-major, after the floor; duplicates dropped), with its
    /// cross-validated RMS error.
    pub candidates: Vec<LocalCandidate>,
    /// The candidate kept by the one-standard-error rule; on fallback the one with the lowest
    /// cross-validated error (first on ties).
    pub chosen: LocalCandidate,
    /// `true` when no candidate beat the global fit by more than one standard error: the model
    /// is the global fit.
    pub fallback: bool,
    /// Grid nodes per row.
    pub nodes_x: usize,
    /// Grid nodes per column.
    pub nodes_y: usize,
    /// Correction scale s at the nodes, row-major `nodes_y × nodes_x` (empty on fallback).
    pub node_scale: Vec<f64>,
    /// Correction shift t at the nodes, target units, row-major (empty on fallback).
    pub node_shift: Vec<f64>,
    #[serde(skip)]
    maps: MapCache<LocalMaps>,
}

/// Leave-one-out predictions `F₍₋ₖ₎(k)` of GSSA from the hat matrix.
fn gssa_loo(samples: &[Sample], m: &GssaModel) -> Result<Vec<f64>> {
    let n = samples.len() as f64;
    let mx = samples.iter().map(|s| s.pred).sum::<f64>() / n;
    let sxx: f64 = samples.iter().map(|s| (s.pred - mx).powi(2)).sum();
    samples
        .iter()
        .enumerate()
        .map(|(k, s)| {
            let h = 1.0 / n + (s.pred - mx).powi(2) / sxx;
            loo_value(k, s, m.predict(s.pred), h)
        })
        .collect()
}

/// Leave-one-out predictions of SSRA from the hat matrix of its (centred) features.
fn ssra_loo(samples: &[Sample], m: &SsraModel) -> Result<Vec<f64>> {
    let n = samples.len() as f64;
    let mu = samples.iter().map(|s| s.u).sum::<f64>() / n;
    let mv = samples.iter().map(|s| s.v).sum::<f64>() / n;
    let feat = |s: &Sample| [s.pred * (s.u - mu), s.pred * (s.v - mv), s.pred, 1.0];
    let mut a = [[0.0f64; 4]; 4];
    for s in samples {
        let x = feat(s);
        for i in 0..4 {
            for j in 0..4 {
                a[i][j] += x[i] * x[j];
            }
        }
    }
    samples
        .iter()
        .enumerate()
        .map(|(k, s)| {
            let x = feat(s);
            let y = solve_spd4(&a, &x).ok_or_else(|| {
                CoreError::Degenerate(
                    "SSRA normal matrix is singular; leave-one-out undefined".into(),
                )
            })?;
            let h: f64 = x.iter().zip(&y).map(|(p, q)| p * q).sum();
            loo_value(k, s, m.predict(s.u, s.v, s.pred), h)
        })
        .collect()
}

/// Features of the global model's linear least squares: GSSA `[ẑ, 1]`, SSRA
/// `[ẑ(u − ū), ẑ(v − v̄), ẑ, 1]` (padded with zeros to four).
fn global_features(samples: &[Sample], base: LocalBase) -> (Vec<[f64; 4]>, usize) {
    let n = samples.len().max(1) as f64;
    match base {
        LocalBase::Gssa => (samples.iter().map(|s| [s.pred, 1.0, 0.0, 0.0]).collect(), 2),
        LocalBase::Ssra => {
            let mu = samples.iter().map(|s| s.u).sum::<f64>() / n;
            let mv = samples.iter().map(|s| s.v).sum::<f64>() / n;
            (
                samples
                    .iter()
                    .map(|s| [s.pred * (s.u - mu), s.pred * (s.v - mv), s.pred, 1.0])
                    .collect(),
                4,
            )
        }
    }
}

/// Predictions at each sample `k` of the global model refitted without the samples of
/// `buffers[k]` (which holds `k`): normal equations summed over the remaining samples (directly,
/// not by subtraction, so that a large buffer cannot leave rounding residue that looks solvable)
/// and solved.
///
/// # Errors
/// [`CoreError::Degenerate`] when fewer samples than parameters + 1 remain or the refit is
/// singular.
fn buffered_global(
    samples: &[Sample],
    base: LocalBase,
    buffers: &[Vec<usize>],
) -> Result<Vec<f64>> {
    let (x, dim) = global_features(samples, base);
    let mut out = vec![false; samples.len()];
    (0..samples.len())
        .map(|k| {
            out.iter_mut().for_each(|o| *o = false);
            for &m in &buffers[k] {
                out[m] = true;
            }
            let undetermined = || {
                CoreError::Degenerate(format!(
                    "without the {} samples near sample {k} the global fit is undetermined; \
                     cross-validation is undefined",
                    buffers[k].len()
                ))
            };
            if samples.len() - buffers[k].len() < dim + 1 {
                return Err(undetermined());
            }
            let mut a = [[0.0f64; 4]; 4];
            let mut b = [0.0f64; 4];
            for ((xi, s), _) in x.iter().zip(samples).zip(&out).filter(|(_, o)| !**o) {
                for i in 0..4 {
                    b[i] += xi[i] * s.target;
                    for j in 0..4 {
                        a[i][j] += xi[i] * xi[j];
                    }
                }
            }
            for (i, row) in a.iter_mut().enumerate().skip(dim) {
                row[i] = 1.0;
            }
            let theta = solve_spd4(&a, &b).ok_or_else(undetermined)?;
            Ok(x[k].iter().zip(&theta).map(|(p, q)| p * q).sum())
        })
        .collect()
}

/// `F₍₋ₖ₎(k) = y − r/(1 − h)`.
fn loo_value(k: usize, s: &Sample, fitted: f64, h: f64) -> Result<f64> {
    if !(h.is_finite() && h < LEVERAGE_MAX) {
        return Err(CoreError::Degenerate(format!(
            "sample {k} alone determines the global fit (leverage {h:.6}); leave-one-out is undefined"
        )));
    }
    Ok(s.target - (s.target - fitted) / (1.0 - h))
}

/// `sqrt(mean(x))` of squared errors (0 for none): the RMS.
fn mean_sqrt(sq: &[f64]) -> f64 {
    if sq.is_empty() {
        0.0
    } else {
        (sq.iter().sum::<f64>() / sq.len() as f64).sqrt()
    }
}

/// Per-sample quantities of the correction.
struct Prep<'a> {
    samples: &'a [Sample],
    /// `F_k − c`.
    x: Vec<f64>,
    /// `y_k − F_k`.
    e: Vec<f64>,
    q: f64,
    cols: Vec<f64>,
    rows: Vec<f64>,
}

impl Prep<'_> {
    /// Node sums `[Σw, Σwx, Σwx², Σwe, Σwxe]` (row-major nodes) at bandwidth `b` (pixels) and
    /// the weight tables.
    fn node_sums(&self, b: f64) -> (Vec<[f64; 5]>, WeightTables) {
        let (nx, ny) = (self.cols.len(), self.rows.len());
        let tables = WeightTables::new(
            self.samples.iter().map(|s| (s.u, s.v)),
            &self.cols,
            &self.rows,
            1.0 / (2.0 * b * b),
        );
        let mut coef = vec![[0.0f64; 5]; self.samples.len()];
        let mut row: [Vec<f64>; 5] = std::array::from_fn(|_| vec![0.0f64; tables.stride]);
        let mut sums = vec![[0.0f64; 5]; nx * ny];
        let fill = |k: usize, w: f64| {
            let (x, e) = (self.x[k], self.e[k]);
            [w, w * x, w * x * x, w * e, w * x * e]
        };
        for i in 0..ny {
            tables.row_sums(i, fill, &mut coef, &mut row);
            for (j, acc) in sums[i * nx..(i + 1) * nx].iter_mut().enumerate() {
                *acc = [row[0][j], row[1][j], row[2][j], row[3][j], row[4][j]];
            }
        }
        (sums, tables)
    }

    /// Solves one node's ridge system; returns `(δs, δt)`.
    #[inline]
    fn solve(&self, s: &[f64; 5], ridge: f64) -> (f64, f64) {
        let [w, wx, wxx, we, wxe] = *s;
        let (a, bb, d) = (wxx + ridge * self.q, wx, w + ridge);
        let det = a * d - bb * bb;
        if !(det.is_finite() && det > 0.0) {
            return (0.0, 0.0);
        }
        ((d * wxe - bb * we) / det, (a * we - bb * wxe) / det)
    }
}

/// The one-standard-error rule on paired cross-validation losses (Breiman et al. 1984; Hastie,
/// Tibshirani & Friedman, *Elements of Statistical Learning* §7.10): `losses[i][k]` is model
/// `i`'s squared cross-validation error on sample `k`, models ordered from simplest to most complex. Returns
/// the index of the simplest model whose mean loss is not worse than the best model's by more
/// than one standard error of the paired differences `losses[i][k] − losses[best][k]`.
///
/// Pairing makes the comparison sensitive to consistent gains and blind to gains that a few
/// samples produce (CV RMS differences of a few percent are often within noise on 100 samples). A
/// more complex model is therefore kept only when it beats every simpler one by more than the
/// noise of the comparison. Non-finite mean losses are never chosen; `None` when none is finite.
pub fn one_standard_error_choice(losses: &[&[f64]]) -> Option<usize> {
    choose_within(losses, 1.0)
}

/// [`one_standard_error_choice`] with a margin of `margin_se` standard errors instead of one
/// (0: the lowest mean loss, first on ties).
pub fn choose_within(losses: &[&[f64]], margin_se: f64) -> Option<usize> {
    let (best, excess) = excess_over_best(losses)?;
    (0..=best).find(|&i| excess[i].is_some_and(|x| x <= margin_se))
}

/// For paired losses (as [`one_standard_error_choice`]): the index of the lowest finite mean
/// (first on ties) and, for each model, by how many standard errors of the paired differences
/// its mean loss exceeds the best's (`Some(0)` for the best, `Some(∞)` for a worse model with
/// identical differences, `None` for a non-finite mean or another sample count).
pub fn excess_over_best(losses: &[&[f64]]) -> Option<(usize, Vec<Option<f64>>)> {
    let mean = |l: &[f64]| l.iter().sum::<f64>() / l.len().max(1) as f64;
    let means: Vec<f64> = losses.iter().map(|l| mean(l)).collect();
    let best = (0..losses.len())
        .filter(|&i| means[i].is_finite())
        .min_by(|&a, &b| means[a].total_cmp(&means[b]).then(a.cmp(&b)))?;
    let excess = (0..losses.len())
        .map(|i| {
            if !means[i].is_finite() || losses[i].len() != losses[best].len() {
                return None;
            }
            if i == best {
                return Some(0.0);
            }
            let n = losses[i].len() as f64;
            let d: Vec<f64> = losses[i]
                .iter()
                .zip(losses[best])
                .map(|(a, b)| a - b)
                .collect();
            let md = mean(&d);
            let var = d.iter().map(|x| (x - md).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
            let se = (var / n).sqrt();
            Some(if md <= 0.0 {
                0.0
            } else if se > 0.0 {
                md / se
            } else {
                f64::INFINITY
            })
        })
        .collect();
    Some((best, excess))
}

/// The image diagonal, pixels.
fn diagonal_px(size: ImageSize) -> f64 {
    ((size.width * size.width + size.height * size.height) as f64).sqrt()
}

/// For each sample `k`, the samples left out when predicting it: `k` and every sample within
/// `radius_px` of it (pixels; 0: `k` alone, plain leave-one-out, also when another sample sits
/// on the same pixel).
fn cv_buffers(samples: &[Sample], radius_px: f64) -> Vec<Vec<usize>> {
    let r2 = radius_px * radius_px;
    (0..samples.len())
        .map(|k| {
            let p = &samples[k];
            (0..samples.len())
                .filter(|&i| {
                    i == k
                        || (radius_px > 0.0
                            && (samples[i].u - p.u).powi(2) + (samples[i].v - p.v).powi(2) <= r2)
                })
                .collect()
        })
        .collect()
}

/// The cross-validation buffers of `config` for `samples` ([`cv_buffers`] at
/// `cv_buffer_fraction` × the diagonal), or plain leave-one-out when leaving some sample's
/// buffer out would leave the global fit undetermined (samples clustered in a small region):
/// SSRA's (GSSA's below 5 samples) refit is tried for every buffer.
fn cv_plan(samples: &SampleSet, config: &LocalConfig) -> Vec<Vec<usize>> {
    let s = &samples.samples;
    let buffers = cv_buffers(
        s,
        config.cv_buffer_fraction * diagonal_px(samples.image_size),
    );
    if buffers.iter().all(|b| b.len() == 1) {
        return buffers;
    }
    let base = if s.len() > ssra::MIN_SAMPLES {
        LocalBase::Ssra
    } else {
        LocalBase::Gssa
    };
    if buffered_global(s, base, &buffers).is_ok() {
        buffers
    } else {
        cv_buffers(s, 0.0)
    }
}

/// The smallest bandwidth (pixels) at which a grid node sees, on average, `min_node_samples`
/// samples' worth of Gaussian weight when `n` samples are spread uniformly over `size`:
/// `n · 2πb² / (W·H) = min_node_samples`.
pub fn min_bandwidth_px(n: usize, size: ImageSize, min_node_samples: f64) -> f64 {
    (min_node_samples * size.pixels() as f64 / (2.0 * std::f64::consts::PI * n.max(1) as f64))
        .sqrt()
}

/// Fits the global model and the cross-validated local correction.
///
/// Candidates: every bandwidth `f × diagonal` of [`LocalConfig::bandwidth_fractions`], raised to
/// [`min_bandwidth_px`] (duplicates dropped), × every ridge. Selection
/// ([`one_standard_error_choice`]) over the global fit (simplest), then the candidates from the
/// widest bandwidth and largest ridge to the narrowest and smallest: the model falls back to the
/// global fit unless a correction beats it by more than one standard error.
///
/// # Errors
/// Too few samples (gssa-local < 4, ssra-local < 6); the global fit's errors
/// ([`CoreError::Degenerate`] ...); a sample with leverage 1; bad settings.
pub fn fit(samples: &SampleSet, base: LocalBase, config: &LocalConfig) -> Result<LocalModel> {
    Ok(fit_with_loo(samples, base, config)?.0)
}

/// [`fit`], also returning the leave-one-out predictions of the model as kept (the global
/// fit's on fallback), target units.
fn fit_with_loo(
    samples: &SampleSet,
    base: LocalBase,
    config: &LocalConfig,
) -> Result<(LocalModel, Vec<f64>)> {
    config.validate()?;
    let size = samples.image_size;
    if size.pixels() == 0 {
        return Err(CoreError::InvalidParameter(format!(
            "local correction image size {size} is empty"
        )));
    }
    let s = &samples.samples;
    let diag = diagonal_px(size);
    let buffers = cv_plan(samples, config);
    let buffered = buffers.iter().any(|b| b.len() > 1);
    let (global, mut f_loo) = match base {
        LocalBase::Gssa => {
            let m = gssa::fit(s)?;
            (GlobalFit::Gssa(m), gssa_loo(s, &m)?)
        }
        LocalBase::Ssra => {
            let m = ssra::fit(samples, &SsraConfig::default())?;
            (GlobalFit::Ssra(m), ssra_loo(s, &m)?)
        }
    };
    if buffered {
        f_loo = buffered_global(s, base, &buffers)?;
    }
    let global_loo_rms_target = mean_sqrt(&losses_of(samples, &f_loo, CvLoss::Target));
    let global_loss = losses_of(samples, &f_loo, config.cv_loss);
    let global_cv = CvScore::of(samples, &f_loo);
    let n = s.len() as f64;
    let f: Vec<f64> = s.iter().map(|p| global.predict(p.u, p.v, p.pred)).collect();
    let c = f.iter().sum::<f64>() / n;
    let x: Vec<f64> = f.iter().map(|v| v - c).collect();
    let q = (x.iter().map(|v| v * v).sum::<f64>() / n).max(f64::MIN_POSITIVE);
    let (cols, rows) = config.grid_nodes(size);
    let prep = Prep {
        samples: s,
        e: s.iter().zip(&f).map(|(p, fk)| p.target - fk).collect(),
        x,
        q,
        cols,
        rows,
    };
    let (nx, ny) = (prep.cols.len(), prep.rows.len());
    let (w, h) = (size.width, size.height);
    let own: Vec<[f64; 5]> = prep
        .x
        .iter()
        .zip(&prep.e)
        .map(|(&x, &e)| [1.0, x, x * x, e, x * e])
        .collect();
    let b_min = min_bandwidth_px(s.len(), size, config.min_node_samples);
    let mut bandwidths: Vec<f64> = Vec::new();
    for &frac in &config.bandwidth_fractions {
        let b = (frac * diag).max(b_min);
        if !bandwidths.contains(&b) {
            bandwidths.push(b);
        }
    }
    // bilinear neighbours of each sample's pixel
    let neighbours: Vec<[(usize, usize, f64); 2]> = s
        .iter()
        .map(|p| {
            let (u, v) = nearest_pixel(p.u, p.v, size);
            [half_pixel_source(u, nx, w), half_pixel_source(v, ny, h)]
        })
        .collect();

    let mut candidates = Vec::new();
    // per-sample CV losses of each candidate ([`LocalConfig::cv_loss`])
    let mut cand_sq: Vec<Vec<f64>> = Vec::new();
    let mut cand_pred: Vec<Vec<f64>> = Vec::new();
    for &b in &bandwidths {
        let (sums, tables) = prep.node_sums(b);
        for &ridge in &config.ridges {
            let loo: Vec<f64> = (0..s.len())
                .map(|k| {
                    let [(x0, x1, fx), (y0, y1, fy)] = neighbours[k];
                    let at = |i: usize, j: usize| {
                        let mut sm = sums[i * nx + j];
                        for &m in &buffers[k] {
                            let wm = tables.weight(m, i, j);
                            for (t, o) in sm.iter_mut().zip(&own[m]) {
                                *t -= wm * o;
                            }
                        }
                        prep.solve(&sm, ridge)
                    };
                    let (a00, a01, a10, a11) = (at(y0, x0), at(y0, x1), at(y1, x0), at(y1, x1));
                    let bil = |p00: f64, p01: f64, p10: f64, p11: f64| {
                        (p00 * (1.0 - fx) + p01 * fx) * (1.0 - fy)
                            + (p10 * (1.0 - fx) + p11 * fx) * fy
                    };
                    let ds = bil(a00.0, a01.0, a10.0, a11.0);
                    let dt = bil(a00.1, a01.1, a10.1, a11.1);
                    let fl = f_loo[k];
                    fl + ds * (fl - c) + dt
                })
                .collect();
            candidates.push(LocalCandidate {
                bandwidth_px: b,
                ridge,
                loo_rms_target: mean_sqrt(&losses_of(samples, &loo, CvLoss::Target)),
                cv: Some(CvScore::of(samples, &loo)),
            });
            cand_sq.push(losses_of(samples, &loo, config.cv_loss));
            cand_pred.push(loo);
        }
    }
    if let Some(bad) = candidates.iter().find(|c| !c.loo_rms_target.is_finite()) {
        return Err(CoreError::Degenerate(format!(
            "local correction leave-one-out error is {} (bandwidth {:.1} px, ridge {}) on these {} samples",
            bad.loo_rms_target,
            bad.bandwidth_px,
            bad.ridge,
            s.len()
        )));
    }
    // simplest first: the global fit, then widest bandwidth / largest ridge first
    let mut order: Vec<usize> = (0..candidates.len()).collect();
    order.sort_by(|&a, &b| {
        let (ca, cb) = (&candidates[a], &candidates[b]);
        cb.bandwidth_px
            .total_cmp(&ca.bandwidth_px)
            .then(cb.ridge.total_cmp(&ca.ridge))
            .then(a.cmp(&b))
    });
    let mut losses: Vec<&[f64]> = vec![&global_loss];
    losses.extend(order.iter().map(|&i| cand_sq[i].as_slice()));
    let pick = choose_within(&losses, config.cv_margin_se).unwrap_or(0);
    let fallback = pick == 0;
    // the chosen candidate: the one kept, or on fallback the best by CV loss (for the report)
    let ci = if fallback {
        let mean = |l: &[f64]| l.iter().sum::<f64>() / l.len().max(1) as f64;
        (0..candidates.len())
            .min_by(|&a, &b| mean(&cand_sq[a]).total_cmp(&mean(&cand_sq[b])))
            .unwrap_or(0)
    } else {
        order[pick - 1]
    };
    let chosen = *candidates
        .get(ci)
        .ok_or_else(|| CoreError::InvalidParameter("local correction has no candidate".into()))?;
    let (mut node_scale, mut node_shift) = (Vec::new(), Vec::new());
    let loo = if fallback {
        f_loo
    } else {
        let b = chosen.bandwidth_px;
        let (sums, _) = prep.node_sums(b);
        for sm in &sums {
            let (ds, dt) = prep.solve(sm, chosen.ridge);
            node_scale.push(1.0 + ds);
            node_shift.push(dt - ds * c);
        }
        std::mem::take(&mut cand_pred[ci])
    };
    let model = LocalModel {
        config: config.clone(),
        image_size: size,
        global,
        global_loo_rms_target,
        global_cv: Some(global_cv),
        candidates,
        chosen,
        fallback,
        nodes_x: nx,
        nodes_y: ny,
        node_scale,
        node_shift,
        maps: MapCache::default(),
    };
    Ok((model, loo))
}

fn nearest_pixel(u: f64, v: f64, size: ImageSize) -> (f64, f64) {
    let cl = |x: f64, len: usize| (x.round().max(0.0)).min(len.saturating_sub(1) as f64);
    (cl(u, size.width), cl(v, size.height))
}

impl LocalModel {
    /// `ssra-local` or `gssa-local`.
    pub fn name(&self) -> &'static str {
        self.method_name().as_str()
    }

    /// [`MethodName::SsraLocal`](super::MethodName::SsraLocal) or
    /// [`MethodName::GssaLocal`](super::MethodName::GssaLocal).
    pub fn method_name(&self) -> super::MethodName {
        match self.global {
            GlobalFit::Gssa(_) => super::MethodName::GssaLocal,
            GlobalFit::Ssra(_) => super::MethodName::SsraLocal,
        }
    }

    /// The cross-validated RMS error of the model as used, in target units: the global one on
    /// fallback, else the chosen candidate's.
    pub fn loo_rms_target(&self) -> f64 {
        if self.fallback {
            self.global_loo_rms_target
        } else {
            self.chosen.loo_rms_target
        }
    }

    /// The fitted value at the pixel nearest to `(u, v)` (clamped) for ẑ = `pred`, in f64:
    /// `s·F + t` with `(s, t)` interpolated from the nodes as the full-size maps are (equal to
    /// [`LocalModel`]'s apply up to f32 rounding); the global value on fallback.
    pub fn predict_at(&self, u: f64, v: f64, pred: f64) -> f64 {
        let (u, v) = nearest_pixel(u, v, self.image_size);
        let fv = self.global.predict(u, v, pred);
        if self.fallback {
            return fv;
        }
        let (nx, ny, size) = (self.nodes_x, self.nodes_y, self.image_size);
        interpolate_nodes(&self.node_scale, nx, ny, size, u, v) * fv
            + interpolate_nodes(&self.node_shift, nx, ny, size, u, v)
    }

    fn maps(&self) -> &LocalMaps {
        self.maps.get_or_init(|| {
            let (w, h) = (self.image_size.width, self.image_size.height);
            let s = resize_bilinear(&self.node_scale, self.nodes_x, self.nodes_y, w, h);
            let t = resize_bilinear(&self.node_shift, self.nodes_x, self.nodes_y, w, h);
            let mut scale = Array2::<f32>::zeros((h, w));
            let mut shift = Array2::<f32>::zeros((h, w));
            for ((v, u), o) in scale.indexed_iter_mut() {
                let (g, t0) = self.global.slope_offset(u as f64, v as f64);
                let sv = f64::from(s[[v, u]]);
                *o = (sv * g) as f32;
                shift[[v, u]] = (sv * t0 + f64::from(t[[v, u]])) as f32;
            }
            LocalMaps { scale, shift }
        })
    }

    /// `out = S ⊙ ẑ + T` (or the global fit on fallback); shapes checked by the caller.
    pub(crate) fn apply_into(
        &self,
        normalised: ArrayView2<'_, f32>,
        out: &mut ArrayViewMut2<'_, f32>,
    ) {
        if self.fallback {
            match &self.global {
                GlobalFit::Gssa(m) => {
                    let (s, t) = (m.scale as f32, m.shift as f32);
                    crate::kernels::map_rows(normalised, out, |_, zin, zout| {
                        crate::kernels::affine(zin, zout, s, t)
                    });
                }
                GlobalFit::Ssra(m) => m.apply_into(normalised, out),
            }
            return;
        }
        let m = self.maps();
        let w = self.image_size.width;
        let (s_all, t_all) = match (m.scale.as_slice(), m.shift.as_slice()) {
            (Some(s), Some(t)) => (s, t),
            _ => return, // maps are built in standard layout
        };
        crate::kernels::map_rows(normalised, out, |v, zin, zout| {
            let (s, t) = (&s_all[v * w..(v + 1) * w], &t_all[v * w..(v + 1) * w]);
            crate::kernels::affine_maps(zin, zout, s, t);
        });
    }

    /// Checks a model read from a file: settings, finite global fit and LOO errors, bandwidth
    /// and ridge > 0, node counts matching the grid, node maps finite (empty on fallback).
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] naming the bad field.
    pub fn validate(&self) -> Result<()> {
        let bad = |msg: String| {
            Err(CoreError::InvalidParameter(format!(
                "{}: {msg}",
                self.name()
            )))
        };
        self.config.validate()?;
        if !self.image_size.is_within_limits() {
            return bad(format!(
                "image size {} is empty or too large",
                self.image_size
            ));
        }
        if let GlobalFit::Ssra(m) = &self.global
            && m.image_size != self.image_size
        {
            return bad("global SSRA fit is for another image size".into());
        }
        self.global.as_model().validate()?;
        if !self.global_loo_rms_target.is_finite() {
            return bad(format!(
                "global_loo_rms_target is {}",
                self.global_loo_rms_target
            ));
        }
        if self.global_cv.is_some_and(|cv| !cv.is_valid()) {
            return bad("global_cv is invalid".into());
        }
        for c in self.candidates.iter().chain([&self.chosen]) {
            if !(c.bandwidth_px.is_finite() && c.bandwidth_px > 0.0) {
                return bad(format!(
                    "bandwidth_px {} must be finite and > 0",
                    c.bandwidth_px
                ));
            }
            if !(c.ridge.is_finite() && c.ridge > 0.0) {
                return bad(format!("ridge {} must be finite and > 0", c.ridge));
            }
            if !c.loo_rms_target.is_finite() {
                return bad(format!("loo_rms_target {} is not finite", c.loo_rms_target));
            }
            if c.cv.is_some_and(|cv| !cv.is_valid()) {
                return bad("a candidate's cross-validation score is invalid".into());
            }
        }
        let (cols, rows) = self.config.grid_nodes(self.image_size);
        if (cols.len(), rows.len()) != (self.nodes_x, self.nodes_y) {
            return bad(format!(
                "{}×{} nodes stored but the grid has {}×{}",
                self.nodes_x,
                self.nodes_y,
                cols.len(),
                rows.len()
            ));
        }
        let want = if self.fallback {
            0
        } else {
            self.nodes_x * self.nodes_y
        };
        if self.node_scale.len() != want || self.node_shift.len() != want {
            return bad(format!(
                "node maps have {} and {} values, expected {want}",
                self.node_scale.len(),
                self.node_shift.len()
            ));
        }
        if let Some(x) = self
            .node_scale
            .iter()
            .chain(&self.node_shift)
            .find(|x| !x.is_finite())
        {
            return bad(format!("node map value {x} is not finite"));
        }
        Ok(())
    }
}

/// One method `auto` considered.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AutoCandidate {
    /// The method.
    pub method: super::MethodName,
    /// Cross-validated RMS error on the calibration samples in target units (metres in depth
    /// space, 1/m in inverse space; `loo_rms` in files before version 5); `None` when the method
    /// could not be fitted on these samples.
    #[serde(alias = "loo_rms")]
    pub loo_rms_target: Option<f64>,
    /// The same cross-validated errors in metres and relative to depth (absent when the method
    /// could not be fitted, and in files written before it existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cv: Option<CvScore>,
    /// The selection loss's mean (RMS for the squared losses, mean for `rel`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cv_error: Option<f64>,
    /// By how many standard errors of the paired loss differences the mean loss exceeds the best
    /// candidate's (0 for the best; [`excess_over_best`]). The kept method is the first whose
    /// excess is within [`AutoSelection::margin_se`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub excess_se: Option<f64>,
}

/// How `auto` chose: the loss, the rule and the candidate with the lowest loss.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AutoSelection {
    /// The cross-validation loss.
    pub loss: CvLoss,
    /// The margin of the rule, standard errors (1: the one-standard-error rule; 0: lowest
    /// loss).
    pub margin_se: f64,
    /// Radius of the cross-validation's spatial buffer, pixels (0: plain leave-one-out).
    pub buffer_px: f64,
    /// The candidate with the lowest mean loss.
    pub best: super::MethodName,
}

/// `auto`'s result: the chosen fitted model and every candidate's cross-validated RMS error.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AutoModel {
    /// The chosen method fitted on all samples.
    pub chosen: Box<AlignmentModel>,
    /// Every candidate in the order tried, simplest first ([`auto_candidates`]).
    pub candidates: Vec<AutoCandidate>,
    /// How the choice was made (absent in files written before it was recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub selection: Option<AutoSelection>,
}

impl AutoModel {
    /// Checks the chosen model (not itself `auto`) and the candidates' LOO values.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] naming the bad value.
    pub fn validate(&self) -> Result<()> {
        if matches!(*self.chosen, AlignmentModel::Auto(_) | AlignmentModel::Raw) {
            return Err(CoreError::InvalidParameter(format!(
                "auto: chosen model cannot be '{}'",
                self.chosen.name()
            )));
        }
        self.chosen.validate()?;
        for c in &self.candidates {
            if let Some(x) = c.loo_rms_target
                && !(x.is_finite() && x >= 0.0)
            {
                return Err(CoreError::InvalidParameter(format!(
                    "auto: candidate {} has leave-one-out RMS {x}",
                    c.method
                )));
            }
            if c.cv.is_some_and(|cv| !cv.is_valid())
                || c.cv_error.is_some_and(|x| !(x.is_finite() && x >= 0.0))
                || c.excess_se.is_some_and(|x| x.is_nan() || x < 0.0)
            {
                return Err(CoreError::InvalidParameter(format!(
                    "auto: candidate {} has an invalid cross-validation score",
                    c.method
                )));
            }
        }
        if let Some(sel) = &self.selection
            && !(sel.margin_se.is_finite()
                && sel.margin_se >= 0.0
                && sel.buffer_px.is_finite()
                && sel.buffer_px >= 0.0)
        {
            return Err(CoreError::InvalidParameter(format!(
                "auto: selection margin {} or buffer {} px is invalid",
                sel.margin_se, sel.buffer_px
            )));
        }
        if !self
            .candidates
            .iter()
            .any(|c| c.method == self.chosen.name())
        {
            return Err(CoreError::InvalidParameter(format!(
                "auto: chosen method '{}' is not among the candidates",
                self.chosen.name()
            )));
        }
        Ok(())
    }
}

/// Cross-validated predictions of LWLR by exact refits without each sample's buffer.
fn lwlr_loo(
    samples: &SampleSet,
    cfg: &lwlr::LwlrConfig,
    buffers: &[Vec<usize>],
) -> Result<Vec<f64>> {
    let s = &samples.samples;
    let mut loo = Vec::with_capacity(s.len());
    let mut rest = SampleSet {
        space: samples.space,
        image_size: samples.image_size,
        samples: Vec::with_capacity(s.len()),
    };
    for (k, p) in s.iter().enumerate() {
        rest.samples.clear();
        rest.samples.extend(
            s.iter()
                .enumerate()
                .filter(|(i, _)| !buffers[k].contains(i))
                .map(|(_, q)| *q),
        );
        let m = lwlr::fit_unmapped(&rest, cfg)?;
        loo.push(m.predict(p.u, p.v, p.pred));
    }
    Ok(loo)
}

/// The methods `auto` considers, with their default settings, simplest first: the order in
/// which the selection rule prefers them (gssa, ssra, gssa-local, ssra-local, lwlr).
pub fn auto_candidates() -> [Method; 5] {
    auto_candidates_with(&LocalConfig::default())
}

/// [`auto_candidates`] with the local variants set to `config`.
pub fn auto_candidates_with(config: &LocalConfig) -> [Method; 5] {
    [
        Method::Gssa,
        Method::Ssra(SsraConfig::default()),
        Method::GssaLocal(config.clone()),
        Method::SsraLocal(config.clone()),
        Method::Lwlr(lwlr::LwlrConfig::faithful()),
    ]
}

/// Fits `method` (with its settings) on `samples` with its cross-validated predictions (target
/// units), the folds of `auto`'s plan ([`cv_plan`] with `plan`'s buffer).
fn fit_candidate(
    samples: &SampleSet,
    method: &Method,
    plan: &LocalConfig,
) -> Result<(Vec<f64>, AlignmentModel)> {
    let s = &samples.samples;
    let buffers = cv_plan(samples, plan);
    let buffered = buffers.iter().any(|b| b.len() > 1);
    match method {
        Method::Gssa => {
            let m = gssa::fit(s)?;
            let loo = if buffered {
                buffered_global(s, LocalBase::Gssa, &buffers)?
            } else {
                gssa_loo(s, &m)?
            };
            Ok((loo, AlignmentModel::Gssa(m)))
        }
        Method::Ssra(cfg) => {
            if s.len() < ssra::MIN_SAMPLES + 1 {
                return Err(too_few("ssra", s.len(), ssra::MIN_SAMPLES + 1));
            }
            let m = ssra::fit(samples, cfg)?;
            let loo = if buffered {
                buffered_global(s, LocalBase::Ssra, &buffers)?
            } else {
                ssra_loo(s, &m)?
            };
            Ok((loo, AlignmentModel::Ssra(m)))
        }
        Method::GssaLocal(cfg) | Method::SsraLocal(cfg) => {
            let (name, base, need) = if matches!(method, Method::GssaLocal(_)) {
                ("gssa-local", LocalBase::Gssa, GSSA_LOCAL_MIN_SAMPLES)
            } else {
                ("ssra-local", LocalBase::Ssra, SSRA_LOCAL_MIN_SAMPLES)
            };
            if s.len() < need {
                return Err(too_few(name, s.len(), need));
            }
            let (m, loo) = fit_with_loo(samples, base, cfg)?;
            Ok((loo, AlignmentModel::Local(Box::new(m))))
        }
        Method::Lwlr(cfg) => {
            let loo = lwlr_loo(samples, cfg, &buffers)?;
            Ok((loo, AlignmentModel::Lwlr(lwlr::fit(samples, cfg)?)))
        }
        other => Err(CoreError::InvalidParameter(format!(
            "auto: '{other}' is not a candidate method (expected one of: {})",
            auto_candidates().map(|m| m.name()).join(", ")
        ))),
    }
}

/// Cross-validated predictions (target units) of `method` — one of [`auto_candidates`], with
/// its settings — on `samples`, as `auto` computes them (spatially buffered leave-one-out,
/// see the module docs): refits from the normal equations for gssa and ssra, exact refits for
/// lwlr, and for the local variants those of the model kept by their own selection (the global
/// fit's on fallback).
///
/// # Errors
/// An unknown method; the method's fitting errors.
pub fn loo_predictions(samples: &SampleSet, method: &Method) -> Result<Vec<f64>> {
    samples.validate()?;
    let plan = match method {
        Method::GssaLocal(c) | Method::SsraLocal(c) | Method::Auto(c) => c.clone(),
        _ => LocalConfig::default(),
    };
    Ok(fit_candidate(samples, method, &plan)?.0)
}

/// The cross-validated error of `method` on `samples` with the folds and buffer of `plan`
/// (its other settings are ignored; the local variants and `auto` use their own settings):
/// what [`crate::pipeline::Calibration::predicted_error`] reports.
///
/// # Errors
/// An unknown method (RAW has no fit to cross-validate); the method's fitting errors.
pub fn cv_score(samples: &SampleSet, method: &Method, plan: &LocalConfig) -> Result<CvScore> {
    samples.validate()?;
    if let Method::Auto(cfg) = method {
        let m = fit_auto(samples, cfg)?;
        return m.chosen_cv().ok_or_else(|| {
            CoreError::Degenerate("auto: the chosen method has no cross-validation score".into())
        });
    }
    Ok(CvScore::of(
        samples,
        &fit_candidate(samples, method, plan)?.0,
    ))
}

impl AutoModel {
    /// The cross-validation score of the chosen method (`None` in files written before it was
    /// recorded).
    pub fn chosen_cv(&self) -> Option<CvScore> {
        self.candidates
            .iter()
            .find(|c| c.method == self.chosen.name())
            .and_then(|c| c.cv)
    }

    /// One line per candidate saying why `auto` kept what it kept: the loss, the rule, each
    /// candidate's CV error and excess over the best in standard errors (empty for files
    /// written before the selection was recorded).
    pub fn explain(&self) -> Vec<String> {
        let Some(sel) = &self.selection else {
            return Vec::new();
        };
        let cv = if sel.buffer_px > 0.0 {
            format!(
                "leave-one-out without the samples within {:.0} px",
                sel.buffer_px
            )
        } else {
            "plain leave-one-out".to_string()
        };
        let mut lines = vec![format!(
            "auto kept {}: the simplest candidate (in this order) whose mean {} loss is within \
             {} standard error(s) of the best's ({}); {cv}",
            self.chosen.name(),
            sel.loss,
            sel.margin_se,
            sel.best
        )];
        for c in &self.candidates {
            lines.push(match (c.cv, c.cv_error, c.excess_se) {
                (Some(cv), Some(err), Some(x)) => format!(
                    "  {:<11} CV {} {err:.4}  (AbsRel {:.4}, RMS {:.1} mm)  +{x:.2} SE{}",
                    c.method,
                    sel.loss,
                    cv.abs_rel,
                    cv.rms_m * 1e3,
                    if c.method == self.chosen.name() {
                        "  <- kept"
                    } else {
                        ""
                    }
                ),
                _ => format!("  {:<11} could not be fitted on these samples", c.method),
            });
        }
        lines
    }
}

impl LocalModel {
    /// The cross-validation score of the model as used (the global fit's on fallback; `None`
    /// in files written before it was recorded).
    pub fn cv(&self) -> Option<CvScore> {
        if self.fallback {
            self.global_cv
        } else {
            self.chosen.cv
        }
    }
}

/// Fits `auto` with `config`: every method of [`auto_candidates_with`] (the local variants with
/// `config`) with its cross-validated errors on the calibration samples (spatially buffered by
/// `config.cv_buffer_fraction`, scored by `config.cv_loss`); kept is the simplest method
/// within `config.cv_margin_se` standard errors of the best ([`choose_within`] on the paired
/// per-sample losses).
///
/// # Errors
/// [`CoreError::TooFewSamples`] below 3 samples; [`CoreError::Degenerate`] when no candidate
/// could be fitted (the first candidate's error is returned); bad settings.
pub fn fit_auto(samples: &SampleSet, config: &LocalConfig) -> Result<AutoModel> {
    config.validate()?;
    let mut candidates = Vec::new();
    let mut fitted: Vec<(Vec<f64>, AlignmentModel, usize)> = Vec::new();
    let mut first_err = None;
    for method in auto_candidates_with(config) {
        let name = super::MethodName::from(&method);
        match fit_candidate(samples, &method, config) {
            Ok((loo, model)) => {
                let loss = losses_of(samples, &loo, config.cv_loss);
                candidates.push(AutoCandidate {
                    method: name,
                    loo_rms_target: Some(mean_sqrt(&losses_of(samples, &loo, CvLoss::Target))),
                    cv: Some(CvScore::of(samples, &loo)),
                    cv_error: Some(config.cv_loss.summary(&loss)),
                    excess_se: None,
                });
                fitted.push((loss, model, candidates.len() - 1));
            }
            Err(e) => {
                candidates.push(AutoCandidate {
                    method: name,
                    loo_rms_target: None,
                    cv: None,
                    cv_error: None,
                    excess_se: None,
                });
                first_err.get_or_insert(e);
            }
        }
    }
    let losses: Vec<&[f64]> = fitted.iter().map(|(l, _, _)| l.as_slice()).collect();
    let Some((best, excess)) = excess_over_best(&losses) else {
        return Err(first_err.unwrap_or_else(|| {
            CoreError::Degenerate("auto: no candidate method could be fitted".into())
        }));
    };
    for ((_, _, ci), x) in fitted.iter().zip(&excess) {
        candidates[*ci].excess_se = *x;
    }
    let pick = (0..=best)
        .find(|&i| excess[i].is_some_and(|x| x <= config.cv_margin_se))
        .unwrap_or(best);
    let selection = AutoSelection {
        loss: config.cv_loss,
        margin_se: config.cv_margin_se,
        buffer_px: cv_buffer_px(samples, config),
        best: candidates[fitted[best].2].method,
    };
    Ok(AutoModel {
        chosen: Box::new(fitted.swap_remove(pick).1),
        candidates,
        selection: Some(selection),
    })
}

/// The radius of the cross-validation buffer `config` gives on `samples` (0 when the plan falls
/// back to plain leave-one-out).
fn cv_buffer_px(samples: &SampleSet, config: &LocalConfig) -> f64 {
    if cv_plan(samples, config).iter().all(|b| b.len() == 1) {
        0.0
    } else {
        config.cv_buffer_fraction * diagonal_px(samples.image_size)
    }
}

fn too_few(method: &'static str, got: usize, need: usize) -> CoreError {
    CoreError::TooFewSamples { method, got, need }
}
