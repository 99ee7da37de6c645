//! The one path from a depth map to grasps ([`plan_grasps`]), with Dex-Net's *robust* grasp
//! quality: the success probability of a grasp under the depth's error model.
//!
//! The planner ([`plan_parallel`] / [`plan_suction`]) proposes up to
//! [`GraspRequest::candidates`] grasps on the planning depth. With an error model
//! ([`moma_core::DepthErrorModel`]), [`GraspRequest::draws`] depth maps are drawn from it
//! around the planning depth (seeded: draw k of seed s is the same on every run and thread
//! count) in the region around the candidates, a scene is made of each with the planning
//! scene's support plane and objects ([`Scene::with_depth_in`]), and every
//! candidate is executed on every drawn scene with the scorer's rules ([`score_grasp`], the
//! rules of the proxy evaluation, unchanged). [`GraspQuality::Robust`] ranks by the share of
//! draws on which a candidate succeeds: the grasps within [`GraspRequest::tie_tolerance`] of the
//! best share first, in the planner's order, then the others by share ([`rank`]);
//! [`GraspQuality::Nominal`] keeps the planner's order. Both report as `success_prob` the
//! posterior mean of the success probability given those draws ([`posterior_success_prob`]).
//! Without an error model, `success_prob` is `None` and the planner's order holds.

use moma_core::error_model::{Draws, Roi};
use moma_core::{DepthErrorModel, Intrinsics, Mask, MetricDepth};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{GraspError, Result};
use crate::grasp::{Grasp, NoGraspReason, PlanOutcome};
use crate::gripper::{Gripper, SuctionCup};
use crate::parallel::{ParallelConfig, plan_parallel};
use crate::scene::{Scene, SceneConfig};
use crate::score::{ScoreConfig, score_grasp};
use crate::suction::{
    DepthUncertainty, PATCH_RADII, SUCTION_EDGE_MARGIN_M, SuctionConfig, plan_suction,
};

/// How grasps are ranked.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GraspQuality {
    /// By the planner's score on the planning depth (taken as exact).
    Nominal,
    /// By the success probability under the error model (Dex-Net's robust quality).
    Robust,
}

impl GraspQuality {
    /// `nominal` or `robust`.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Nominal => "nominal",
            Self::Robust => "robust",
        }
    }
}

impl std::fmt::Display for GraspQuality {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for GraspQuality {
    type Err = GraspError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "nominal" => Ok(Self::Nominal),
            "robust" => Ok(Self::Robust),
            _ => Err(GraspError::InvalidConfig(format!(
                "unknown grasp quality '{s}' (expected 'nominal' or 'robust')"
            ))),
        }
    }
}

/// Default number of depth draws per frame.
pub const DEFAULT_GRASP_DRAWS: usize = 4;

/// Default tolerance of the robust ranking on the success probability ([`rank`]) for the
/// parallel jaw.
pub const DEFAULT_TIE_TOLERANCE: f32 = 0.2;

/// Default tolerance of the robust ranking for a suction cup: wider than the parallel jaw's,
/// because the suction planner's score already weighs the depth's error
/// ([`crate::DepthUncertainty`]) and tells its candidates apart better than 4 draws do
/// (docs/grasping.md, "Suction candidates for an uncertain depth": 0.2, 0.35 and 0.5
/// measured; 0.5 is also the 95 % half-width of a 4-draw estimate at p = 0.5).
pub const DEFAULT_SUCTION_TIE_TOLERANCE: f32 = 0.5;

/// The default tie tolerance of the robust ranking for `gripper`.
pub fn default_tie_tolerance(gripper: &Gripper) -> f32 {
    match gripper {
        Gripper::Parallel(_) => DEFAULT_TIE_TOLERANCE,
        Gripper::Suction(_) => DEFAULT_SUCTION_TIE_TOLERANCE,
    }
}

/// Default number of planner candidates scored on the draws.
pub const DEFAULT_ROBUST_CANDIDATES: usize = 20;

/// What [`plan_grasps`] plans.
#[derive(Debug, Clone, PartialEq)]
pub struct GraspRequest {
    /// The gripper (validated by the planner).
    pub gripper: Gripper,
    /// Grasps returned at most.
    pub top_k: usize,
    /// Seed of the planner's sampling and of the depth draws.
    pub seed: u64,
    /// Ranking; [`GraspQuality::Robust`] needs an error model.
    pub quality: GraspQuality,
    /// The planning depth's error model (`None`: no success probabilities).
    pub error_model: Option<DepthErrorModel>,
    /// Depth draws per frame (≥ 1).
    pub draws: usize,
    /// Planner candidates scored on the draws (≥ `top_k`).
    pub candidates: usize,
    /// Robust ranking: probabilities within this of the best count as tied, and the planner's
    /// order decides among them ([`rank`]). Default [`default_tie_tolerance`] of the gripper.
    pub tie_tolerance: f32,
    /// Drop grasps whose success probability is below this (in [0, 1]).
    pub min_success_prob: Option<f64>,
    /// Scene construction.
    pub scene: SceneConfig,
    /// Parallel-jaw planner settings (`top_k` and `seed` are the request's).
    pub parallel: ParallelConfig,
    /// Suction planner settings (`top_k` and `seed` are the request's).
    pub suction: SuctionConfig,
    /// The execution rules the draws are scored with.
    pub score: ScoreConfig,
}

impl GraspRequest {
    /// A request for `gripper` with the defaults: top 10, seed 0, robust ranking where an error
    /// model is given ([`GraspRequest::with_error_model`]), nominal otherwise.
    pub fn new(gripper: Gripper) -> Self {
        let tie_tolerance = default_tie_tolerance(&gripper);
        Self {
            gripper,
            top_k: 10,
            seed: 0,
            quality: GraspQuality::Nominal,
            error_model: None,
            draws: DEFAULT_GRASP_DRAWS,
            candidates: DEFAULT_ROBUST_CANDIDATES,
            tie_tolerance,
            min_success_prob: None,
            scene: SceneConfig::default(),
            parallel: ParallelConfig::default(),
            suction: SuctionConfig::default(),
            score: ScoreConfig::default(),
        }
    }

    /// Adds an error model and makes the ranking robust.
    pub fn with_error_model(mut self, model: Option<DepthErrorModel>) -> Self {
        self.quality = if model.is_some() {
            GraspQuality::Robust
        } else {
            GraspQuality::Nominal
        };
        self.error_model = model;
        self
    }

    /// Checks the request.
    ///
    /// # Errors
    /// [`GraspError::InvalidConfig`] naming the field.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(GraspError::InvalidConfig(m));
        if self.top_k == 0 {
            return bad("at least one grasp must be asked for (top_k ≥ 1)".into());
        }
        if self.draws == 0 {
            return bad("the number of depth draws must be at least 1".into());
        }
        if self.draws > 4096 {
            return bad(format!("{} depth draws is more than 4096", self.draws));
        }
        if !(0.0..=1.0).contains(&self.tie_tolerance) {
            return bad(format!(
                "the robust ranking's tolerance {} is outside [0, 1]",
                self.tie_tolerance
            ));
        }
        if let Some(p) = self.min_success_prob
            && !(0.0..=1.0).contains(&p)
        {
            return bad(format!("minimum success probability {p} is outside [0, 1]"));
        }
        if self.quality == GraspQuality::Robust && self.error_model.is_none() {
            return bad(
                "robust grasp quality needs an error model of the depth (a calibration's, or a \
                 uniform σ)"
                    .into(),
            );
        }
        if self.min_success_prob.is_some() && self.error_model.is_none() {
            return bad(
                "a minimum success probability needs an error model of the depth (a \
                 calibration's, or a uniform σ)"
                    .into(),
            );
        }
        if let Some(m) = &self.error_model {
            m.validate()
                .map_err(|e| GraspError::InvalidConfig(format!("depth error model: {e}")))?;
        }
        Ok(())
    }
}

/// Plans grasps on `depth` (object `mask` if given) as [`GraspRequest`] says (module
/// documentation). With an error model the planner works on [`planning_depth`], the error
/// model's expected truth of `depth`; the scene built on the depth planned on is returned too.
///
/// # Errors
/// An invalid request or gripper; the errors of [`Scene::build`] on the planning depth.
pub fn plan_grasps(
    depth: &MetricDepth,
    intrinsics: &Intrinsics,
    mask: Option<&Mask>,
    request: &GraspRequest,
) -> Result<(Scene, PlanOutcome)> {
    request.validate()?;
    let planning = planning_depth(depth, intrinsics, request);
    let scene = Scene::build(&planning, intrinsics, mask, &request.scene)?;
    let outcome = plan_on_scene(&scene, &planning, intrinsics, request)?;
    Ok((scene, outcome))
}

/// The depth a request plans on. Without an error model, `depth` itself. With one, its
/// expected truth ([`DepthErrorModel::expected_truth_map`]): the mean relief correction and
/// edge share that the calibration measured, and, for suction, the short-range bumps averaged
/// out as far as [`suction_noise_guard`] says the depth is rough (`intrinsics` give the cup's
/// size in pixels). Dex-Net plans on the mean estimate and draws the deviations around it;
/// planning on the aligned depth as if exact put suction cups 15–25 mm short of objects whose
/// relief the depth model flattened (`cup_crash`) and closed fingers on blurred silhouette ramps
/// (`not_antipodal`): docs/grasping.md, "Planning on the expected truth".
pub fn planning_depth<'a>(
    depth: &'a MetricDepth,
    intrinsics: &Intrinsics,
    request: &GraspRequest,
) -> std::borrow::Cow<'a, MetricDepth> {
    let Some(model) = &request.error_model else {
        return std::borrow::Cow::Borrowed(depth);
    };
    let mut expected = model.expected_truth_map(depth.depth_m.view(), false);
    if let Gripper::Suction(cup) = &request.gripper {
        let guard = planning_noise_guard(model, cup, intrinsics);
        if guard > 0.0 {
            let (h, w) = expected.dim();
            let smooth = model.expected_truth(expected.view(), Roi::full(w, h));
            if guard >= 1.0 {
                expected = smooth;
            } else {
                // the smoothing in proportion to the guard
                ndarray::Zip::from(&mut expected)
                    .and(&smooth)
                    .for_each(|z, &s| *z += guard * (s - *z));
            }
        }
    }
    std::borrow::Cow::Owned(MetricDepth::new(expected))
}

/// The guard a suction plan with `model` works with: [`suction_noise_guard`] at the model's
/// reference depth, one value for the planning depth's smoothing ([`planning_depth`]) and for
/// the candidates' patch normals and edge margin ([`plan_on_scene`]).
fn planning_noise_guard(model: &DepthErrorModel, cup: &SuctionCup, intrinsics: &Intrinsics) -> f32 {
    suction_noise_guard(model, model.depth_ref_m as f32, cup, intrinsics.fx)
}

/// Short-range noise (metres, RMS within one cup radius: [`DepthErrorModel::noise_within_m`])
/// under which the suction planner takes the depth as exact: no smoothing, the pixel's
/// normal, no edge margin ([`suction_noise_guard`]).
pub const NOISE_GUARD_FROM_M: f64 = 0.0005;

/// Short-range noise (metres) from which the suction planner's guards against it are whole.
pub const NOISE_GUARD_FULL_M: f64 = 0.0015;

/// How much of the suction planner's guards against short-range noise a depth needs, in
/// [0, 1]: 0 where the error model's noise within one cup radius at depth `z_m` is under
/// [`NOISE_GUARD_FROM_M`], 1 from [`NOISE_GUARD_FULL_M`] on, linear between. The guards are
/// the smoothing of the planning depth ([`planning_depth`]), the approach along the normal of
/// the largest planar patch instead of the pixel's ([`SuctionConfig::patch_noise_m`]) and the
/// edge margin ([`DepthUncertainty::edge_margin_m`]). They are worth 20 points of the GT's
/// success rate on the simulated depth model, and they cost 13 points on an exact
/// prediction, where they flatten curved faces and push cups off small objects
/// (docs/grasping.md, "What limits the deployed configuration"). A planner with an error
/// model of no short-range noise now plans suction as on exact depth.
pub fn suction_noise_guard(model: &DepthErrorModel, z_m: f32, cup: &SuctionCup, fx_px: f64) -> f32 {
    let radius_px = f64::from(cup.radius_m) * fx_px / f64::from(z_m.max(1e-3));
    let noise = model.noise_within_m(z_m, radius_px);
    let guard = (noise - NOISE_GUARD_FROM_M) / (NOISE_GUARD_FULL_M - NOISE_GUARD_FROM_M);
    if guard.is_finite() {
        guard.clamp(0.0, 1.0) as f32
    } else {
        1.0
    }
}

/// [`ParallelConfig::opening_margin_m`] of `model` at the median object depth of `scene`.
fn opening_margin(model: &DepthErrorModel, scene: &Scene) -> f32 {
    let sigma = model.flat_sigma_m(scene.object_depth_m()) as f32;
    crate::parallel::OPENING_MARGIN_SIGMAS * sigma
}

/// [`SuctionConfig::patch_noise_m`] of `model` at the median object depth of `scene`; all 0
/// (the pixel's normal) where the depth needs no guard against noise (`guard`, the request's
/// [`suction_noise_guard`]).
fn patch_noise(model: &DepthErrorModel, scene: &Scene, cup_radius_m: f32, guard: f32) -> [f32; 4] {
    if guard <= 0.0 {
        return [0.0; 4];
    }
    let z = scene.object_depth_m();
    let px_per_m = scene.cloud.fx / z.max(1e-3);
    PATCH_RADII.map(|k| model.noise_within_m(z, f64::from(k * cup_radius_m * px_per_m)) as f32)
}

/// The depth error a suction candidate is weighed for ([`DepthUncertainty`]), from `model` at
/// the objects' depth; the edge margin in proportion to `guard` ([`suction_noise_guard`]).
fn suction_uncertainty(model: &DepthErrorModel, scene: &Scene, guard: f32) -> DepthUncertainty {
    DepthUncertainty {
        flat_sigma_m: model.flat_sigma_m(scene.object_depth_m()) as f32,
        relief_sigma: model.relief_sigma as f32,
        edge_margin_m: SUCTION_EDGE_MARGIN_M * guard,
    }
}

/// [`plan_grasps`] on a scene already built from `depth` (with `mask` and
/// `request.scene`), `depth` being the request's [`planning_depth`].
///
/// # Errors
/// As [`plan_grasps`].
pub fn plan_on_scene(
    scene: &Scene,
    depth: &MetricDepth,
    intrinsics: &Intrinsics,
    request: &GraspRequest,
) -> Result<PlanOutcome> {
    request.validate()?;
    let k = match &request.error_model {
        Some(_) => request.candidates.max(request.top_k),
        None => request.top_k,
    };
    let mut outcome = match &request.gripper {
        Gripper::Parallel(jaw) => plan_parallel(
            scene,
            jaw,
            &ParallelConfig {
                top_k: k,
                seed: request.seed,
                opening_margin_m: request
                    .error_model
                    .as_ref()
                    .map_or(request.parallel.opening_margin_m, |m| {
                        opening_margin(m, scene)
                    }),
                ..request.parallel.clone()
            },
        )?,
        Gripper::Suction(cup) => {
            // the guard of `planning_depth`
            let model_guard = request
                .error_model
                .as_ref()
                .map(|m| (m, planning_noise_guard(m, cup, intrinsics)));
            plan_suction(
                scene,
                cup,
                &SuctionConfig {
                    top_k: k,
                    seed: request.seed,
                    patch_noise_m: model_guard
                        .map_or(request.suction.patch_noise_m, |(m, guard)| {
                            patch_noise(m, scene, cup.radius_m, guard)
                        }),
                    uncertainty: model_guard.map_or(request.suction.uncertainty, |(m, guard)| {
                        Some(suction_uncertainty(m, scene, guard))
                    }),
                    ..request.suction
                },
            )?
        }
    };
    let Some(model) = &request.error_model else {
        outcome.grasps.truncate(request.top_k);
        return Ok(outcome);
    };
    if outcome.grasps.is_empty() {
        return Ok(outcome);
    }
    let shares = success_probabilities(&outcome.grasps, scene, depth, intrinsics, model, request)?;
    let mut ranked: Vec<(Grasp, f32)> = outcome.grasps.drain(..).zip(shares).collect();
    rank(&mut ranked, request.quality, request.tie_tolerance);
    for (_, p) in &mut ranked {
        *p = posterior_success_prob(*p, request.draws);
    }
    let min = request.min_success_prob;
    let below = ranked
        .iter()
        .filter(|(_, p)| min.is_some_and(|m| f64::from(*p) < m))
        .count();
    let best = ranked.iter().map(|(_, p)| *p).fold(0.0f32, f32::max);
    outcome.grasps = ranked
        .into_iter()
        .filter(|(_, p)| min.is_none_or(|m| f64::from(*p) >= m))
        .take(request.top_k)
        .map(|(mut g, p)| {
            g.set_success_prob(Some(p));
            g
        })
        .collect();
    if outcome.grasps.is_empty()
        && let Some(m) = min
    {
        outcome.no_grasp_reason = Some(NoGraspReason::BelowMinSuccessProb {
            candidates: below,
            best_success_prob: best,
            min_success_prob: m,
            draws: request.draws,
        });
    }
    Ok(outcome)
}

/// The success probability reported for a grasp that succeeded on a `share` of `draws` drawn
/// depth maps: the posterior mean under a uniform prior, `(successes + 1) / (draws + 2)`
/// (Laplace's rule of succession). It is the estimate with the least expected squared error,
/// the Brier score's loss, where the plain share claims certainty from a handful of draws (4 of
/// 4 is not a sure grasp): over the three opaque shared sets it lowered the mean Brier score of
/// both grippers, re-aligned and one-shot, e.g. 0.274 → 0.236 re-aligned suction, 0.278 → 0.237
/// re-aligned parallel jaw (SIMULATED predictions, PROXY scores; docs/grasping.md, "Success
/// probabilities from a few draws"). Monotone in the share, so it never reorders grasps.
pub fn posterior_success_prob(share: f32, draws: usize) -> f32 {
    let n = draws as f32;
    (share * n + 1.0) / (n + 2.0)
}

/// The share of successful draws that [`posterior_success_prob`] reported as `success_prob`
/// (its inverse, rounded to a whole number of the `draws`): what [`rank`] compares, for a
/// caller that re-ranks reported grasps with a tie tolerance (`moma grasp-eval`).
pub fn share_of_draws(success_prob: f32, draws: usize) -> f32 {
    let n = draws.max(1) as f32;
    ((success_prob * (n + 2.0) - 1.0).round() / n).clamp(0.0, 1.0)
}

/// Orders `(grasp, share of successful draws)` pairs, given in the planner's order, by
/// `quality`. Nominal keeps the planner's order. Robust puts first, in the planner's order, every
/// grasp whose share is within `tolerance` of the best one (a Monte-Carlo estimate from a few
/// draws cannot tell those apart, and the planner's score then decides), then the others by
/// share, highest first (stable).
pub fn rank(grasps: &mut [(Grasp, f32)], quality: GraspQuality, tolerance: f32) {
    if quality == GraspQuality::Robust {
        let best = grasps.iter().map(|g| g.1).fold(0.0f32, f32::max);
        let key = |p: f32| if p >= best - tolerance { best } else { p };
        grasps.sort_by(|a, b| key(b.1).total_cmp(&key(a.1)));
    }
}

/// The share of `request.draws` depth maps on which each grasp succeeds (what [`rank`] orders
/// by; the reported `success_prob` is [`posterior_success_prob`] of it): maps drawn from
/// `model`'s deviations around its expected truth ([`DepthErrorModel::deviations`]), long-range
/// part only ([`DepthErrorModel::long_range`]: the short-range bumps are averaged out of the
/// suction planning depth and already present once in the parallel jaw's), on which it
/// succeeds by the scorer's rules, drawn around `depth`, the request's [`planning_depth`]
/// (whose scene is `scene`).
/// Each draw covers only the region around the grasps (their image points plus the gripper's
/// reach at their depth, [`draw_region`]); its scene keeps the planning scene's support plane
/// and objects ([`Scene::with_depth_in`]).
///
/// # Errors
/// A malformed grasp (never from the planners).
pub fn success_probabilities(
    grasps: &[Grasp],
    scene: &Scene,
    depth: &MetricDepth,
    intrinsics: &Intrinsics,
    model: &DepthErrorModel,
    request: &GraspRequest,
) -> Result<Vec<f32>> {
    if grasps.is_empty() {
        return Ok(Vec::new());
    }
    let roi = draw_region(grasps, intrinsics, &request.gripper);
    let k = Intrinsics {
        width: roi.width,
        height: roi.height,
        cx: intrinsics.cx - roi.u0 as f64,
        cy: intrinsics.cy - roi.v0 as f64,
        ..*intrinsics
    };
    // the planning depth is the model's expected truth: draws add its deviations, without the
    // means that the planning depth already holds (relief correction, edge share)
    let mut spread = model.deviations().long_range();
    if let Gripper::Suction(_) = request.gripper {
        // a suction candidate's score already keeps its ring clear of the edges by a margin
        // (`DepthUncertainty`); the edge noise on top broke the draws' seals near every
        // silhouette and made suction's probabilities pessimistic (docs/grasping.md, "Suction
        // candidates for an uncertain depth": Brier 0.378 → 0.274 without it)
        spread.edge_gain = 0.0;
    }
    let draws = Draws::new(&spread, depth.depth_m.view(), roi);
    let per_draw: Vec<Vec<bool>> = (0..request.draws as u64)
        .into_par_iter()
        .map(|d| -> Result<Vec<bool>> {
            let drawn = MetricDepth::new(draws.draw(request.seed, d));
            let drawn_scene = match scene.with_depth_in(roi, &drawn, &k, &request.scene) {
                Ok(s) => s,
                // nothing to execute on in this draw: every grasp fails there
                Err(GraspError::AllInvalidDepth | GraspError::MaskNoValidDepth { .. }) => {
                    return Ok(vec![false; grasps.len()]);
                }
                // anything else is a fault (the crop's intrinsics refused made every draw
                // fail, silently, when their validation was first tightened)
                Err(e) => return Err(e),
            };
            grasps
                .iter()
                // the camera frame is the same: the crop only moves the principal point
                .map(|g| {
                    Ok(score_grasp(&drawn_scene, g, &request.gripper, &request.score)?.success)
                })
                .collect()
        })
        .collect::<Result<_>>()?;
    let n = per_draw.len() as f32;
    Ok((0..grasps.len())
        .map(|i| per_draw.iter().filter(|d| d[i]).count() as f32 / n)
        .collect())
}

/// The image region the draws of `grasps` need: the bounding box of their points' pixels,
/// widened on every side by what the scorer looks at around a grasp (parallel: half the
/// stroke, a finger and 2 cm; suction: 2 cup radii and 2 cm) at the nearest grasp's depth,
/// clipped to the image.
pub fn draw_region(grasps: &[Grasp], k: &Intrinsics, gripper: &Gripper) -> Roi {
    let reach_m = match gripper {
        Gripper::Parallel(j) => f64::from(0.5 * j.stroke_m + j.finger_thickness_m) + 0.02,
        Gripper::Suction(c) => 2.0 * f64::from(c.radius_m) + 0.02,
    };
    let (mut u0, mut u1, mut v0, mut v1) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    let mut z_min = f64::INFINITY;
    for g in grasps {
        let p = g.point_m();
        let z = f64::from(p[2]);
        if !(z.is_finite() && z > 0.0) {
            continue;
        }
        let (u, v) = (
            k.fx * f64::from(p[0]) / z + k.cx,
            k.fy * f64::from(p[1]) / z + k.cy,
        );
        u0 = u0.min(u);
        u1 = u1.max(u);
        v0 = v0.min(v);
        v1 = v1.max(v);
        z_min = z_min.min(z);
    }
    if !z_min.is_finite() {
        return Roi::full(k.width, k.height);
    }
    let m = k.fx.max(k.fy) * reach_m / z_min;
    let clip = |x: f64, hi: usize| x.clamp(0.0, hi as f64) as usize;
    let (a, b) = (
        clip((u0 - m).floor(), k.width),
        clip((u1 + m).ceil() + 1.0, k.width),
    );
    let (c, d) = (
        clip((v0 - m).floor(), k.height),
        clip((v1 + m).ceil() + 1.0, k.height),
    );
    Roi {
        u0: a,
        v0: c,
        width: b - a,
        height: d - c,
    }
}
