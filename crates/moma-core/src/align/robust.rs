//! Robust fits for GSSA, SSRA and their local variants: Huber and Tukey-biweight IRLS, and RANSAC
//! (docs/method.md §2). Real sensor depth is wrong at object edges and on glass; least squares
//! follows such gross errors, these fits do not.
//!
//! Residuals are always measured in **metres**, whatever the alignment space: in inverse space the
//! fit's target is 1/z, so the fitted value is turned back into depth (its reciprocal) before it
//! is compared with the ground-truth depth. A fitted disparity ≤ 0 (no depth) counts as an
//! infinite residual.
//!
//! ## The threshold: `auto` (default) or fixed
//!
//! `threshold_m` (`c` below) is the residual scale. Given (`Some(m)`), it is a fixed number of
//! metres: Huber's corner, Tukey's cut-off and RANSAC's inlier bound alike. By default (`None`,
//! `auto`) it comes from the data, the standard practice of robust regression: `c = k·σ̂` with
//! σ̂ a robust standard deviation of the residuals and k = [`HUBER_K`] (1.345) for Huber,
//! [`TUKEY_K`] (4.685) for Tukey (both 95 % efficient at the normal), [`RANSAC_K`] (2.5) for
//! RANSAC. σ̂ is [`robust_scale_m`]: `σ₀ = 1.4826·(1 + 5/(n − p))·median|r|` (the
//! least-median-of-squares scale of Rousseeuw & Leroy, p the minimal sample size), then the
//! RMS of the residuals within `2.5·σ₀` over their count minus p. The median alone would
//! overestimate σ by ≈ 30 % with 20 % gross outliers (it is then the 62.5 % quantile of the good
//! residuals); the reweighted estimate does not. σ̂ is floored at [`SCALE_FLOOR_M`] (0.1 mm) so
//! that exact data (σ̂ = 0) keep a working threshold.
//!
//! Under `auto` every kind starts from a least-median-of-squares fit: seeded minimal samples
//! (GSSA 2, SSRA 4; `log(1 − p)/log(1 − 0.5ᵐ)` of them, p = 0.999: enough for half the samples
//! being outliers), the one with the smallest median absolute residual; then least squares on
//! its samples within `2.5·σ̂` (σ̂ re-estimated on that fit), until they stop changing.
//! - **Huber / Tukey**: IRLS from that fit with σ̂ kept fixed, as MM-estimation does (a
//!   high-breakdown start and scale, then an efficient M-step; R's `lmrob`). statsmodels' `RLM`
//!   and MATLAB's `robustfit` instead start from least squares and re-estimate the MAD scale at
//!   every step: from least squares, 20 % gross outliers can keep SSRA's IRLS away from the
//!   optimum (measured), and re-estimating σ̂ per step (tried) moved single evaluation rows by
//!   up to 0.6 mm either way, passed the same number of checks, and let σ̂ drift upwards on
//!   scenes the model does not fit exactly. Tukey runs the Huber phase first
//!   (c = 1.345·σ̂), then the biweight (c = 4.685·σ̂).
//! - **RANSAC**: the standard consensus below with the threshold `2.5·σ̂` of the start.
//!
//! The inlier bound under `auto` (inliers reported, the local variants' inlier sets) is
//! [`OUTLIER_K`]`·σ̂` (4.685·σ̂, Tukey's cut-off) for every kind. The report's
//! [`RobustReport::auto`] records σ̂, k and that bound.
//!
//! ## The fits
//!
//! - **Huber** (IRLS): weight `1` for `|r| ≤ c`, `c/|r|` beyond. With a fixed threshold, starts
//!   from the RANSAC fit below (seeded; least squares where RANSAC finds none): from a
//!   least-squares start, IRLS with a small `c` and 20 % gross outliers can stop far from the
//!   optimum within `max_iterations`.
//! - **Tukey** biweight (IRLS): weight `(1 − (r/c)²)²` for `|r| < c`, `0` beyond (a sample more
//!   than `c` from the fit is ignored). Not convex: starts from the Huber fit.
//!
//!   IRLS stops when no sample's fitted depth moves by more than [`IRLS_TOLERANCE_M`] between two
//!   reweightings, or after `max_iterations` reweightings (per phase: Tukey runs up to
//!   `max_iterations` Huber steps, then up to `max_iterations` Tukey steps). In inverse space the
//!   weighted least squares is solved on the 1/z target, and the weights use the target
//!   residual converted to metres to first order at the fitted value (`Δ(1/z)/t_fit²`), so that
//!   each sample's pull on the fit stays bounded (weights from the exact metre residual let a
//!   wrong *near* ground truth, whose 1/z is huge, pull the fit away: seen to diverge on
//!   gqcnn-primesense with 20 % outliers). Inliers, RANSAC's consensus, the scale and the report
//!   use the exact metre residual.
//! - **RANSAC**: minimal samples of the global model (GSSA 2, SSRA 4 samples), drawn with
//!   `ChaCha8Rng::seed_from_u64(seed)`; consensus = samples with `|r| < c`; the hypothesis with the
//!   most inliers wins (ties: the lower sum of squared inlier residuals); then least squares on
//!   its inliers, repeated while the inlier set changes and does not shrink. Hypotheses: at most
//!   `max_iterations`, fewer once the standard bound `log(1 − p)/log(1 − εᵐ)` (p = 0.999, ε the
//!   best inlier fraction so far, m the minimal sample size) is reached.
//!
//! Local variants (`ssra-local`, `gssa-local`): the robust fit of the global part (as above) gives
//! the inliers (`|r|` below the inlier bound: `c` for a fixed threshold, 4.685·σ̂ under `auto`); the whole local model (global least squares, cross-validated
//! correction, fallback guard: [`super::local::fit`]) is fitted on the inliers only; its residuals
//! on all samples give the next inlier set, and this repeats until the set stops changing (at most
//! [`LOCAL_ROUNDS`] rounds). Outliers therefore never reach the local correction, which would
//! otherwise bend towards them. The rounds run from two starts: the robust global fit's inliers,
//! and those joined by the inliers of the plain local fit on all samples (where the scene departs
//! from the global model by more than the bound, only a local model can tell its samples from
//! outliers). Of every round's model, the one with the largest consensus (inliers within the
//! bound, then the lower sum of their squared residuals) is kept: the plain local fit saw the
//! outliers too, and a few of them joined to the start can drag the global least squares of the
//! next round away, after which the inlier set collapses (seen: gqcnn-primesense, simulator seed
//! 8, 20 % outliers: 82 → 33 inliers and 196 mm MAE, against 22 mm from the robust start alone).
//!
//! Inliers reported: samples with `|r|` below the inlier bound under the final model, for every
//! kind (with a fixed threshold, for Huber: the samples in its quadratic zone). LWLR, `auto` and `raw` are refused with a clear error: LWLR has
//! no global model to reweight (its per-pixel fits would need their own robust weights) and `auto`
//! chooses by cross-validation on all samples.

use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::local::{self, GlobalFit, LocalBase, LocalConfig};
use super::ssra::SsraConfig;
use super::{AlignmentModel, FitReport, Method, Sample, SampleSet, gssa, ssra};
use crate::error::{CoreError, Result};
use crate::normalise::AlignSpace;

/// The former fixed default residual scale, metres (1 cm). The default is now [`Robust::new`]'s
/// `auto` rule (a scale estimated from the data); this value is kept for comparisons.
pub const DEFAULT_THRESHOLD_M: f64 = 0.01;
/// Huber's tuning constant in robust standard deviations (95 % efficiency at the normal).
pub const HUBER_K: f64 = 1.345;
/// Tukey biweight's tuning constant in robust standard deviations (95 % efficiency at the
/// normal).
pub const TUKEY_K: f64 = 4.685;
/// RANSAC's inlier bound under `auto`, in robust standard deviations (Rousseeuw & Leroy's
/// reweighting rule; also the cut-off of [`robust_scale_m`]'s reweighted estimate).
pub const RANSAC_K: f64 = 2.5;
/// The inlier bound under `auto` for every kind (the inliers reported, the local variants'
/// inlier sets), in robust standard deviations: Tukey's cut-off, beyond which the biweight gives
/// a sample no weight. Wider than [`RANSAC_K`]: real scenes' good residuals are heavier-tailed
/// than the normal (measured on m2t2-table), and the local model should lose none of them.
pub const OUTLIER_K: f64 = TUKEY_K;
/// 1/Φ⁻¹(3/4): turns a median absolute residual into a standard deviation at the normal.
pub const MAD_TO_SIGMA: f64 = 1.4826;
/// Floor of the estimated scale, metres (0.1 mm: far below any depth sensor's noise, so real data
/// never reach it; it keeps exact data, whose scale estimate is 0, working).
pub const SCALE_FLOOR_M: f64 = 1e-4;
/// Default reweightings of Huber/Tukey IRLS (per phase).
pub const DEFAULT_IRLS_ITERATIONS: usize = 50;
/// Default most RANSAC hypotheses.
pub const DEFAULT_RANSAC_ITERATIONS: usize = 1000;
/// IRLS stops once no fitted depth moves by more than this between two reweightings, metres.
pub const IRLS_TOLERANCE_M: f64 = 1e-9;
/// Most rounds of (inliers → local fit → inliers) for the local variants.
pub const LOCAL_ROUNDS: usize = 5;
/// RANSAC's confidence for its adaptive number of hypotheses.
const RANSAC_CONFIDENCE: f64 = 0.999;
/// Most least-squares refits on the consensus set.
const RANSAC_REFITS: usize = 10;

/// The robust loss or estimator.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RobustKind {
    /// Huber loss by iteratively reweighted least squares.
    Huber,
    /// Tukey biweight by iteratively reweighted least squares (started from Huber).
    Tukey,
    /// Random sample consensus on minimal samples, then least squares on the inliers.
    Ransac,
}

impl RobustKind {
    /// Every kind, in documentation order.
    pub const ALL: [RobustKind; 3] = [Self::Huber, Self::Tukey, Self::Ransac];

    /// The command-line and file name (`huber`, `tukey`, `ransac`).
    pub const fn name(self) -> &'static str {
        match self {
            Self::Huber => "huber",
            Self::Tukey => "tukey",
            Self::Ransac => "ransac",
        }
    }
}

impl std::fmt::Display for RobustKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for RobustKind {
    type Err = CoreError;
    fn from_str(s: &str) -> Result<Self> {
        crate::names::parse(s, &Self::ALL, Self::name, "robust fit")
    }
}

/// A robust fit's settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Robust {
    /// Huber, Tukey or RANSAC.
    pub kind: RobustKind,
    /// Fixed residual scale c, metres (Huber's corner, Tukey's cut-off, RANSAC's inlier bound),
    /// > 0; `None` (the default, `auto`): c from a scale estimated on the data (module docs).
    pub threshold_m: Option<f64>,
    /// Most IRLS reweightings per phase, or most RANSAC hypotheses; ≥ 1.
    pub max_iterations: usize,
    /// Seed of RANSAC's minimal samples (also the start of Huber and Tukey IRLS).
    pub seed: u64,
}

impl Robust {
    /// `kind` with the defaults: threshold `auto` (from the data), [`DEFAULT_IRLS_ITERATIONS`]
    /// or [`DEFAULT_RANSAC_ITERATIONS`], seed 0.
    pub const fn new(kind: RobustKind) -> Self {
        Self {
            kind,
            threshold_m: None,
            max_iterations: match kind {
                RobustKind::Ransac => DEFAULT_RANSAC_ITERATIONS,
                RobustKind::Huber | RobustKind::Tukey => DEFAULT_IRLS_ITERATIONS,
            },
            seed: 0,
        }
    }

    /// The same settings with the fixed residual scale `threshold_m` (metres).
    pub const fn with_threshold_m(self, threshold_m: f64) -> Self {
        Self {
            threshold_m: Some(threshold_m),
            ..self
        }
    }

    /// The same settings with the threshold estimated from the data (`auto`, the default).
    pub const fn with_auto_threshold(self) -> Self {
        Self {
            threshold_m: None,
            ..self
        }
    }

    /// The same settings with RANSAC seed `seed`.
    pub const fn with_seed(self, seed: u64) -> Self {
        Self { seed, ..self }
    }

    /// Checks the settings: `threshold_m` auto or finite and > 0, `max_iterations` ≥ 1.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] naming the bad value.
    pub fn validate(&self) -> Result<()> {
        if let Some(t) = self.threshold_m
            && !(t.is_finite() && t > 0.0)
        {
            return Err(CoreError::InvalidParameter(format!(
                "robust threshold must be 'auto' or a finite number of metres > 0, got {t}"
            )));
        }
        if self.max_iterations == 0 {
            return Err(CoreError::InvalidParameter(
                "robust fit needs max_iterations ≥ 1".into(),
            ));
        }
        Ok(())
    }

    /// Errors unless `method` supports robust fitting (gssa, ssra, gssa-local, ssra-local).
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] for lwlr, lwlr-exact, lwlr-bare, auto and raw.
    pub fn check_method(&self, method: &Method) -> Result<()> {
        self.bases(method).map(|_| ())
    }

    /// The global model and, for a local variant, its base and settings.
    fn bases<'m>(
        &self,
        method: &'m Method,
    ) -> Result<(Base, Option<(LocalBase, &'m LocalConfig)>)> {
        match method {
            Method::Gssa => Ok((Base::Gssa, None)),
            Method::Ssra(cfg) => Ok((Base::Ssra(*cfg), None)),
            Method::GssaLocal(cfg) => Ok((Base::Gssa, Some((LocalBase::Gssa, cfg)))),
            Method::SsraLocal(cfg) => Ok((
                Base::Ssra(SsraConfig::default()),
                Some((LocalBase::Ssra, cfg)),
            )),
            other => Err(CoreError::InvalidParameter(format!(
                "robust fitting ({}) supports gssa, ssra, gssa-local and ssra-local, not '{}' \
                 (LWLR has no global model to reweight, auto chooses by cross-validation on all \
                 samples, raw fits nothing)",
                self.kind,
                other.name()
            ))),
        }
    }

    /// Fits `method` robustly on `targets`, whose `depth_m` field holds the fit's target in
    /// `space` (depth in metres, or 1/z in inverse space, as the pipeline prepares it). The report
    /// carries the [`RobustReport`]; its `rms_residual_m` is over all samples, in metres (a
    /// sample without depth counts with its full ground-truth depth).
    ///
    /// # Errors
    /// - settings or method refused ([`Robust::validate`], [`Robust::check_method`]);
    /// - [`CoreError::InvalidSample`] for a bad sample;
    /// - [`CoreError::TooFewSamples`]: fewer samples than the method needs (RANSAC: fewer than
    ///   its minimal sample, 2 for GSSA, 4 for SSRA), or fewer inliers than the local variant
    ///   needs;
    /// - [`CoreError::Degenerate`]: no sample within `threshold_m` of the fit (Tukey), no
    ///   minimal sample giving a fit (RANSAC), or the weighted fit's own degeneracies.
    pub fn fit(
        &self,
        method: &Method,
        targets: &SampleSet,
        space: AlignSpace,
    ) -> Result<(AlignmentModel, FitReport)> {
        let start = Instant::now();
        self.validate()?;
        let (base, local_cfg) = self.bases(method)?;
        targets.validate()?;
        let ctx = Ctx {
            samples: &targets.samples,
            set: targets,
            space,
        };
        if self.kind == RobustKind::Ransac && ctx.samples.len() < base.minimal() {
            return Err(CoreError::TooFewSamples {
                method: base.ransac_name(),
                got: ctx.samples.len(),
                need: base.minimal(),
            });
        }
        targets.require(method.name(), method.min_samples())?;
        // (global fit, iterations, the kind's constant c, inlier bound, auto block)
        let (global, mut iterations, c, bound, auto) = match self.threshold_m {
            Some(c) => {
                let (g, it) = match self.kind {
                    RobustKind::Huber | RobustKind::Tukey => {
                        let ransac = Self {
                            kind: RobustKind::Ransac,
                            max_iterations: DEFAULT_RANSAC_ITERATIONS,
                            ..*self
                        };
                        let start = match ransac.ransac(&ctx, base, c) {
                            Ok((m, _)) => m,
                            Err(_) => base.fit(ctx.set, None)?,
                        };
                        let phases: &[(bool, f64)] = if self.kind == RobustKind::Tukey {
                            &[(false, 1.0), (true, 1.0)]
                        } else {
                            &[(false, 1.0)]
                        };
                        self.irls(&ctx, base, start, c, phases)?
                    }
                    RobustKind::Ransac => self.ransac(&ctx, base, c)?,
                };
                (g, it, c, c, None)
            }
            None => {
                let (start, sigma_start, drawn) = self.auto_start(&ctx, base)?;
                let (g, it, factor, sigma) = match self.kind {
                    RobustKind::Huber => {
                        let (g, it) =
                            self.irls(&ctx, base, start, sigma_start, &[(false, HUBER_K)])?;
                        (g, it, HUBER_K, sigma_start)
                    }
                    RobustKind::Tukey => {
                        let phases = [(false, HUBER_K), (true, TUKEY_K)];
                        let (g, it) = self.irls(&ctx, base, start, sigma_start, &phases)?;
                        (g, it, TUKEY_K, sigma_start)
                    }
                    RobustKind::Ransac => {
                        let (g, d) = self.ransac(&ctx, base, RANSAC_K * sigma_start)?;
                        (g, d + drawn, RANSAC_K, sigma_start)
                    }
                };
                let bound = OUTLIER_K * sigma;
                let auto = AutoThreshold {
                    scale_m: sigma,
                    factor,
                    inlier_bound_m: bound,
                };
                (g, it, factor * sigma, bound, Some(auto))
            }
        };
        let model = match local_cfg {
            None => global_model(global),
            Some((lbase, cfg)) => {
                // Two starts: the inliers of the robust global fit, and those joined by the
                // inliers of the plain local fit on all samples (where the scene departs from
                // the global model by more than the bound, only a local model can tell its
                // samples from outliers; but that fit saw the outliers too, and may have bent
                // towards some). From each, rounds of (local fit on the inliers → its inliers);
                // of every round's model the one with the largest consensus is kept.
                let robust_start = ctx.inliers(bound, |s| global.predict(s.u, s.v, s.pred));
                let mut starts = vec![robust_start.clone()];
                if let Ok(plain) = local::fit(targets, lbase, cfg) {
                    let plain = AlignmentModel::Local(Box::new(plain));
                    let more = ctx.inliers(bound, |s| plain.predict_at(s.u, s.v, s.pred));
                    let joined: Vec<bool> = robust_start
                        .iter()
                        .zip(more)
                        .map(|(a, b)| *a || b)
                        .collect();
                    if joined != robust_start {
                        starts.push(joined);
                    }
                }
                let mut best: Option<(AlignmentModel, (usize, f64))> = None;
                for mut inliers in starts {
                    for _ in 0..LOCAL_ROUNDS {
                        let subset = SampleSet {
                            space: targets.space,
                            image_size: targets.image_size,
                            samples: ctx
                                .samples
                                .iter()
                                .zip(&inliers)
                                .filter(|(_, i)| **i)
                                .map(|(s, _)| *s)
                                .collect(),
                        };
                        if subset.len() < method.min_samples() {
                            if best.is_some() {
                                break;
                            }
                            return Err(CoreError::TooFewSamples {
                                method: local_name(lbase),
                                got: subset.len(),
                                need: method.min_samples(),
                            });
                        }
                        let m = match local::fit(&subset, lbase, cfg) {
                            Ok(m) => AlignmentModel::Local(Box::new(m)),
                            // the other start already gave a model: keep it
                            Err(_) if best.is_some() => break,
                            Err(e) => return Err(e),
                        };
                        iterations += 1;
                        let predict = |s: &Sample| m.predict_at(s.u, s.v, s.pred);
                        let next = ctx.inliers(bound, predict);
                        let score = ctx.consensus_of(bound, predict);
                        let stable = next == inliers;
                        if best.as_ref().is_none_or(|(_, b)| better(score, *b)) {
                            best = Some((m, score));
                        }
                        if stable {
                            break;
                        }
                        inliers = next;
                    }
                }
                best.map(|(m, _)| m)
                    .ok_or_else(|| CoreError::Degenerate("robust local fit made no round".into()))?
            }
        };
        let predict = |s: &Sample| model.predict_at(s.u, s.v, s.pred);
        let residuals: Vec<f64> = ctx
            .samples
            .iter()
            .map(|s| ctx.residual_m(s, predict(s)))
            .collect();
        let in_r: Vec<f64> = residuals
            .iter()
            .zip(ctx.inliers(bound, predict))
            .filter(|(_, i)| *i)
            .map(|(r, _)| *r)
            .collect();
        let rms = |rs: &[f64], fallback: &[f64]| {
            if rs.is_empty() {
                return 0.0;
            }
            let ss: f64 = rs
                .iter()
                .zip(fallback)
                .map(|(r, z)| if r.is_finite() { r * r } else { z * z })
                .sum();
            (ss / rs.len() as f64).sqrt()
        };
        let depths: Vec<f64> = ctx.samples.iter().map(|s| ctx.depth_m(s)).collect();
        let report = FitReport {
            method: super::MethodName::from(method),
            n_used: ctx.samples.len(),
            rms_residual_m: rms(&residuals, &depths),
            fit_time_s: start.elapsed().as_secs_f64(),
            robust: Some(RobustReport {
                kind: self.kind,
                threshold_m: c,
                inliers: in_r.len(),
                iterations,
                inlier_rms_residual_m: rms(&in_r, &in_r),
                auto,
            }),
        };
        Ok((model, report))
    }

    /// The `auto` rule's start and scale: least median of squares over seeded minimal samples
    /// ([`Self::lmeds`]); least squares on its samples within [`RANSAC_K`]`·σ̂₀` (σ̂₀ the
    /// [`robust_scale_m`] of its residuals); σ̂ again from that fit's residuals; least squares on
    /// the samples within [`RANSAC_K`]`·σ̂` until they stop changing. Scales are floored at
    /// [`SCALE_FLOOR_M`]. Returns (fit, σ̂ in metres, minimal samples drawn).
    fn auto_start(&self, ctx: &Ctx<'_>, base: Base) -> Result<(GlobalFit, f64, usize)> {
        let most = match self.kind {
            RobustKind::Ransac => self.max_iterations,
            RobustKind::Huber | RobustKind::Tukey => DEFAULT_RANSAC_ITERATIONS,
        };
        let (hyp, drawn) = self.lmeds(ctx, base, most)?;
        let sigma_h = ctx.scale_m(&hyp, base.minimal());
        let first = consensus_refit(ctx, base, hyp, RANSAC_K * sigma_h);
        let sigma = ctx.scale_m(&first, base.minimal());
        let fit = consensus_refit(ctx, base, first, RANSAC_K * sigma);
        Ok((fit, sigma, drawn))
    }

    /// Least median of squares over minimal samples (metre residuals): the hypothesis with the
    /// smallest median absolute residual wins. Hypotheses: the standard bound for half the
    /// samples being outliers (`log(1 − p)/log(1 − 0.5ᵐ)`: 24 for GSSA, 107 for SSRA, the
    /// median's breakdown point), at most `most`.
    fn lmeds(&self, ctx: &Ctx<'_>, base: Base, most: usize) -> Result<(GlobalFit, usize)> {
        let n = ctx.samples.len();
        let m = base.minimal();
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
        let mut best: Option<(f64, GlobalFit)> = None;
        // half the samples good: εᵐ = 0.5ᵐ
        let needed = adaptive_bound(n.div_ceil(2), n, m, 0, most).max(1);
        let mut drawn = 0;
        let mut subset = SampleSet {
            space: ctx.set.space,
            image_size: ctx.set.image_size,
            samples: Vec::with_capacity(m),
        };
        let mut abs_r = Vec::with_capacity(n);
        while drawn < needed {
            drawn += 1;
            subset.samples.clear();
            subset.samples.extend(
                rand::seq::index::sample(&mut rng, n, m)
                    .iter()
                    .map(|k| ctx.samples[k]),
            );
            let Ok(hyp) = base.fit(&subset, None) else {
                continue; // degenerate minimal sample (equal ẑ, collinear pixels)
            };
            abs_r.clear();
            abs_r.extend(
                ctx.samples
                    .iter()
                    .map(|s| abs_or_inf(ctx.residual_m(s, hyp.predict(s.u, s.v, s.pred)))),
            );
            let med = median(&mut abs_r);
            if best.as_ref().is_none_or(|(b, _)| med < *b) {
                best = Some((med, hyp));
            }
        }
        let (_, model) = best.ok_or_else(|| {
            CoreError::Degenerate(format!(
                "robust fit: none of {drawn} minimal samples of {m} gave a {} fit (constant ẑ \
                 or collinear pixels)",
                base.name()
            ))
        })?;
        Ok((model, drawn))
    }

    /// Huber IRLS (then Tukey IRLS) from `start` in `phases` of (is Tukey, factor k): constant
    /// `c = k·scale_m` (a fixed threshold: k = 1). Returns (fit, reweightings).
    fn irls(
        &self,
        ctx: &Ctx<'_>,
        base: Base,
        start: GlobalFit,
        scale_m: f64,
        phases: &[(bool, f64)],
    ) -> Result<(GlobalFit, usize)> {
        let mut model = start;
        let mut iterations = 0;
        for &(is_tukey, k) in phases {
            for _ in 0..self.max_iterations {
                let (next, moved) = self.reweight(ctx, base, &model, is_tukey, k * scale_m)?;
                iterations += 1;
                model = next;
                if moved <= IRLS_TOLERANCE_M {
                    break;
                }
            }
        }
        Ok((model, iterations))
    }

    /// One IRLS step with constant `c` (metres): the weighted fit and the largest move of a
    /// fitted depth.
    fn reweight(
        &self,
        ctx: &Ctx<'_>,
        base: Base,
        model: &GlobalFit,
        is_tukey: bool,
        c: f64,
    ) -> Result<(GlobalFit, f64)> {
        let mut weights = vec![0.0; ctx.samples.len()];
        let mut positive = 0;
        for (w, s) in weights.iter_mut().zip(ctx.samples) {
            let r = ctx
                .linearised_residual_m(s, model.predict(s.u, s.v, s.pred))
                .abs();
            *w = if is_tukey {
                if r < c {
                    (1.0 - (r / c).powi(2)).powi(2)
                } else {
                    0.0
                }
            } else if r <= c {
                1.0
            } else {
                c / r // 0 for an infinite residual
            };
            if *w > 0.0 {
                positive += 1;
            }
        }
        if positive < base.minimal() {
            return Err(CoreError::Degenerate(format!(
                "{}: only {positive} of {} samples lie within {c} m of the fit; the threshold is \
                 too small for these data",
                self.kind,
                ctx.samples.len()
            )));
        }
        let next = base.fit(ctx.set, Some(&weights))?;
        let moved = ctx
            .samples
            .iter()
            .map(|s| {
                let a = ctx.space.depth_from_target(model.predict(s.u, s.v, s.pred));
                let b = ctx.space.depth_from_target(next.predict(s.u, s.v, s.pred));
                if a.is_finite() && b.is_finite() {
                    (a - b).abs()
                } else if a.is_finite() == b.is_finite() {
                    0.0
                } else {
                    f64::INFINITY
                }
            })
            .fold(0.0, f64::max);
        Ok((next, moved))
    }

    /// RANSAC on the global model with inlier bound `c` (metres), then least squares on the
    /// consensus set.
    fn ransac(&self, ctx: &Ctx<'_>, base: Base, c: f64) -> Result<(GlobalFit, usize)> {
        let n = ctx.samples.len();
        let m = base.minimal();
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
        let mut best: Option<((usize, f64), GlobalFit)> = None;
        let mut needed = self.max_iterations;
        let mut drawn = 0;
        let mut subset = SampleSet {
            space: ctx.set.space,
            image_size: ctx.set.image_size,
            samples: Vec::with_capacity(m),
        };
        while drawn < needed {
            drawn += 1;
            subset.samples.clear();
            subset.samples.extend(
                rand::seq::index::sample(&mut rng, n, m)
                    .iter()
                    .map(|k| ctx.samples[k]),
            );
            let Ok(hyp) = base.fit(&subset, None) else {
                continue; // degenerate minimal sample (equal ẑ, collinear pixels)
            };
            let score = ctx.consensus(&hyp, c);
            if best.as_ref().is_none_or(|(b, _)| better(score, *b)) {
                best = Some((score, hyp));
                needed = adaptive_bound(score.0, n, m, drawn, self.max_iterations);
            }
        }
        let ((count, _), model) = best.ok_or_else(|| {
            CoreError::Degenerate(format!(
                "ransac: none of {drawn} minimal samples of {m} gave a {} fit (constant ẑ or \
                 collinear pixels)",
                base.name()
            ))
        })?;
        // a consensus of the minimal sample alone is an exact fit through it, whatever the
        // data: the threshold is below the data's own scatter (1e-9 m kept 2 of 100)
        if count <= m {
            let why = if self.threshold_m.is_some() {
                "the fixed threshold is too small for these data (the `auto` threshold is \
                 estimated from them)"
                    .to_string()
            } else if n <= 2 * m {
                format!(
                    "the `auto` threshold, estimated from the data, keeps no consensus: {n} \
                     samples are too few to tell inliers from outliers (give more samples)"
                )
            } else {
                "the `auto` threshold, estimated from the data, keeps no consensus: no fit \
                 agrees with more than its minimal sample (samples scattered beyond any one \
                 fit)"
                    .to_string()
            };
            return Err(CoreError::Degenerate(format!(
                "ransac: at best {count} of {n} samples lie within {c} m of a fit (its minimal \
                 sample of {m}); {why}"
            )));
        }
        Ok((consensus_refit(ctx, base, model, c), drawn))
    }
}

/// Robust standard deviation of the residuals (metres) of a fit with `params` parameters
/// (Rousseeuw & Leroy 1987): the preliminary `σ₀ = 1.4826·(1 + 5/(n − params))·median|r|`,
/// then the root mean square of the residuals within [`RANSAC_K`]`·σ₀`, over their count minus
/// `params`. With 20 % gross outliers the median alone overestimates σ by about 30 % (it is then
/// the 62.5 % quantile of the good residuals); the reweighted estimate does not. Returns 0 for no
/// residuals or exact data (the fit floors it at [`SCALE_FLOOR_M`]); a non-finite residual
/// counts as an outlier.
pub fn robust_scale_m(residuals_m: &[f64], params: usize) -> f64 {
    let n = residuals_m.len();
    if n == 0 {
        return 0.0;
    }
    let mut abs_r: Vec<f64> = residuals_m.iter().map(|r| abs_or_inf(*r)).collect();
    let sigma0 =
        MAD_TO_SIGMA * (1.0 + 5.0 / n.saturating_sub(params).max(1) as f64) * median(&mut abs_r);
    let (ss, count) = abs_r
        .iter()
        .filter(|r| **r <= RANSAC_K * sigma0)
        .fold((0.0, 0usize), |(ss, k), r| (ss + r * r, k + 1));
    match count.checked_sub(params) {
        Some(dof) if dof > 0 => (ss / dof as f64).sqrt(),
        _ => sigma0,
    }
}

/// `|r|`, infinite for NaN.
/// Consensus order: more inliers, then (same count) the lower sum of squared inlier residuals.
fn better(a: (usize, f64), b: (usize, f64)) -> bool {
    a.0 > b.0 || (a.0 == b.0 && a.1 < b.1)
}

fn abs_or_inf(r: f64) -> f64 {
    if r.is_nan() { f64::INFINITY } else { r.abs() }
}

/// Median of `v` (mean of the middle two for an even count); reorders `v`; 0 when empty.
fn median(v: &mut [f64]) -> f64 {
    let n = v.len();
    if n == 0 {
        return 0.0;
    }
    let (lo, mid, _) = v.select_nth_unstable_by(n / 2, f64::total_cmp);
    let mid = *mid;
    if n % 2 == 1 {
        mid
    } else {
        let below = lo.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        0.5 * (below + mid)
    }
}

/// Hypotheses needed for [`RANSAC_CONFIDENCE`] with `count` of `n` inliers and minimal sample
/// `m` (`log(1 − p)/log(1 − εᵐ)`), at least `drawn`, at most `most`.
fn adaptive_bound(count: usize, n: usize, m: usize, drawn: usize, most: usize) -> usize {
    let eps = count as f64 / n as f64;
    let p_good = eps.powi(m as i32);
    if p_good >= 1.0 {
        drawn
    } else if p_good <= 0.0 {
        most
    } else {
        let k = ((1.0 - RANSAC_CONFIDENCE).ln() / (1.0 - p_good).ln()).ceil();
        (k.max(1.0) as usize).min(most)
    }
}

/// Least squares on the samples within `c` (metres) of `model`, repeated while the set changes
/// and does not shrink (at most [`RANSAC_REFITS`] times).
fn consensus_refit(ctx: &Ctx<'_>, base: Base, mut model: GlobalFit, c: f64) -> GlobalFit {
    let mut inliers = ctx.inliers(c, |s| model.predict(s.u, s.v, s.pred));
    let mut count = inliers.iter().filter(|&&i| i).count();
    for _ in 0..RANSAC_REFITS {
        let weights: Vec<f64> = inliers.iter().map(|&i| f64::from(u8::from(i))).collect();
        let Ok(refit) = base.fit(ctx.set, Some(&weights)) else {
            break;
        };
        let next = ctx.inliers(c, |s| refit.predict(s.u, s.v, s.pred));
        let next_count = next.iter().filter(|&&i| i).count();
        if next_count < count {
            break;
        }
        model = refit;
        count = next_count;
        if next == inliers {
            break;
        }
        inliers = next;
    }
    model
}

impl std::fmt::Display for Robust {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.kind.name())
    }
}

impl std::str::FromStr for Robust {
    type Err = CoreError;
    /// A kind name (`huber`, `tukey`, `ransac`) with the defaults of [`Robust::new`].
    fn from_str(s: &str) -> Result<Self> {
        s.parse::<RobustKind>().map(Self::new)
    }
}

/// What a robust fit reports (inside [`FitReport::robust`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobustReport {
    /// Huber, Tukey or RANSAC.
    pub kind: RobustKind,
    /// Residual scale used, metres: Huber's corner, Tukey's cut-off (its final phase), RANSAC's
    /// inlier bound; under `auto`, `factor · scale_m`.
    pub threshold_m: f64,
    /// Samples whose residual under the final model is below the inlier bound (in metres):
    /// `threshold_m` for a fixed threshold, `auto.inlier_bound_m` under `auto`.
    pub inliers: usize,
    /// IRLS reweightings (both phases for Tukey; the RANSAC start not counted) or RANSAC
    /// hypotheses drawn, plus one per inlier-set round of a local variant.
    pub iterations: usize,
    /// RMS residual over the inliers, metres.
    pub inlier_rms_residual_m: f64,
    /// The `auto` rule's estimate; absent for a fixed threshold (and in files written before
    /// the rule existed, which all used a fixed threshold).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub auto: Option<AutoThreshold>,
}

/// The scale the `auto` threshold rule estimated (inside [`RobustReport::auto`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AutoThreshold {
    /// Robust standard deviation σ̂ of the good residuals, metres ([`robust_scale_m`], floored
    /// at [`SCALE_FLOOR_M`]).
    pub scale_m: f64,
    /// `threshold_m / scale_m`: [`HUBER_K`], [`TUKEY_K`] or [`RANSAC_K`].
    pub factor: f64,
    /// [`OUTLIER_K`]` · scale_m`, metres: the inlier bound (inliers reported, local variants'
    /// inlier sets).
    pub inlier_bound_m: f64,
}

impl RobustReport {
    /// Checks a report read from a file against the number of samples used.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] naming the bad value.
    pub fn validate(&self, n_used: usize) -> Result<()> {
        Robust::new(self.kind)
            .with_threshold_m(self.threshold_m)
            .validate()?;
        if let Some(a) = &self.auto {
            for (name, v) in [
                ("scale_m", a.scale_m),
                ("factor", a.factor),
                ("inlier_bound_m", a.inlier_bound_m),
            ] {
                if !(v.is_finite() && v > 0.0) {
                    return Err(CoreError::InvalidParameter(format!(
                        "robust report auto.{name} must be a finite number > 0, got {v}"
                    )));
                }
            }
        }
        if self.inliers > n_used {
            return Err(CoreError::InvalidParameter(format!(
                "robust report counts {} inliers among {n_used} samples",
                self.inliers
            )));
        }
        if !(self.inlier_rms_residual_m.is_finite() && self.inlier_rms_residual_m >= 0.0) {
            return Err(CoreError::InvalidParameter(format!(
                "robust report inlier_rms_residual_m is {}",
                self.inlier_rms_residual_m
            )));
        }
        Ok(())
    }
}

/// The global model a robust fit works on.
#[derive(Debug, Clone, Copy)]
enum Base {
    Gssa,
    Ssra(SsraConfig),
}

impl Base {
    /// Minimal sample size.
    fn minimal(self) -> usize {
        match self {
            Self::Gssa => gssa::MIN_SAMPLES,
            Self::Ssra(_) => ssra::MIN_SAMPLES,
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::Gssa => "gssa",
            Self::Ssra(_) => "ssra",
        }
    }

    fn ransac_name(self) -> &'static str {
        match self {
            Self::Gssa => "ransac (gssa)",
            Self::Ssra(_) => "ransac (ssra)",
        }
    }

    /// (Weighted) least squares of the global model.
    fn fit(self, set: &SampleSet, weights: Option<&[f64]>) -> Result<GlobalFit> {
        Ok(match (self, weights) {
            (Self::Gssa, None) => GlobalFit::Gssa(gssa::fit(&set.samples)?),
            (Self::Gssa, Some(w)) => GlobalFit::Gssa(gssa::fit_weighted(&set.samples, w)?),
            (Self::Ssra(cfg), None) => GlobalFit::Ssra(ssra::fit(set, &cfg)?),
            (Self::Ssra(cfg), Some(w)) => GlobalFit::Ssra(ssra::fit_weighted(set, &cfg, w)?),
        })
    }
}

fn local_name(base: LocalBase) -> &'static str {
    match base {
        LocalBase::Gssa => "gssa-local (inliers)",
        LocalBase::Ssra => "ssra-local (inliers)",
    }
}

fn global_model(g: GlobalFit) -> AlignmentModel {
    match g {
        GlobalFit::Gssa(m) => AlignmentModel::Gssa(m),
        GlobalFit::Ssra(m) => AlignmentModel::Ssra(m),
    }
}

/// The samples and their space.
struct Ctx<'a> {
    samples: &'a [Sample],
    set: &'a SampleSet,
    space: AlignSpace,
}

impl Ctx<'_> {
    /// Ground-truth depth of a sample, metres.
    fn depth_m(&self, s: &Sample) -> f64 {
        self.space.depth_from_target(s.target)
    }

    /// Fitted minus ground-truth depth, metres; infinite where the fit gives no depth.
    fn residual_m(&self, s: &Sample, fitted_target: f64) -> f64 {
        let z = self.space.depth_from_target(fitted_target);
        if z.is_finite() {
            z - self.depth_m(s)
        } else {
            f64::INFINITY
        }
    }

    /// The target-space residual in metres to first order at the *fitted* value:
    /// `(fitted − target)·dz/dt` (`−1/fitted²` in inverse space, 1 in depth space; infinite
    /// where the fitted disparity is ≤ 0). IRLS weighs with it, so that every sample's pull on
    /// the target-space least squares (`w·Δt`) stays bounded by about `c·t²` at the fit — a
    /// wrong near ground truth (1/z huge) would otherwise dominate the fit.
    fn linearised_residual_m(&self, s: &Sample, fitted_target: f64) -> f64 {
        match self.space {
            AlignSpace::Depth => fitted_target - s.target,
            AlignSpace::Inverse if fitted_target > 0.0 && fitted_target.is_finite() => {
                -(fitted_target - s.target) / (fitted_target * fitted_target)
            }
            AlignSpace::Inverse => f64::INFINITY,
        }
    }

    /// `|r| < c` per sample under `predict` (fitted target value), `r` in metres.
    fn inliers(&self, c: f64, predict: impl Fn(&Sample) -> f64) -> Vec<bool> {
        self.samples
            .iter()
            .map(|s| self.residual_m(s, predict(s)).abs() < c)
            .collect()
    }

    /// [`robust_scale_m`] of the metre residuals of `g`, floored at [`SCALE_FLOOR_M`].
    fn scale_m(&self, g: &GlobalFit, params: usize) -> f64 {
        let r: Vec<f64> = self
            .samples
            .iter()
            .map(|s| self.residual_m(s, g.predict(s.u, s.v, s.pred)))
            .collect();
        robust_scale_m(&r, params).max(SCALE_FLOOR_M)
    }

    /// Inlier count and sum of squared inlier residuals (m²) of a hypothesis.
    fn consensus(&self, g: &GlobalFit, c: f64) -> (usize, f64) {
        self.consensus_of(c, |s| g.predict(s.u, s.v, s.pred))
    }

    /// Inlier count and sum of squared inlier residuals (m²) under `predict` (fitted target).
    fn consensus_of(&self, c: f64, predict: impl Fn(&Sample) -> f64) -> (usize, f64) {
        let mut count = 0;
        let mut ss = 0.0;
        for s in self.samples {
            let r = self.residual_m(s, predict(s));
            if r.abs() < c {
                count += 1;
                ss += r * r;
            }
        }
        (count, ss)
    }
}
