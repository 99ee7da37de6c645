//! Robust fits for GSSA, SSRA and their local variants: Huber and Tukey-biweight IRLS, and RANSAC
//! (issue 12, item 3). Real sensor depth is wrong at object edges and on glass; least squares
//! follows such gross errors, these fits do not.
//!
//! Residuals are always measured in **metres**, whatever the alignment space: in inverse space the
//! fit's target is 1/z, so the fitted value is turned back into depth (its reciprocal) before it
//! is compared with the ground-truth depth. A fitted disparity ≤ 0 (no depth) counts as an
//! infinite residual. `threshold_m` (`c` below) is the residual scale:
//!
//! - **Huber** (IRLS): weight `1` for `|r| ≤ c`, `c/|r|` beyond. Starts from the RANSAC fit
//!   below (seeded; least squares where RANSAC finds none): from a least-squares start, IRLS with
//!   a small `c` and 20 % gross outliers can stop far from the optimum within `max_iterations`.
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
//!   gqcnn-primesense with 20 % outliers). Inliers, RANSAC's consensus and the report use the
//!   exact metre residual.
//! - **RANSAC**: minimal samples of the global model (GSSA 2, SSRA 4 samples), drawn with
//!   `ChaCha8Rng::seed_from_u64(seed)`; consensus = samples with `|r| < c`; the hypothesis with the
//!   most inliers wins (ties: the lower sum of squared inlier residuals); then least squares on
//!   its inliers, repeated while the inlier set changes and does not shrink. Hypotheses: at most
//!   `max_iterations`, fewer once the standard bound `log(1 − p)/log(1 − εᵐ)` (p = 0.999, ε the
//!   best inlier fraction so far, m the minimal sample size) is reached.
//!
//! Local variants (`ssra-local`, `gssa-local`): the robust fit of the global part (as above) gives
//! the inliers (`|r| < c`); the whole local model (global least squares, cross-validated
//! correction, fallback guard: [`super::local::fit`]) is fitted on the inliers only; its residuals
//! on all samples give the next inlier set, and this repeats until the set stops changing (at most
//! [`LOCAL_ROUNDS`] rounds). Outliers therefore never reach the local correction, which would
//! otherwise bend towards them.
//!
//! Inliers reported: samples with `|r| < c` under the final model, for every kind (for Huber: the
//! samples in its quadratic zone). LWLR, `auto` and `raw` are refused with a clear error: LWLR has
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

/// Default residual scale, metres (1 cm: well above a good depth sensor's noise at grasping
/// range, well below the errors at edges and on glass).
pub const DEFAULT_THRESHOLD_M: f64 = 0.01;
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
    /// Residual scale c, metres (Huber's corner, Tukey's cut-off, RANSAC's inlier bound); > 0.
    pub threshold_m: f64,
    /// Most IRLS reweightings per phase, or most RANSAC hypotheses; ≥ 1.
    pub max_iterations: usize,
    /// Seed of RANSAC's minimal samples (also the start of Huber and Tukey IRLS).
    pub seed: u64,
}

impl Robust {
    /// `kind` with the defaults: [`DEFAULT_THRESHOLD_M`], [`DEFAULT_IRLS_ITERATIONS`] or
    /// [`DEFAULT_RANSAC_ITERATIONS`], seed 0.
    pub const fn new(kind: RobustKind) -> Self {
        Self {
            kind,
            threshold_m: DEFAULT_THRESHOLD_M,
            max_iterations: match kind {
                RobustKind::Ransac => DEFAULT_RANSAC_ITERATIONS,
                RobustKind::Huber | RobustKind::Tukey => DEFAULT_IRLS_ITERATIONS,
            },
            seed: 0,
        }
    }

    /// The same settings with residual scale `threshold_m` (metres).
    pub const fn with_threshold_m(self, threshold_m: f64) -> Self {
        Self {
            threshold_m,
            ..self
        }
    }

    /// The same settings with RANSAC seed `seed`.
    pub const fn with_seed(self, seed: u64) -> Self {
        Self { seed, ..self }
    }

    /// Checks the settings: `threshold_m` finite and > 0, `max_iterations` ≥ 1.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] naming the bad value.
    pub fn validate(&self) -> Result<()> {
        if !(self.threshold_m.is_finite() && self.threshold_m > 0.0) {
            return Err(CoreError::InvalidParameter(format!(
                "robust threshold must be a finite number of metres > 0, got {}",
                self.threshold_m
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
            c: self.threshold_m,
        };
        if self.kind == RobustKind::Ransac && ctx.samples.len() < base.minimal() {
            return Err(CoreError::TooFewSamples {
                method: base.ransac_name(),
                got: ctx.samples.len(),
                need: base.minimal(),
            });
        }
        targets.require(method.name(), method.min_samples())?;
        let (global, mut iterations) = match self.kind {
            RobustKind::Huber => self.irls(&ctx, base, false)?,
            RobustKind::Tukey => self.irls(&ctx, base, true)?,
            RobustKind::Ransac => self.ransac(&ctx, base)?,
        };
        let model = match local_cfg {
            None => global_model(global),
            Some((lbase, cfg)) => {
                // Start: inliers of the robust global fit, joined by those of the plain local
                // fit on all samples (where the scene departs from the global model by more than
                // c, only a local model can tell its samples from outliers).
                let mut inliers = ctx.inliers(|s| global.predict(s.u, s.v, s.pred));
                if let Ok(plain) = local::fit(targets, lbase, cfg) {
                    let plain = AlignmentModel::Local(Box::new(plain));
                    let more = ctx.inliers(|s| plain.predict_at(s.u, s.v, s.pred));
                    for (i, m) in inliers.iter_mut().zip(more) {
                        *i |= m;
                    }
                }
                let mut model = None;
                for _ in 0..LOCAL_ROUNDS {
                    let subset = SampleSet {
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
                        return Err(CoreError::TooFewSamples {
                            method: local_name(lbase),
                            got: subset.len(),
                            need: method.min_samples(),
                        });
                    }
                    let m = AlignmentModel::Local(Box::new(local::fit(&subset, lbase, cfg)?));
                    iterations += 1;
                    let next = ctx.inliers(|s| m.predict_at(s.u, s.v, s.pred));
                    model = Some(m);
                    if next == inliers {
                        break;
                    }
                    inliers = next;
                }
                model
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
            .copied()
            .filter(|r| r.abs() < self.threshold_m)
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
            method: method.name().to_string(),
            n_used: ctx.samples.len(),
            rms_residual_m: rms(&residuals, &depths),
            fit_time_s: start.elapsed().as_secs_f64(),
            robust: Some(RobustReport {
                kind: self.kind,
                threshold_m: self.threshold_m,
                inliers: in_r.len(),
                iterations,
                inlier_rms_residual_m: rms(&in_r, &in_r),
            }),
        };
        Ok((model, report))
    }

    /// Huber IRLS from a RANSAC start (least squares where RANSAC finds no fit); for Tukey, then
    /// Tukey IRLS from the Huber fit.
    fn irls(&self, ctx: &Ctx<'_>, base: Base, tukey: bool) -> Result<(GlobalFit, usize)> {
        let c = self.threshold_m;
        let start = Self {
            kind: RobustKind::Ransac,
            max_iterations: DEFAULT_RANSAC_ITERATIONS,
            ..*self
        };
        let mut model = match start.ransac(ctx, base) {
            Ok((m, _)) => m,
            Err(_) => base.fit(ctx.set, None)?,
        };
        let mut iterations = 0;
        let phases: &[bool] = if tukey { &[false, true] } else { &[false] };
        let mut weights = vec![1.0; ctx.samples.len()];
        for &is_tukey in phases {
            for _ in 0..self.max_iterations {
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
                        "{}: only {positive} of {} samples lie within {c} m of the fit; the \
                         threshold is too small for these data",
                        self.kind,
                        ctx.samples.len()
                    )));
                }
                iterations += 1;
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
                model = next;
                if moved <= IRLS_TOLERANCE_M {
                    break;
                }
            }
        }
        Ok((model, iterations))
    }

    /// RANSAC on the global model, then least squares on the consensus set.
    fn ransac(&self, ctx: &Ctx<'_>, base: Base) -> Result<(GlobalFit, usize)> {
        let n = ctx.samples.len();
        let m = base.minimal();
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed);
        let mut best: Option<(usize, f64, GlobalFit)> = None;
        let mut needed = self.max_iterations;
        let mut drawn = 0;
        let mut subset = SampleSet {
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
            let (count, ss) = ctx.consensus(&hyp);
            if best
                .as_ref()
                .is_none_or(|(bc, bss, _)| count > *bc || (count == *bc && ss < *bss))
            {
                best = Some((count, ss, hyp));
                let eps = count as f64 / n as f64;
                let p_good = eps.powi(m as i32);
                needed = if p_good >= 1.0 {
                    drawn
                } else if p_good <= 0.0 {
                    self.max_iterations
                } else {
                    let k = ((1.0 - RANSAC_CONFIDENCE).ln() / (1.0 - p_good).ln()).ceil();
                    (k.max(1.0) as usize).min(self.max_iterations)
                };
            }
        }
        let (mut count, _, mut model) = best.ok_or_else(|| {
            CoreError::Degenerate(format!(
                "ransac: none of {drawn} minimal samples of {m} gave a {} fit (constant ẑ or \
                 collinear pixels)",
                base.name()
            ))
        })?;
        let mut inliers = ctx.inliers(|s| model.predict(s.u, s.v, s.pred));
        for _ in 0..RANSAC_REFITS {
            let weights: Vec<f64> = inliers.iter().map(|&i| f64::from(u8::from(i))).collect();
            let Ok(refit) = base.fit(ctx.set, Some(&weights)) else {
                break;
            };
            let next = ctx.inliers(|s| refit.predict(s.u, s.v, s.pred));
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
        Ok((model, drawn))
    }
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
    /// Residual scale, metres.
    pub threshold_m: f64,
    /// Samples whose residual under the final model is below `threshold_m` (in metres).
    pub inliers: usize,
    /// IRLS reweightings (both phases for Tukey; the RANSAC start not counted) or RANSAC
    /// hypotheses drawn, plus one per inlier-set round of a local variant.
    pub iterations: usize,
    /// RMS residual over the inliers, metres.
    pub inlier_rms_residual_m: f64,
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

/// The samples, their space and the threshold.
struct Ctx<'a> {
    samples: &'a [Sample],
    set: &'a SampleSet,
    space: AlignSpace,
    c: f64,
}

impl Ctx<'_> {
    /// Ground-truth depth of a sample, metres.
    fn depth_m(&self, s: &Sample) -> f64 {
        self.space.depth_from_target(s.depth_m)
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
            AlignSpace::Depth => fitted_target - s.depth_m,
            AlignSpace::Inverse if fitted_target > 0.0 && fitted_target.is_finite() => {
                -(fitted_target - s.depth_m) / (fitted_target * fitted_target)
            }
            AlignSpace::Inverse => f64::INFINITY,
        }
    }

    /// `|r| < c` per sample under `predict` (fitted target value).
    fn inliers(&self, predict: impl Fn(&Sample) -> f64) -> Vec<bool> {
        self.samples
            .iter()
            .map(|s| self.residual_m(s, predict(s)).abs() < self.c)
            .collect()
    }

    /// Inlier count and sum of squared inlier residuals (m²) of a hypothesis.
    fn consensus(&self, g: &GlobalFit) -> (usize, f64) {
        let mut count = 0;
        let mut ss = 0.0;
        for s in self.samples {
            let r = self.residual_m(s, g.predict(s.u, s.v, s.pred));
            if r.abs() < self.c {
                count += 1;
                ss += r * r;
            }
        }
        (count, ss)
    }
}
