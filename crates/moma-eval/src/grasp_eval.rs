//! Grasp success by proxy (docs/method.md §8, the paper's §V-E table): calibrate as [`crate::protocol`]
//! does, align every evaluated frame, plan the top-1 grasp per trial on the aligned depth, and
//! execute it in imagination on the ground-truth depth of the same frame.
//!
//! A trial is one object region: an 8-connected component of the frame's mask with at least
//! [`GraspEvalConfig::min_object_px`] pixels (the whole frame without a mask); planning and scoring
//! use that component as the object mask. A trial where no grasp is found is a failure with that
//! reason. Rows `gt` (planned on the ground truth itself: the planner's own ceiling) and `sensor`
//! (planned on the frame's `raw_depth.png`, where the set has one) are always added; they do not
//! depend on the sampling seed and are run once.
//!
//! **Every number is a proxy for a robot trial, not a robot result**, and is made from simulated
//! predictions whenever the predictions are simulated; tables say so.

use std::collections::BTreeMap;

use std::sync::Arc;

use moma_core::align::robust::Robust;
use moma_core::normalise::NormalisedMap;
use moma_core::{DepthErrorModel, Mask, MetricDepth};
use moma_grasp::{
    DEFAULT_GRASP_DRAWS, DEFAULT_ROBUST_CANDIDATES, FailureReason, Grasp, GraspQuality,
    GraspRequest, MIN_TRIAL_COMPONENT_PX, ParallelConfig, Scene, SceneConfig, ScoreConfig,
    SuctionConfig, mask_components, plan_on_scene, planning_depth, rank, score_grasp,
    share_of_draws,
};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::data::LoadedSet;
use crate::error::{EvalError, Result};
use crate::protocol::{
    EvalConfig, PredictionSet, Prepared, check_calib_frame_counts, check_few_shot,
    few_shot_variant, variant_name,
};
use crate::realign::RealignSetup;
use crate::report::Table;

/// Which gripper a row is for.
pub use moma_grasp::GripperKind;

/// Settings of a grasp evaluation (the alignment settings are an [`EvalConfig`]).
#[derive(Debug, Clone, PartialEq)]
pub struct GraspEvalConfig {
    /// Alignment protocol: methods, normalisation (the first of `norms`; none: the
    /// predictions' kind's default), samples, seeds, ...
    pub eval: EvalConfig,
    /// Grippers, in table order.
    pub grippers: Vec<GripperKind>,
    /// Smallest mask component that counts as an object (trial), pixels (default 200).
    pub min_object_px: usize,
    /// Scene construction (support plane, objects without a mask).
    pub scene: SceneConfig,
    /// Proxy execution (friction μ, thresholds).
    pub score: ScoreConfig,
    /// Parallel-jaw planner settings.
    pub parallel: ParallelConfig,
    /// Suction planner settings.
    pub suction: SuctionConfig,
    /// Few-shot calibration frame counts (`moma eval --calib-frames`): rows `one-shot` /
    /// `few-shot-K`, every K scored on the frames after the largest; empty: the one-shot,
    /// robust and re-alignment variants of [`GraspEvalConfig::eval`].
    pub calib_frames: Vec<usize>,
    /// Grasp rankings evaluated, one block of rows each (rows of the `gt` and `sensor` depths
    /// plan with σ = 0: nominal).
    pub qualities: Vec<GraspQuality>,
    /// Depth draws per trial for the success probabilities.
    pub draws: usize,
    /// Planner candidates scored on the draws.
    pub candidates: usize,
    /// Robust ranking's tolerance on the share of successful draws ([`moma_grasp::rank`]); `None`:
    /// each gripper's default ([`moma_grasp::default_tie_tolerance`]).
    pub tie_tolerance: Option<f32>,
}

impl Default for GraspEvalConfig {
    fn default() -> Self {
        Self {
            eval: EvalConfig::default(),
            grippers: GripperKind::ALL.to_vec(),
            min_object_px: MIN_TRIAL_COMPONENT_PX,
            scene: SceneConfig::default(),
            score: ScoreConfig::default(),
            parallel: ParallelConfig::default(),
            suction: SuctionConfig::default(),
            calib_frames: Vec::new(),
            qualities: vec![GraspQuality::Robust],
            draws: DEFAULT_GRASP_DRAWS,
            candidates: DEFAULT_ROBUST_CANDIDATES,
            tie_tolerance: None,
        }
    }
}

/// One row of the success-rate table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GraspRow {
    /// Set name.
    pub set: String,
    /// Method name, or `gt` (planned on ground truth) / `sensor` (planned on raw sensor depth).
    pub method: String,
    /// Calibration variant, as `moma eval` labels it (`one-shot`, `few-shot-K`,
    /// `robust-<kind>`, `realign-anchors`, ...; `-` for `gt` and `sensor`).
    pub variant: String,
    /// Normalisation of the predictions, as `moma eval` names it (`minmax`, `minmax-unit`,
    /// `median`, `none`: the predictions' kind's default unless `--norm` says; `-` for `gt` and
    /// `sensor`).
    pub norm: String,
    /// How the grasp was chosen (`nominal`, `robust`).
    pub grasp_quality: GraspQuality,
    /// Gripper.
    pub gripper: GripperKind,
    /// Trials (object regions × evaluated frames × seeds; × 1 seed for `gt` and `sensor`).
    pub trials: usize,
    /// Successful top-1 grasps (proxy).
    pub successes: usize,
    /// successes / trials.
    pub success_rate: f64,
    /// Trials in which at least one of the planner's candidates (up to
    /// [`GraspEvalConfig::candidates`], the grasps the ranking chooses from) succeeds on the
    /// ground truth: the successes a perfect ranking of these candidates would reach. Below
    /// it, the ranking loses grasps; above it, the candidates do not hold one.
    pub best_of_candidates: usize,
    /// Failures by reason (`collision`, `no_grasp`, ...).
    pub failures: BTreeMap<String, usize>,
    /// Brier score of the top-1 grasps' `success_prob` against their proxy outcome (trials with
    /// a grasp that has a probability; `None` when none has).
    pub brier: Option<f64>,
    /// The Brier score of one constant forecast for the same grasps, their achieved success
    /// rate `r`: `r (1 − r)` ([`brier_base_rate`]). `brier` below it: `success_prob` tells
    /// the grasps that hold from those that do not better than one rate for all does.
    #[serde(default)]
    pub brier_base_rate: Option<f64>,
    /// Mean `success_prob` of those top-1 grasps (`None` when none has one).
    pub mean_success_prob: Option<f64>,
    /// Reliability table of `success_prob` (5 bins of predicted probability).
    pub reliability: Vec<ReliabilityBin>,
    /// The calibration frame's grasp check of every calibration of the row, summed
    /// ([`moma_grasp::grasp_check`], as `moma calibrate --grasp-check` runs it: the calibration
    /// frame aligned one-shot, planned without a mask, every grasp executed on its ground
    /// truth): what a cell would have been told at calibration time. `None` for `gt` and
    /// `sensor`.
    #[serde(default)]
    pub calibration_frame_check: Option<CheckSums>,
    /// Prediction source label (`SIMULATED …` for simulated predictions).
    pub source: String,
    /// Whether the depth the grasps were planned on came from simulated predictions.
    pub simulated: bool,
}

/// One bin of a reliability table: grasps whose predicted success probability lies in `bin`,
/// their mean prediction and their achieved (proxy) success rate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ReliabilityBin {
    /// `[lo, hi]` of the predicted probability (the last bin includes 1).
    pub bin: [f64; 2],
    /// Top-1 grasps in the bin.
    pub grasps: usize,
    /// Their mean predicted probability (`null` when empty).
    pub predicted: Option<f64>,
    /// Their achieved success rate (`null` when empty).
    pub achieved: Option<f64>,
}

/// Grasp checks summed over calibrations ([`GraspRow::calibration_frame_check`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct CheckSums {
    /// Grasps planned on the calibration frames' aligned depth.
    pub grasps: usize,
    /// Of those, the grasps that hold on the calibration frames' ground truth.
    pub successes: usize,
    /// Their mean `success_prob` (`null` without one).
    pub mean_success_prob: Option<f64>,
}

/// Grasp checks as they are summed ([`CheckSums`]).
#[derive(Default, Clone, Copy)]
struct CheckTally {
    /// Checks added.
    runs: usize,
    grasps: usize,
    successes: usize,
    /// Σ success_prob over the grasps that have one, and their number.
    prob_sum: f64,
    probs: usize,
}

impl CheckTally {
    /// One check; `None`: a check that could not plan (no grasps).
    fn add(&mut self, c: Option<&moma_grasp::GraspCheck>) {
        let grasps = c.map_or(0, |c| c.grasps);
        let prob = c.and_then(|c| c.mean_success_prob);
        self.merge(CheckTally {
            runs: 1,
            grasps,
            successes: c.map_or(0, |c| c.successes),
            prob_sum: prob.map_or(0.0, |p| p * grasps as f64),
            probs: prob.map_or(0, |_| grasps),
        });
    }

    fn merge(&mut self, o: CheckTally) {
        self.runs += o.runs;
        self.grasps += o.grasps;
        self.successes += o.successes;
        self.prob_sum += o.prob_sum;
        self.probs += o.probs;
    }

    fn sums(&self) -> Option<CheckSums> {
        (self.runs > 0).then(|| CheckSums {
            grasps: self.grasps,
            successes: self.successes,
            mean_success_prob: (self.probs > 0).then(|| self.prob_sum / self.probs as f64),
        })
    }
}

/// The `--json` contract: one object per (set, method, variant, grasp quality, gripper).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GraspJsonRow {
    /// Set name.
    pub set: String,
    /// Method (or `gt`, `sensor`).
    pub method: String,
    /// Calibration variant (as `moma eval --json`).
    pub variant: String,
    /// Normalisation (as `moma eval --json`'s `norm`; `-` for `gt` and `sensor`).
    pub norm: String,
    /// `nominal` or `robust`.
    pub grasp_quality: GraspQuality,
    /// `parallel` or `suction`.
    pub gripper: GripperKind,
    /// Trials.
    pub trials: usize,
    /// Successes.
    pub successes: usize,
    /// successes / trials.
    pub success_rate: f64,
    /// Trials where some candidate of the planner succeeds (what a perfect ranking reaches).
    pub best_of_candidates: usize,
    /// Brier score of `success_prob` (`null` without probabilities).
    pub brier: Option<f64>,
    /// Brier score of a constant forecast at the same grasps' achieved success rate (`null`
    /// without probabilities): what `brier` must be under for `success_prob` to carry
    /// information.
    pub brier_base_rate: Option<f64>,
    /// Reliability table.
    pub reliability: Vec<ReliabilityBin>,
    /// The calibration frame's grasp check (`null` for `gt` and `sensor`).
    pub calibration_frame_check: Option<CheckSums>,
}

impl From<&GraspRow> for GraspJsonRow {
    fn from(r: &GraspRow) -> Self {
        Self {
            set: r.set.clone(),
            method: r.method.clone(),
            variant: r.variant.clone(),
            norm: r.norm.clone(),
            grasp_quality: r.grasp_quality,
            brier: r.brier,
            brier_base_rate: r.brier_base_rate,
            reliability: r.reliability.clone(),
            calibration_frame_check: r.calibration_frame_check,
            gripper: r.gripper,
            trials: r.trials,
            successes: r.successes,
            success_rate: r.success_rate,
            best_of_candidates: r.best_of_candidates,
        }
    }
}

/// One trial: the object region of a frame.
struct Trial {
    frame: usize,
    mask: Option<Mask>,
}

/// Outcome counts of a list of trials.
#[derive(Default)]
struct Tally {
    trials: usize,
    successes: usize,
    /// Trials where some candidate succeeds on the ground truth.
    best_of: usize,
    failures: BTreeMap<String, usize>,
    /// (predicted success probability, success) of the top-1 grasps that have one.
    probs: Vec<(f64, bool)>,
    /// The calibration frames' grasp checks.
    check: CheckTally,
}

/// One trial's result: the top-1 grasp's proxy outcome and its success probability.
type TrialOutcome = (std::result::Result<(), FailureReason>, Option<f32>);

impl Tally {
    fn add(&mut self, (outcome, prob): TrialOutcome) {
        self.trials += 1;
        if let Some(p) = prob {
            self.probs.push((f64::from(p), outcome.is_ok()));
        }
        match outcome {
            Ok(()) => self.successes += 1,
            Err(r) => *self.failures.entry(r.to_string()).or_default() += 1,
        }
    }

    fn merge(&mut self, other: Tally) {
        self.trials += other.trials;
        self.successes += other.successes;
        self.best_of += other.best_of;
        self.probs.extend(other.probs);
        self.check.merge(other.check);
        for (k, v) in other.failures {
            *self.failures.entry(k).or_default() += v;
        }
    }

    fn brier(&self) -> Option<f64> {
        (!self.probs.is_empty()).then(|| {
            self.probs
                .iter()
                .map(|&(p, s)| (p - f64::from(u8::from(s))).powi(2))
                .sum::<f64>()
                / self.probs.len() as f64
        })
    }

    fn reliability(&self) -> Vec<ReliabilityBin> {
        reliability_table(&self.probs)
    }
}

/// The Brier score of the constant forecast `r` for every one of `probs`' outcomes, `r` their
/// achieved success rate: `r (1 − r)` (`None` for no outcomes). It is the Brier score of the
/// best forecast that cannot tell one grasp from another, so a `success_prob` whose Brier
/// score is not under it carries no information on which grasps hold (Murphy's decomposition:
/// Brier = reliability − resolution + this uncertainty term).
pub fn brier_base_rate(probs: &[(f64, bool)]) -> Option<f64> {
    (!probs.is_empty()).then(|| {
        let r = probs.iter().filter(|(_, s)| *s).count() as f64 / probs.len() as f64;
        r * (1.0 - r)
    })
}

/// Bins of the reliability table.
pub const RELIABILITY_BINS: usize = 5;

/// The reliability table of `(predicted probability, success)` pairs: [`RELIABILITY_BINS`]
/// equal bins of [0, 1], the last closed.
pub fn reliability_table(probs: &[(f64, bool)]) -> Vec<ReliabilityBin> {
    // Edges as b / 5, not b · 0.2: the JSON then reads [0.4, 0.6], not [0.4, 0.6000000000000001].
    let edge = |b: usize| b as f64 / RELIABILITY_BINS as f64;
    (0..RELIABILITY_BINS)
        .map(|b| {
            let (lo, hi) = (edge(b), edge(b + 1));
            let inside: Vec<&(f64, bool)> = probs
                .iter()
                .filter(|(p, _)| *p >= lo && (*p < hi || (b + 1 == RELIABILITY_BINS && *p <= 1.0)))
                .collect();
            let n = inside.len();
            ReliabilityBin {
                bin: [lo, hi],
                grasps: n,
                predicted: (n > 0).then(|| inside.iter().map(|(p, _)| p).sum::<f64>() / n as f64),
                achieved: (n > 0)
                    .then(|| inside.iter().filter(|(_, s)| *s).count() as f64 / n as f64),
            }
        })
        .collect()
}

/// A depth to plan on for one frame: metres and its error model (`None`: planned as exact).
struct Planned<'a> {
    depth: &'a MetricDepth,
    error_model: Option<DepthErrorModel>,
    /// Seed of the planner's sampling and of the depth draws.
    seed: u64,
}

/// The request of `config`'s planner settings for `gripper` with `error_model` and `seed` (top
/// 10, the default ranking of the model).
fn base_request(
    gripper: GripperKind,
    error_model: Option<DepthErrorModel>,
    seed: u64,
    config: &GraspEvalConfig,
) -> GraspRequest {
    let mut request = GraspRequest::new(gripper.default_gripper()).with_error_model(error_model);
    request.seed = seed;
    request.draws = config.draws;
    request.candidates = config.candidates;
    request.scene = config.scene;
    request.parallel = config.parallel.clone();
    request.suction = config.suction;
    request.score = config.score;
    if let Some(t) = config.tie_tolerance {
        request.tie_tolerance = t;
    }
    request
}

/// The grasp checks of a set's calibration frames ([`moma_grasp::grasp_check`] as `moma
/// calibrate --grasp-check` runs it: no mask), each computed once. A frame's maskless truth
/// scene is built once, and a check is reused when the same frame comes again with the same
/// aligned depth and error model (bit for bit), gripper, ranking and seed: the one-shot and the
/// re-aligned variants of a calibration align its frame alike, but nothing assumes they do.
#[derive(Default)]
struct CheckCache {
    /// Truth scenes by frame index (`None`: cannot be built, e.g. no support plane).
    truth: BTreeMap<usize, Option<Scene>>,
    /// The distinct aligned calibration frames met: frame index, depth, error model.
    aligned: Vec<(usize, MetricDepth, Option<DepthErrorModel>)>,
    /// Checks by (index into `aligned`, gripper, ranking, seed).
    checks: BTreeMap<(usize, GripperKind, GraspQuality, u64), Option<moma_grasp::GraspCheck>>,
}

/// Whether two depth maps are the same bit for bit (NaN included, which `==` never is).
fn same_bits(a: &MetricDepth, b: &MetricDepth) -> bool {
    a.depth_m.dim() == b.depth_m.dim()
        && a.depth_m
            .iter()
            .zip(b.depth_m.iter())
            .all(|(x, y)| x.to_bits() == y.to_bits())
}

impl CheckCache {
    /// The check of calibration frame `frame` (its aligned depth and error model) for
    /// `gripper`, ranked by `quality` where the model allows it. `None` where the frame's scenes
    /// cannot be built (no valid depth, no support plane): a check without grasps.
    #[allow(clippy::too_many_arguments)]
    fn check(
        &mut self,
        set: &LoadedSet,
        frame: usize,
        aligned: &(MetricDepth, Option<DepthErrorModel>),
        gripper: GripperKind,
        quality: GraspQuality,
        seed: u64,
        config: &GraspEvalConfig,
    ) -> Option<moma_grasp::GraspCheck> {
        let (depth, model) = aligned;
        let a = match self
            .aligned
            .iter()
            .position(|(f, d, m)| *f == frame && m == model && same_bits(d, depth))
        {
            Some(a) => a,
            None => {
                self.aligned.push((frame, depth.clone(), model.clone()));
                self.aligned.len() - 1
            }
        };
        if let Some(check) = self.checks.get(&(a, gripper, quality, seed)) {
            return check.clone();
        }
        let mut request = base_request(gripper, model.clone(), seed, config);
        if model.is_some() {
            request.quality = quality;
        }
        // built as `grasp_check` builds it, from the request's scene settings
        let truth = self.truth.entry(frame).or_insert_with(|| {
            Scene::build(&set.frames[frame].gt, &set.intrinsics, None, &request.scene).ok()
        });
        let check = truth.as_ref().and_then(|t| {
            moma_grasp::grasp_check_on(depth, t, &set.intrinsics, None, &request).ok()
        });
        self.checks
            .insert((a, gripper, quality, seed), check.clone());
        check
    }
}

/// Plans on `planned` (object `mask`) through [`plan_on_scene`] (the path of `moma grasp`),
/// and executes the top-1 grasp of each ranking in `qualities` on the ground-truth scene.
/// Also returns whether any of the planner's candidates succeeds there
/// ([`GraspRow::best_of_candidates`]).
fn run_trial(
    planned: &Planned<'_>,
    gt_scene: &Scene,
    set: &LoadedSet,
    mask: Option<&Mask>,
    gripper: GripperKind,
    qualities: &[GraspQuality],
    config: &GraspEvalConfig,
) -> Result<(Vec<TrialOutcome>, bool)> {
    let no_grasp = || {
        (
            vec![(Err(FailureReason::NoGrasp), None); qualities.len()],
            false,
        )
    };
    let mut request = base_request(gripper, planned.error_model.clone(), planned.seed, config);
    request.quality = GraspQuality::Nominal; // every candidate, in the planner's order
    // every candidate, also without an error model (the top-1 is the same: the planner keeps
    // grasps greedily in its own order), for the best of the candidates
    request.top_k = config.candidates;
    // the path of `plan_grasps`: the scene of the request's planning depth
    let depth = planning_depth(planned.depth, &set.intrinsics, &request);
    let scene = match Scene::build(&depth, &set.intrinsics, mask, &config.scene) {
        Ok(s) => s,
        // the planning depth may hold no valid pixel in the object region: no grasp
        Err(_) => return Ok(no_grasp()),
    };
    let outcome = plan_on_scene(&scene, &depth, &set.intrinsics, &request)
        .map_err(|e| EvalError::InvalidParameter(format!("grasp planner: {e}")))?;
    if outcome.grasps.is_empty() {
        return Ok(no_grasp());
    }
    let candidates: Vec<(Grasp, f32)> = outcome
        .grasps
        .iter()
        // ranked by the share of successful draws, as `plan_on_scene` ranks
        .map(|g| {
            let share = g.success_prob().map(|p| share_of_draws(p, request.draws));
            (*g, share.unwrap_or(f32::NAN))
        })
        .collect();
    let execute = |grasp: &Grasp| {
        score_grasp(gt_scene, grasp, &request.gripper, &config.score)
            .map_err(|e| EvalError::InvalidParameter(format!("grasp scoring: {e}")))
    };
    // the top-1 grasp of each ranking, executed once (the best of the candidates reuses it)
    let mut tops: Vec<Grasp> = Vec::with_capacity(qualities.len());
    let outcomes: Vec<TrialOutcome> = qualities
        .iter()
        .map(|&q| {
            let mut ranked = candidates.clone();
            // the request's: --grasp-tie-tolerance, else the gripper's default
            rank(&mut ranked, q, request.tie_tolerance);
            let grasp = ranked[0].0;
            tops.push(grasp);
            let score = execute(&grasp)?;
            let result = match score.failure {
                None if score.success => Ok(()),
                Some(r) => Err(r),
                None => Err(FailureReason::NoGrasp),
            };
            Ok((result, grasp.success_prob()))
        })
        .collect::<Result<_>>()?;
    let mut any_succeeds = outcomes.iter().any(|(r, _)| r.is_ok());
    for (g, _) in &candidates {
        if any_succeeds {
            break;
        }
        if !tops.contains(g) {
            any_succeeds = execute(g)?.success;
        }
    }
    Ok((outcomes, any_succeeds))
}

/// Ground-truth scenes of every (evaluated frame, trial) pair, built once.
fn gt_scenes(
    set: &LoadedSet,
    trials: &[Trial],
    config: &GraspEvalConfig,
) -> Result<Vec<Option<Scene>>> {
    trials
        .par_iter()
        .map(|t| {
            let f = &set.frames[t.frame];
            // a trial whose ground truth holds no depth cannot be scored: reported as no grasp
            Ok(Scene::build(&f.gt, &set.intrinsics, t.mask.as_ref(), &config.scene).ok())
        })
        .collect()
}

/// How well the σ of the error model covers the true error: pixels where |aligned − truth| ≤
/// σ and ≤ 2σ, over all pixels, inside the object masks, and within 5 px of a depth edge of the
/// ground truth.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CoverageRow {
    /// Set name.
    pub set: String,
    /// Method.
    pub method: String,
    /// Calibration variant.
    pub variant: String,
    /// `all`, `masks` or `edges`.
    pub region: String,
    /// Pixels with an aligned depth, a truth and a σ (over frames and seeds).
    pub pixels: usize,
    /// Share within ±1σ (a Gaussian: 0.683).
    pub within_1sigma: f64,
    /// Share within ±2σ (a Gaussian: 0.954).
    pub within_2sigma: f64,
    /// Whether the predictions were simulated.
    pub simulated: bool,
}

/// Counts of σ coverage in the three regions.
#[derive(Default, Clone, Copy)]
struct Coverage {
    /// [all, masks, edges] × (pixels, within 1σ, within 2σ)
    counts: [[usize; 3]; 3],
}

/// Pixels within this distance of a ground-truth depth edge count as "near an edge".
const EDGE_DISTANCE_PX: u32 = 5;

impl Coverage {
    /// The pixels within [`EDGE_DISTANCE_PX`] of a depth discontinuity of the ground truth `gt`
    /// ([`moma_core::sampling::near_depth_edges`]: neighbours that jump by more than 3 % of the
    /// depth, or a hole): computed once per frame, shared by every seed, method and variant.
    /// (A depth range above 10 mm in the 11 × 11 window, the earlier rule, also took slanted
    /// surfaces: 85 % of m2t2-table's pixels, its whole table seen at a grazing angle.)
    fn edge_band(gt: &MetricDepth) -> ndarray::Array2<bool> {
        moma_core::sampling::near_depth_edges(gt, EDGE_DISTANCE_PX)
    }

    fn add(
        &mut self,
        aligned: &MetricDepth,
        sigma: &ndarray::Array2<f32>,
        gt: &MetricDepth,
        mask: Option<&Mask>,
        edges: &ndarray::Array2<bool>,
    ) {
        let w = aligned.depth_m.ncols();
        for (k, ((&a, &s), &t)) in aligned
            .depth_m
            .iter()
            .zip(sigma.iter())
            .zip(gt.depth_m.iter())
            .enumerate()
        {
            if !(moma_core::is_valid_depth(a) && moma_core::is_valid_depth(t) && s.is_finite()) {
                continue;
            }
            let e = (a - t).abs();
            let (v, u) = (k / w, k % w);
            let regions = [true, mask.is_some_and(|m| m.data()[[v, u]]), edges[[v, u]]];
            for (r, inside) in regions.into_iter().enumerate() {
                if inside {
                    let c = &mut self.counts[r];
                    c[0] += 1;
                    c[1] += usize::from(e <= s);
                    c[2] += usize::from(e <= 2.0 * s);
                }
            }
        }
    }

    fn rows(&self, set: &str, method: &str, variant: &str, simulated: bool) -> Vec<CoverageRow> {
        ["all", "masks", "edges"]
            .iter()
            .enumerate()
            .filter(|(r, _)| self.counts[*r][0] > 0)
            .map(|(r, name)| {
                let c = self.counts[r];
                CoverageRow {
                    set: set.into(),
                    method: method.into(),
                    variant: variant.into(),
                    region: (*name).into(),
                    pixels: c[0],
                    within_1sigma: c[1] as f64 / c[0] as f64,
                    within_2sigma: c[2] as f64 / c[0] as f64,
                    simulated,
                }
            })
            .collect()
    }
}

/// What one evaluated variant is: its label, calibration frames, robust fit or re-alignment.
enum VariantSpec {
    /// Least-squares (or robust) calibration on `calib` frames.
    Plain {
        name: String,
        calib: Vec<usize>,
        robust: Option<Robust>,
    },
    /// One-shot calibration with per-frame re-alignment at brightness β.
    Realign { beta: f64 },
}

/// The results of one set: success rows and σ-coverage rows.
#[derive(Debug, Clone, Default)]
pub struct GraspEvalResult {
    /// Success-rate rows.
    pub rows: Vec<GraspRow>,
    /// σ-coverage rows of the error models.
    pub coverage: Vec<CoverageRow>,
}

/// Evaluates one set: rows for every (method, variant, grasp quality, gripper), plus `gt` and
/// (with raw depth) `sensor`. The variants are `moma eval`'s, with its labels: one-shot,
/// `robust-<kind>` ([`EvalConfig::robust`](crate::protocol::EvalConfig::robust)),
/// `realign-anchors[-bβ]` ([`EvalConfig::realign`](crate::protocol::EvalConfig::realign)), or
/// with [`GraspEvalConfig::calib_frames`] `one-shot` / `few-shot-K` (scored on the frames after
/// the largest K; not combined with the others, as in `moma eval`). The depth of each variant
/// comes from the library calls `moma eval` scores; grasps from [`plan_on_scene`], the path of
/// `moma grasp`, with the frame's error model ([`Calibration::frame_error_model`]).
///
/// # Errors
/// Bad input (see [`Prepared::new`]), alignment errors, an invalid planner configuration, more
/// than one normalisation, a few-shot request the set cannot serve.
pub fn grasp_evaluate(
    set: &LoadedSet,
    preds: &PredictionSet,
    config: &GraspEvalConfig,
) -> Result<GraspEvalResult> {
    if config.min_object_px == 0 {
        return Err(EvalError::InvalidParameter(
            "the smallest object region must be at least 1 pixel".into(),
        ));
    }
    if config.eval.norms.len() > 1 {
        return Err(EvalError::InvalidParameter(
            "the grasp evaluation plans with one normalisation: more than one (--norm) is not \
             supported here (use `moma eval` for it)"
                .into(),
        ));
    }
    if config.qualities.is_empty() {
        return Err(EvalError::InvalidParameter(
            "give at least one grasp quality (nominal, robust)".into(),
        ));
    }
    if config.draws == 0 {
        return Err(EvalError::InvalidParameter(
            "the number of depth draws must be at least 1".into(),
        ));
    }
    let k_max = if config.calib_frames.is_empty() {
        None
    } else {
        let k = check_calib_frame_counts(&config.calib_frames)?;
        check_few_shot(set, &config.eval, k)?;
        Some(k)
    };
    let source = match config.eval.gt_outliers {
        Some(f) => format!(
            "{}; calibrated on ground truth with {:.1} % SIMULATED outliers",
            preds.label,
            100.0 * f
        ),
        None => preds.label.clone(),
    };
    let prep = Prepared::new(set, preds, &config.eval)?;
    prep.require_fixed_camera("grasp evaluation")?;
    let eval_idx = match k_max {
        Some(k) => (k..set.frames.len()).collect(),
        None => prep.eval_indices(),
    };
    let mut trials = Vec::new();
    for &i in &eval_idx {
        match &set.frames[i].mask {
            Some(m) => trials.extend(mask_components(m, config.min_object_px).into_iter().map(
                |c| Trial {
                    frame: i,
                    mask: Some(c),
                },
            )),
            None => trials.push(Trial {
                frame: i,
                mask: None,
            }),
        }
    }
    if trials.is_empty() {
        return Err(EvalError::NoGraspTrials {
            set: set.name.clone(),
            min_object_px: config.min_object_px,
            frames: eval_idx.len(),
        });
    }
    let gt = gt_scenes(set, &trials, config)?;
    let edge_bands: Vec<Option<ndarray::Array2<bool>>> = (0..set.frames.len())
        .into_par_iter()
        .map(|i| {
            eval_idx
                .contains(&i)
                .then(|| Coverage::edge_band(&set.frames[i].gt))
        })
        .collect();
    let norm0 = prep.first_norm();
    let seeds: Vec<u64> = (0..config.eval.seeds as u64)
        .map(|s| config.eval.seed_base + s)
        .collect();
    let mut out = GraspEvalResult::default();
    let row = |method: String,
               variant: String,
               norm: &str,
               quality: GraspQuality,
               gripper: GripperKind,
               t: Tally,
               source: &str,
               simulated: bool| GraspRow {
        set: set.name.clone(),
        method,
        variant,
        norm: norm.to_string(),
        grasp_quality: quality,
        gripper,
        success_rate: if t.trials > 0 {
            t.successes as f64 / t.trials as f64
        } else {
            f64::NAN
        },
        trials: t.trials,
        successes: t.successes,
        best_of_candidates: t.best_of,
        brier: t.brier(),
        brier_base_rate: brier_base_rate(&t.probs),
        mean_success_prob: (!t.probs.is_empty())
            .then(|| t.probs.iter().map(|p| p.0).sum::<f64>() / t.probs.len() as f64),
        reliability: t.reliability(),
        calibration_frame_check: t.check.sums(),
        failures: t.failures,
        source: source.to_string(),
        simulated,
    };
    // `depths[i]`: what is planned on for frame i (None: nothing to plan on); one tally per
    // quality
    let tally_on = |depths: &[Option<Planned<'_>>],
                    gripper: GripperKind,
                    qualities: &[GraspQuality]|
     -> Result<Vec<Tally>> {
        let outcomes: Vec<(Vec<TrialOutcome>, bool)> = trials
            .par_iter()
            .zip(&gt)
            .map(|(t, g)| {
                let (Some(g), Some(d)) = (g, depths[t.frame].as_ref()) else {
                    return Ok((
                        vec![(Err(FailureReason::NoGrasp), None); qualities.len()],
                        false,
                    ));
                };
                run_trial(d, g, set, t.mask.as_ref(), gripper, qualities, config)
            })
            .collect::<Result<_>>()?;
        let mut tallies: Vec<Tally> = qualities.iter().map(|_| Tally::default()).collect();
        for (o, any_succeeds) in outcomes {
            for (k, r) in o.into_iter().enumerate() {
                tallies[k].add(r);
                tallies[k].best_of += usize::from(any_succeeds);
            }
        }
        Ok(tallies)
    };
    let mut checks = CheckCache::default();
    for m in &config.eval.methods {
        let method = prep.method(m);
        let norm = prep.normalisation_for(&method, norm0);
        let mut variants: Vec<VariantSpec> = Vec::new();
        match k_max {
            Some(_) => {
                for &k in &config.calib_frames {
                    variants.push(VariantSpec::Plain {
                        name: few_shot_variant(k),
                        calib: (0..k).collect(),
                        robust: None,
                    });
                }
            }
            None => {
                variants.push(VariantSpec::Plain {
                    name: variant_name(None),
                    calib: vec![prep.calib],
                    robust: None,
                });
                for r in config
                    .eval
                    .robust
                    .iter()
                    .filter(|r| r.check_method(&method).is_ok())
                {
                    variants.push(VariantSpec::Plain {
                        name: variant_name(Some(r)),
                        calib: vec![prep.calib],
                        robust: Some(*r),
                    });
                }
                if let Some(r) = &config.eval.realign {
                    for &beta in &r.brightness {
                        crate::realign::check_brightness(beta, r.brightness_response)?;
                        variants.push(VariantSpec::Realign { beta });
                    }
                }
            }
        }
        for variant in &variants {
            let (name, setup) = match variant {
                VariantSpec::Plain { name, .. } => (name.clone(), None),
                VariantSpec::Realign { beta } => {
                    let r = config.eval.realign.as_ref().ok_or_else(|| {
                        EvalError::InvalidParameter("re-alignment settings missing".into())
                    })?;
                    (
                        crate::realign::variant_name(*beta),
                        Some(RealignSetup::new(&prep, &norm, r, *beta)?),
                    )
                }
            };
            let maps = match &setup {
                Some(s) => Arc::clone(&s.maps),
                None => prep.normalised_all(&norm)?,
            };
            let mut per_gq: Vec<Vec<Tally>> = config
                .grippers
                .iter()
                .map(|_| config.qualities.iter().map(|_| Tally::default()).collect())
                .collect();
            let mut coverage = Coverage::default();
            for &seed in &seeds {
                let mut frames: Vec<Option<(MetricDepth, Option<DepthErrorModel>)>> =
                    vec![None; set.frames.len()];
                // the calibration frame (the first of several) aligned one-shot, for its check
                let one_shot = |cal: &moma_core::Calibration, i: usize| -> Result<_> {
                    Ok((
                        i,
                        (prep.aligned(cal, &maps[i], i)?, cal.frame_error_model(None)),
                    ))
                };
                let calib_frame = match (variant, &setup) {
                    (VariantSpec::Plain { calib, robust, .. }, _) => {
                        let regions = prep.sample_regions(calib);
                        let inputs: Vec<(usize, &NormalisedMap, Option<&Mask>)> = calib
                            .iter()
                            .zip(&regions)
                            .map(|(&i, r)| (i, &maps[i], r.as_ref()))
                            .collect();
                        let cal = prep.calibrate_on(
                            &method,
                            &norm,
                            &inputs,
                            config.eval.samples,
                            seed,
                            robust.as_ref(),
                        )?;
                        for &i in &eval_idx {
                            let (d, _) = prep.score(&cal, &maps[i], i)?;
                            frames[i] = Some((d, cal.frame_error_model(None)));
                        }
                        one_shot(&cal, calib[0])?
                    }
                    (VariantSpec::Realign { .. }, Some(s)) => {
                        let cal = s.calibrate(&prep, &method, &norm, config.eval.samples, seed)?;
                        for &i in &eval_idx {
                            let (d, report) = s.realign_frame(&prep, &cal, i, seed)?;
                            frames[i] = Some((d, cal.frame_error_model(Some(&report))));
                        }
                        one_shot(&cal, prep.calib)?
                    }
                    (VariantSpec::Realign { .. }, None) => unreachable!("set up above"),
                };
                for &i in &eval_idx {
                    if let (Some((d, Some(model))), Some(edges)) = (&frames[i], &edge_bands[i]) {
                        coverage.add(
                            d,
                            &model.sigma_map(d),
                            &set.frames[i].gt,
                            set.frames[i].mask.as_ref(),
                            edges,
                        );
                    }
                }
                let depths: Vec<Option<Planned<'_>>> = frames
                    .iter()
                    .map(|f| {
                        f.as_ref().map(|(depth, model)| Planned {
                            depth,
                            error_model: model.clone(),
                            seed,
                        })
                    })
                    .collect();
                for (k, &g) in config.grippers.iter().enumerate() {
                    for (q, t) in tally_on(&depths, g, &config.qualities)?
                        .into_iter()
                        .enumerate()
                    {
                        per_gq[k][q].merge(t);
                    }
                    for (q, &quality) in config.qualities.iter().enumerate() {
                        let (c0, aligned) = &calib_frame;
                        let check = checks.check(set, *c0, aligned, g, quality, seed, config);
                        per_gq[k][q].check.add(check.as_ref());
                    }
                }
            }
            for (k, &g) in config.grippers.iter().enumerate() {
                for (q, &quality) in config.qualities.iter().enumerate() {
                    out.rows.push(row(
                        method.to_string(),
                        name.clone(),
                        norm.method.name(),
                        quality,
                        g,
                        std::mem::take(&mut per_gq[k][q]),
                        &source,
                        preds.simulated,
                    ));
                }
            }
            out.coverage.extend(coverage.rows(
                &set.name,
                &method.to_string(),
                &name,
                preds.simulated,
            ));
        }
    }
    let nominal = [GraspQuality::Nominal];
    let gt_depths: Vec<Option<Planned<'_>>> = set
        .frames
        .iter()
        .map(|f| {
            Some(Planned {
                depth: &f.gt,
                error_model: None,
                seed: config.eval.seed_base,
            })
        })
        .collect();
    for &g in &config.grippers {
        let t = tally_on(&gt_depths, g, &nominal)?;
        for t in t {
            out.rows.push(row(
                "gt".into(),
                "-".into(),
                "-",
                GraspQuality::Nominal,
                g,
                t,
                "ground-truth depth",
                false,
            ));
        }
    }
    if eval_idx.iter().any(|&i| set.frames[i].raw_depth.is_some()) {
        let raw: Vec<Option<Planned<'_>>> = set
            .frames
            .iter()
            .map(|f| {
                f.raw_depth.as_ref().map(|depth| Planned {
                    depth,
                    error_model: None,
                    seed: config.eval.seed_base,
                })
            })
            .collect();
        for &g in &config.grippers {
            for t in tally_on(&raw, g, &nominal)? {
                out.rows.push(row(
                    "sensor".into(),
                    "-".into(),
                    "-",
                    GraspQuality::Nominal,
                    g,
                    t,
                    "raw sensor depth",
                    false,
                ));
            }
        }
    }
    Ok(out)
}

/// The success-rate table (proxy). Title says "proxy" and, for simulated predictions,
/// "SIMULATED predictions".
pub fn grasp_table(rows: &[GraspRow]) -> Table {
    let simulated = rows.iter().any(|r| r.simulated);
    let sources: Vec<String> = {
        let mut s: Vec<String> = rows
            .iter()
            .filter(|r| r.method != "gt" && r.method != "sensor")
            .map(|r| r.source.clone())
            .collect();
        s.dedup();
        s
    };
    let title = format!(
        "{}grasp success by PROXY (top-1 grasp planned on the method's depth, executed on the \
         ground-truth depth; docs/grasping.md) — not robot trials; predictions: {}",
        if simulated {
            "SIMULATED predictions — "
        } else {
            ""
        },
        sources.join(", ")
    );
    Table {
        title,
        headers: [
            "set",
            "method",
            "variant",
            "grasps",
            "gripper",
            "trials",
            "successes",
            "success rate",
            "best of candidates",
            "mean success_prob",
            "Brier",
            "Brier of the base rate",
            "calibration frame check",
            "failures",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect(),
        rows: rows
            .iter()
            .map(|r| {
                vec![
                    r.set.clone(),
                    r.method.to_uppercase(),
                    r.variant.clone(),
                    r.grasp_quality.to_string(),
                    r.gripper.to_string(),
                    r.trials.to_string(),
                    r.successes.to_string(),
                    format!("{:.0} %", 100.0 * r.success_rate),
                    format!(
                        "{:.0} %",
                        100.0 * r.best_of_candidates as f64 / r.trials.max(1) as f64
                    ),
                    r.mean_success_prob
                        .map_or("-".into(), |p| format!("{:.0} %", 100.0 * p)),
                    brier_cell(r.brier),
                    brier_cell(r.brier_base_rate),
                    r.calibration_frame_check.map_or("-".into(), |c| {
                        let p = c
                            .mean_success_prob
                            .map_or(String::new(), |p| format!(" (p {p:.2})"));
                        format!("{} / {}{p}", c.successes, c.grasps)
                    }),
                    r.failures
                        .iter()
                        .map(|(k, v)| format!("{k} {v}"))
                        .collect::<Vec<_>>()
                        .join(", "),
                ]
            })
            .collect(),
    }
}

/// A Brier score's table cell.
fn brier_cell(b: Option<f64>) -> String {
    b.map_or("-".into(), |b| format!("{b:.3}"))
}

/// The reliability tables: one row per (set, method, variant, grasps, gripper) with
/// probabilities, "predicted → achieved (n)" per bin.
pub fn reliability_table_of(rows: &[GraspRow]) -> Table {
    let simulated = rows.iter().any(|r| r.simulated);
    let mut headers: Vec<String> = [
        "set",
        "method",
        "variant",
        "grasps",
        "gripper",
        "Brier",
        "Brier of the base rate",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let w = 1.0 / RELIABILITY_BINS as f64;
    headers.extend(
        (0..RELIABILITY_BINS).map(|b| format!("p {:.1}–{:.1}", b as f64 * w, (b + 1) as f64 * w)),
    );
    Table {
        title: format!(
            "{}reliability of success_prob: mean predicted → achieved proxy success (top-1 grasps)",
            if simulated {
                "SIMULATED predictions — "
            } else {
                ""
            }
        ),
        headers,
        rows: rows
            .iter()
            .filter(|r| r.brier.is_some())
            .map(|r| {
                let mut v = vec![
                    r.set.clone(),
                    r.method.to_uppercase(),
                    r.variant.clone(),
                    r.grasp_quality.to_string(),
                    r.gripper.to_string(),
                    brier_cell(r.brier),
                    brier_cell(r.brier_base_rate),
                ];
                v.extend(
                    r.reliability
                        .iter()
                        .map(|b| match (b.predicted, b.achieved) {
                            (Some(p), Some(a)) => format!("{p:.2} → {a:.2} ({})", b.grasps),
                            _ => "-".into(),
                        }),
                );
                v
            })
            .collect(),
    }
}

/// The σ-coverage table of the error models.
pub fn coverage_table(rows: &[CoverageRow]) -> Table {
    let simulated = rows.iter().any(|r| r.simulated);
    Table {
        title: format!(
            "{}error model: share of true errors within ±1σ / ±2σ (a Gaussian: 68 % / 95 %)",
            if simulated {
                "SIMULATED predictions — "
            } else {
                ""
            }
        ),
        headers: [
            "set",
            "method",
            "variant",
            "region",
            "pixels",
            "within 1σ",
            "within 2σ",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect(),
        rows: rows
            .iter()
            .map(|r| {
                vec![
                    r.set.clone(),
                    r.method.to_uppercase(),
                    r.variant.clone(),
                    r.region.clone(),
                    r.pixels.to_string(),
                    format!("{:.1} %", 100.0 * r.within_1sigma),
                    format!("{:.1} %", 100.0 * r.within_2sigma),
                ]
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The check cache's key: maps equal bit for bit, NaN (no depth) included, which `==` on
    /// `f32` never calls equal; any other value, a sign of zero or another size is a new map.
    #[test]
    fn depth_maps_are_the_same_bit_for_bit_or_not_at_all() {
        let a = MetricDepth::new(ndarray::array![[0.5, f32::NAN], [0.7, 0.0]]);
        assert!(same_bits(&a, &a.clone()));
        assert_ne!(
            a,
            a.clone(),
            "NaN makes `==` false: the reason for same_bits"
        );
        let mut b = a.clone();
        b.depth_m[[1, 0]] = 0.7 + f32::EPSILON;
        assert!(!same_bits(&a, &b));
        let mut c = a.clone();
        c.depth_m[[1, 1]] = -0.0;
        assert!(!same_bits(&a, &c));
        let d = MetricDepth::new(ndarray::array![[0.5, f32::NAN, 0.7, 0.0]]);
        assert!(!same_bits(&a, &d));
    }
}
