//! Parallel-jaw planning: Dex-Net-style antipodal sampling on silhouette contacts.
//!
//! 1. Contacts: object pixels on a silhouette edge (the near side of a depth jump), subsampled
//!    with the seed; each has the outward horizontal normal `n₁` of the edge.
//! 2. For each contact, the closing axis is `b = −n₁` and the approaches are top-down (`−up`) and
//!    tilted about `b` by `±tilt_angles_deg`. The closing line runs `contact_depth_m` below the
//!    contact along the approach; the opposite side is where that line leaves the object.
//! 3. The grasp is executed on the planning scene with the proxy-scoring rules ([`crate::score`]):
//!    contacts found by closing the fingers, friction cone at `planner_mu`, both fingers and the
//!    palm collision-free, enough points between the fingers. The centre is then moved to the
//!    midpoint of the two contacts found.
//! 4. Score, rank, greedy NMS, top-K (each kept edge grasp re-executed at its final pose).
//!
//! When that finds nothing, the same strict pass runs with the steeper tilts
//! [`ParallelConfig::fallback_tilt_angles_deg`] (40° and 60° by default) only: an object held in
//! a robot hand or under an overhang cannot be reached from above, but often from the side.
//!
//! This strict pass applies the scorer's own rules to the planning depth. On depth aligned from a
//! depth-model prediction (docs/method.md §6: silhouettes spread over 3–5 px, normals rotating over
//! the soft edge, a few mm of correlated noise) it rejects every candidate, so when neither strict
//! pass finds a grasp a **tolerant pass** ([`ParallelConfig::tolerant_pass`]) runs the same steps with
//! - silhouettes found as a depth drop over a small window (`soft_edge_window_px`,
//!   `soft_edge_jump_m`) and their normals averaged over a larger disc (`soft_normal_radius_px`);
//! - the fingertips shortened by `collision_margin_m` in the collision test, and mixed pixels of
//!   a soft silhouette (a blend of object and background, in mid-air behind the object) not
//!   counted as collisions beside the fingers (in the palm they are: a wall's steep face is
//!   "mixed" too);
//! - footprint candidates ([`crate::footprint`]): top-down grasps across the object's top-view
//!   footprint, which need neither sharp depth edges nor clean per-pixel normals.
//!
//! The scorer ([`crate::score`]) keeps the strict rules on the ground truth.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::cloud::Vec3;
use crate::contact::{ExecConfig, JawPose, Soft};
use crate::error::{GraspError, Result, positive};
use crate::footprint::{FootprintConfig, footprint_candidates};
use crate::grasp::{
    FailureReason, Grasp, NoGraspReason, ParallelGrasp, ParallelPose, PlanOutcome, arr, tally,
};
use crate::gripper::ParallelJaw;
use crate::nms::{greedy, rank, subsample};
use crate::scene::Scene;

/// Parallel-jaw planner settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ParallelConfig {
    /// Execution rules shared with the scorer.
    pub exec: ExecConfig,
    /// At most this many silhouette contacts are sampled (seeded). Default 400.
    pub max_contact_samples: usize,
    /// Approach tilts about the closing axis besides top-down (each used with both signs),
    /// degrees. Default `[20]`.
    pub tilt_angles_deg: Vec<f32>,
    /// When the strict pass with `tilt_angles_deg` finds no grasp, it runs again with these
    /// steeper approach tilts about the closing axis (each with both signs), degrees: objects
    /// whose top is blocked (held in a robot hand, under an overhang) or seen only from the side
    /// can often be reached only from an angle. Empty = no such retry. Default `[40, 60]`.
    pub fallback_tilt_angles_deg: Vec<f32>,
    /// Depth of the closing line below the sampled contact along the approach, metres.
    /// Default 0.003 m.
    pub contact_depth_m: f32,
    /// Thin objects lying flat (tools, spoons, pens: 10–25 mm tall): where `contact_depth_m`
    /// would bring the fingertips closer to the support plane than this, the closing line is
    /// raised so that they clear it by this much (never above 0.5 mm below the contact),
    /// metres. Default 0.003 m.
    pub fingertip_clearance_m: f32,
    /// Friction coefficient a planned grasp must pass (the scorer uses 0.8). Default 0.6.
    pub planner_mu: f32,
    /// Free length along the closing line that ends the object when finding the far side, metres.
    /// Default 0.003 m.
    pub exit_gap_m: f32,
    /// Least free space between a finger and its contact before closing, metres. Default 0.003 m.
    pub min_clearance_m: f32,
    /// Grasps returned at most. Default 10.
    pub top_k: usize,
    /// NMS: a grasp whose centre is within this of a kept one, metres, …  Default 0.01 m.
    pub nms_distance_m: f32,
    /// … and whose closing axis is within this angle of it, degrees, is suppressed. Default 30.
    pub nms_angle_deg: f32,
    /// Seed of the contact sampling. Default 0.
    pub seed: u64,
    /// When the strict pass (the scorer's own rules on the planning depth) finds no grasp, run a
    /// tolerant pass for depth aligned from a depth-model prediction: soft silhouettes
    /// (`soft_edge_*`), the collision margin, mixed silhouette pixels ignored in the collision
    /// test beside the fingers, and footprint candidates. Default true.
    pub tolerant_pass: bool,
    /// Tolerant pass: a contact is on a silhouette when a pixel within this many pixels lies
    /// farther by more than `soft_edge_jump_m` (depth-model output spreads a silhouette over 3–5
    /// px, so adjacent pixels never jump), pixels. Default 3.
    pub soft_edge_window_px: usize,
    /// Tolerant pass: depth drop over that window marking a silhouette, metres. Default 0.008 m.
    pub soft_edge_jump_m: f32,
    /// Tolerant pass: radius of the disc giving a silhouette contact's normal (larger than the
    /// scorer's [`ExecConfig::silhouette_radius_px`] to average over the soft edge), pixels.
    /// Default 6.
    pub soft_normal_radius_px: usize,
    /// Free space left on each side of the object before closing, on top of the jaw's
    /// [`ParallelJaw::opening_clearance_m`] (and the footprint candidates'
    /// [`FootprintConfig::clearance_m`]), for depth that is not exact (metres). The grasps that
    /// failed on the ground truth after planning on aligned depth mostly did so by a finger
    /// landing on the object (docs/grasping.md, "A wider opening"). Set by
    /// [`crate::plan_on_scene`] from the error model: [`OPENING_MARGIN_SIGMAS`] × its flat σ at
    /// the median object depth. Default 0 (exact depth).
    pub opening_margin_m: f32,
    /// Tolerant pass: the fingertips are shortened by this in the collision test, so that a few mm
    /// of depth noise on the table or the object do not reject every grasp, metres. Default
    /// 0.003 m.
    pub collision_margin_m: f32,
    /// Tolerant pass: footprint candidates (robust to soft silhouettes and noisy depth), see
    /// [`FootprintConfig`]. Default: enabled.
    pub footprint: FootprintConfig,
}

impl Default for ParallelConfig {
    fn default() -> Self {
        Self {
            exec: ExecConfig::default(),
            max_contact_samples: 400,
            tilt_angles_deg: vec![20.0],
            fallback_tilt_angles_deg: vec![40.0, 60.0],
            contact_depth_m: 0.003,
            fingertip_clearance_m: 0.003,
            planner_mu: 0.6,
            exit_gap_m: 0.003,
            min_clearance_m: 0.003,
            top_k: 10,
            nms_distance_m: 0.01,
            nms_angle_deg: 30.0,
            seed: 0,
            tolerant_pass: true,
            soft_edge_window_px: 3,
            soft_edge_jump_m: 0.008,
            soft_normal_radius_px: 6,
            collision_margin_m: 0.003,
            opening_margin_m: 0.0,
            footprint: FootprintConfig::default(),
        }
    }
}

impl ParallelConfig {
    pub(crate) fn soft(&self) -> Soft {
        Soft {
            window_px: self.soft_edge_window_px,
            jump_m: self.soft_edge_jump_m,
            radius_px: self.soft_normal_radius_px,
            collision_margin_m: self.collision_margin_m,
        }
    }

    /// Checks the settings.
    ///
    /// # Errors
    /// [`GraspError::InvalidConfig`] naming the field.
    pub fn validate(&self) -> Result<()> {
        self.exec.validate()?;
        self.footprint.validate()?;
        let e = GraspError::InvalidConfig;
        positive("planner_mu", self.planner_mu, e)?;
        positive("exit_gap_m", self.exit_gap_m, e)?;
        positive("min_clearance_m", self.min_clearance_m, e)?;
        positive("nms_distance_m", self.nms_distance_m, e)?;
        positive("soft_edge_jump_m", self.soft_edge_jump_m, e)?;
        if !(self.collision_margin_m.is_finite() && self.collision_margin_m >= 0.0) {
            return Err(e(format!(
                "collision_margin_m = {} must be >= 0",
                self.collision_margin_m
            )));
        }
        if self.soft_edge_window_px == 0 || self.soft_normal_radius_px == 0 {
            return Err(e(
                "soft_edge_window_px and soft_normal_radius_px must be >= 1".into(),
            ));
        }
        if !(self.opening_margin_m.is_finite() && self.opening_margin_m >= 0.0) {
            return Err(e(format!(
                "opening_margin_m = {} must be >= 0",
                self.opening_margin_m
            )));
        }
        if !(self.fingertip_clearance_m.is_finite() && self.fingertip_clearance_m >= 0.0) {
            return Err(e(format!(
                "fingertip_clearance_m = {} must be >= 0",
                self.fingertip_clearance_m
            )));
        }
        if !(self.contact_depth_m.is_finite() && self.contact_depth_m >= 0.0) {
            return Err(e(format!(
                "contact_depth_m = {} must be >= 0",
                self.contact_depth_m
            )));
        }
        if self
            .tilt_angles_deg
            .iter()
            .chain(&self.fallback_tilt_angles_deg)
            .any(|t| !t.is_finite() || t.abs() >= 90.0)
        {
            return Err(e(
                "tilt_angles_deg and fallback_tilt_angles_deg must lie in (-90, 90)".into(),
            ));
        }
        if self.top_k == 0 || self.max_contact_samples == 0 {
            return Err(e("top_k and max_contact_samples must be >= 1".into()));
        }
        Ok(())
    }
}

#[derive(Debug, Clone, Copy)]
struct Candidate {
    pose: JawPose,
    score: f32,
    /// Already tested at its final pose (footprint candidates).
    tested: bool,
}

/// Planner score in `[0, 1]`:
/// `0.4·(1 − μ_needed/1.2) + 0.2·(1 − width/stroke) + 0.3·exp(−(d/0.02 m)²) + 0.1·(1 − tilt/90°)`,
/// `d` the distance from the grasp centre to the object's centroid across "up".
fn grasp_score(mu_needed: f32, width: f32, stroke: f32, d_centre_m: f32, tilt_deg: f32) -> f32 {
    let q_mu = (1.0 - mu_needed / 1.2).clamp(0.0, 1.0);
    let q_w = (1.0 - width / stroke).clamp(0.0, 1.0);
    let q_c = (-(d_centre_m / 0.02).powi(2)).exp();
    let q_t = (1.0 - tilt_deg.abs() / 90.0).clamp(0.0, 1.0);
    0.4 * q_mu + 0.2 * q_w + 0.3 * q_c + 0.1 * q_t
}

/// [`ParallelConfig::opening_margin_m`] in flat σ of the error model (chosen over three
/// simulator seeds of the shared sets, checked on `moma demo`'s scene; docs/grasping.md).
pub const OPENING_MARGIN_SIGMAS: f32 = 2.0;

/// Shallowest depth of a closing line below its contact, metres.
const MIN_CONTACT_DEPTH_M: f32 = 0.0005;

/// How far below contact `i` the closing line runs along `approach`: `contact_depth_m`, or less
/// where the fingertips (`contact_to_tip_m` further) would come within `fingertip_clearance_m`
/// of the support plane (thin objects), but at least [`MIN_CONTACT_DEPTH_M`].
fn contact_depth(
    scene: &Scene,
    i: usize,
    approach: Vec3,
    jaw: &ParallelJaw,
    config: &ParallelConfig,
) -> f32 {
    let Some(plane) = &scene.plane else {
        return config.contact_depth_m;
    };
    let down = approach.dot(&-scene.up());
    if down < 0.1 {
        return config.contact_depth_m;
    }
    let height = plane.height_m(&scene.cloud.points[i]);
    let deepest = (height - config.fingertip_clearance_m) / down - jaw.contact_to_tip_m;
    if deepest >= MIN_CONTACT_DEPTH_M {
        config.contact_depth_m.min(deepest)
    } else {
        config.contact_depth_m
    }
}

#[allow(clippy::too_many_arguments)]
fn candidate(
    scene: &Scene,
    i: usize,
    approach: Vec3,
    closing: Vec3,
    tilt_deg: f32,
    jaw: &ParallelJaw,
    config: &ParallelConfig,
    soft: Option<&Soft>,
) -> std::result::Result<Candidate, FailureReason> {
    let exec = &config.exec;
    let step = exec.march_step_m;
    let l0 = scene.cloud.points[i] + approach * contact_depth(scene, i, approach, jaw, config);
    // Near side: where the closing line enters the object (`l0` itself, or farther on when moving
    // along a tilted approach, or past a rounded edge, left the object); far side: where it leaves
    // the object for at least `exit_gap_m`.
    let mut t_in: Option<f32> = None;
    let mut t_occ = 0.0f32;
    let mut t = step;
    loop {
        match t_in {
            None if t > jaw.stroke_m => return Err(FailureReason::MissedObject),
            Some(t0) if t - t0 > jaw.stroke_m => return Err(FailureReason::NotAntipodal),
            _ => {}
        }
        let q = l0 + closing * t;
        match scene.occupied(&q, exec.occupancy_tol_m) {
            Some(j) if scene.is_object(j) => {
                t_in.get_or_insert(t - step);
                t_occ = t;
            }
            _ if t_in.is_some() && t - t_occ >= config.exit_gap_m => break,
            _ => {}
        }
        t += step;
    }
    let t_in = t_in.unwrap_or(0.0);
    let span = t_occ - t_in;
    let clearance =
        (jaw.opening_clearance_m + config.opening_margin_m).min((jaw.stroke_m - span) / 2.0);
    if clearance < config.min_clearance_m {
        return Err(FailureReason::NotAntipodal);
    }
    let width = span + 2.0 * clearance;
    let pose = JawPose {
        center: l0 + closing * ((t_in + t_occ) / 2.0),
        approach,
        closing,
        width,
    };
    let run = scene.execute_parallel(&pose, jaw, exec, config.planner_mu, true, soft);
    if let Some(f) = run.failure {
        return Err(f);
    }
    let Some([c1, c2]) = run.contacts else {
        return Err(FailureReason::MissedObject);
    };
    let center = (c1.point + c2.point) / 2.0;
    let up = scene.up();
    let d_centre = scene.centroid(scene.label(c1.index)).map_or(0.0, |c| {
        let d = center - c;
        (d - up * d.dot(&up)).norm()
    });
    Ok(Candidate {
        pose: JawPose { center, ..pose },
        score: grasp_score(run.mu_needed, width, jaw.stroke_m, d_centre, tilt_deg),
        tested: false,
    })
}

/// Plans parallel-jaw grasps on `scene` (camera frame), best first, at most `config.top_k`.
/// Deterministic for a given `config.seed`, with any number of rayon threads.
///
/// # Errors
/// Invalid gripper or config. No grasp is not an error: see [`PlanOutcome::no_grasp_reason`].
pub fn plan_parallel(
    scene: &Scene,
    jaw: &ParallelJaw,
    config: &ParallelConfig,
) -> Result<PlanOutcome> {
    jaw.validate()?;
    config.validate()?;
    if scene.plane.is_none() {
        return Ok(PlanOutcome::none(NoGraspReason::NoSupportPlane));
    }
    if scene.components().is_empty() {
        return Ok(PlanOutcome::none(NoGraspReason::NoObject));
    }
    let strict = plan_pass(
        scene,
        jaw,
        config,
        &with_top_down(&config.tilt_angles_deg),
        None,
    );
    if !strict.grasps.is_empty() {
        return Ok(strict);
    }
    let mut outcome = strict;
    if !config.fallback_tilt_angles_deg.is_empty() {
        let steep = plan_pass(
            scene,
            jaw,
            config,
            &signed(&config.fallback_tilt_angles_deg),
            None,
        );
        if !steep.grasps.is_empty() {
            return Ok(steep);
        }
        outcome = merge_no_grasp(outcome, steep);
    }
    if !config.tolerant_pass {
        return Ok(outcome);
    }
    let tolerant = plan_pass(
        scene,
        jaw,
        config,
        &with_top_down(&config.tilt_angles_deg),
        Some(&config.soft()),
    );
    if !tolerant.grasps.is_empty() {
        return Ok(tolerant);
    }
    Ok(merge_no_grasp(outcome, tolerant))
}

/// `tilts` with both signs, each once.
fn signed(tilts: &[f32]) -> Vec<f32> {
    let mut out = Vec::with_capacity(2 * tilts.len());
    for t in tilts {
        out.push(*t);
        out.push(-*t);
    }
    out
}

/// Top-down (0°) followed by `tilts` with both signs.
fn with_top_down(tilts: &[f32]) -> Vec<f32> {
    let mut out = vec![0.0];
    out.extend(signed(tilts));
    out
}

/// Two grasp-less outcomes as one: the candidates and failure counts of both passes.
fn merge_no_grasp(a: PlanOutcome, b: PlanOutcome) -> PlanOutcome {
    let failures = |o: &PlanOutcome| match &o.no_grasp_reason {
        Some(NoGraspReason::AllRejected { failures, .. }) => failures.clone(),
        _ => Vec::new(),
    };
    let (fa, fb) = (failures(&a), failures(&b));
    if fa.is_empty() && fb.is_empty() {
        return a;
    }
    let all = fa
        .iter()
        .chain(&fb)
        .flat_map(|(r, n)| std::iter::repeat_n(*r, *n));
    let candidates = a.candidates + b.candidates;
    PlanOutcome {
        grasps: Vec::new(),
        no_grasp_reason: Some(NoGraspReason::AllRejected {
            candidates,
            failures: tally(all),
        }),
        candidates,
    }
}

/// Runs only the tolerant pass of [`plan_parallel`] (soft silhouettes, collision margin, mixed
/// pixels, footprint candidates), whatever the strict pass would find; for benches and
/// diagnostics.
///
/// # Errors
/// Invalid gripper or config.
pub fn plan_parallel_tolerant(
    scene: &Scene,
    jaw: &ParallelJaw,
    config: &ParallelConfig,
) -> Result<PlanOutcome> {
    jaw.validate()?;
    config.validate()?;
    if scene.plane.is_none() {
        return Ok(PlanOutcome::none(NoGraspReason::NoSupportPlane));
    }
    if scene.components().is_empty() {
        return Ok(PlanOutcome::none(NoGraspReason::NoObject));
    }
    Ok(plan_pass(
        scene,
        jaw,
        config,
        &with_top_down(&config.tilt_angles_deg),
        Some(&config.soft()),
    ))
}

/// One planning pass with approach `tilts` (degrees about the closing axis, 0 = top-down):
/// strict (`soft = None`: the scorer's rules, edge candidates only) or tolerant (soft
/// silhouettes, collision margin, footprint candidates).
fn plan_pass(
    scene: &Scene,
    jaw: &ParallelJaw,
    config: &ParallelConfig,
    tilts: &[f32],
    soft: Option<&Soft>,
) -> PlanOutcome {
    let cloud = &scene.cloud;
    let edges: Vec<usize> = (0..cloud.valid.len())
        .filter(|&i| scene.is_object(i) && cloud.near_edge[i])
        .collect();
    let samples = subsample(edges, config.max_contact_samples, config.seed);
    let up = scene.up();
    let a0 = -up;
    let r = config.exec.silhouette_radius_px;
    let mut results: Vec<std::result::Result<Candidate, FailureReason>> = samples
        .par_iter()
        .flat_map_iter(|&i| {
            let normal = soft
                .and_then(|s| scene.soft_silhouette_normal(i, s))
                .or_else(|| scene.silhouette_normal(i, r));
            tilts.iter().map(move |&tilt| {
                let n1 = normal.ok_or(FailureReason::NotAntipodal)?;
                let b = -(n1 - a0 * n1.dot(&a0)).normalize();
                let th = tilt.to_radians();
                let a = a0 * th.cos() + b.cross(&a0) * th.sin();
                candidate(scene, i, a, b, tilt, jaw, config, soft)
            })
        })
        .collect();
    if let Some(soft) = soft.filter(|_| config.footprint.enabled) {
        let footprint = FootprintConfig {
            clearance_m: config.footprint.clearance_m + config.opening_margin_m,
            ..config.footprint.clone()
        };
        let fp = footprint_candidates(
            scene,
            jaw,
            config.planner_mu,
            &footprint,
            &config.exec,
            soft,
        );
        results.extend(fp.into_iter().map(|r| {
            r.map(|g| {
                let d_centre = scene.centroid(g.label).map_or(0.0, |c| {
                    let d = g.pose.center - c;
                    (d - up * d.dot(&up)).norm()
                });
                Candidate {
                    pose: g.pose,
                    score: grasp_score(g.mu_needed, g.pose.width, jaw.stroke_m, d_centre, 0.0),
                    tested: true,
                }
            })
        }));
    }
    if results.is_empty() {
        return PlanOutcome::none(NoGraspReason::NoCandidate);
    }
    let n_candidates = results.len();
    let mut failures = Vec::new();
    let mut cands = Vec::new();
    for r in results {
        match r {
            Ok(c) => cands.push(c),
            Err(f) => failures.push(f),
        }
    }
    let scores: Vec<f32> = cands.iter().map(|c| c.score).collect();
    let order = rank(&scores);
    let cos_nms = config.nms_angle_deg.to_radians().cos();
    let kept = greedy(
        &order,
        config.top_k,
        |k| {
            if cands[k].tested {
                return true;
            }
            let run = scene.execute_parallel(
                &cands[k].pose,
                jaw,
                &config.exec,
                config.planner_mu,
                false,
                soft,
            );
            run.failure.is_none()
        },
        |a, b| {
            let (pa, pb) = (&cands[a].pose, &cands[b].pose);
            (pa.center - pb.center).norm() < config.nms_distance_m
                && pa.closing.dot(&pb.closing).abs() >= cos_nms
        },
    );
    let grasps: Vec<Grasp> = kept
        .iter()
        .map(|&k| {
            let c = &cands[k];
            Grasp::Parallel(ParallelGrasp {
                success_prob: None,
                score: c.score,
                pose: ParallelPose {
                    center_m: arr(&c.pose.center),
                    approach: arr(&c.pose.approach),
                    closing: arr(&c.pose.closing),
                    width_m: c.pose.width,
                },
                base: None,
            })
        })
        .collect();
    let no_grasp_reason = grasps.is_empty().then(|| NoGraspReason::AllRejected {
        candidates: n_candidates,
        failures: tally(failures.into_iter()),
    });
    PlanOutcome {
        grasps,
        no_grasp_reason,
        candidates: n_candidates,
    }
}

#[cfg(test)]
mod tests {
    use moma_core::{Intrinsics, MetricDepth};
    use ndarray::Array2;

    use super::*;
    use crate::scene::SceneConfig;

    /// Top-down camera 0.7 m above a table with a 40 (x) × 60 (y) × 50 mm box centred on the axis.
    fn box_scene() -> (Scene, Intrinsics) {
        let k = Intrinsics {
            width: 640,
            height: 480,
            fx: 600.0,
            fy: 600.0,
            cx: 319.5,
            cy: 239.5,
        };
        let depth = Array2::from_shape_fn((480, 640), |(v, u)| {
            let (x, y) = ((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy);
            if (x * 0.65).abs() < 0.02 && (y * 0.65).abs() < 0.03 {
                0.65f32
            } else {
                0.7
            }
        });
        let scene = Scene::build(&MetricDepth::new(depth), &k, None, &SceneConfig::default());
        (scene.unwrap(), k)
    }

    /// Top-down camera 0.7 m above a table with a box of `x_m` × 100 mm × 50 mm (longer than
    /// the stroke along y: it can only be grasped across x), with its object mask.
    fn long_box(x_m: f64) -> Scene {
        let k = box_scene().1;
        let depth = Array2::from_shape_fn((480, 640), |(v, u)| {
            let (x, y) = ((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy);
            if (x * 0.65).abs() < x_m / 2.0 && (y * 0.65).abs() < 0.05 {
                0.65f32
            } else {
                0.7
            }
        });
        let depth = MetricDepth::new(depth);
        let mask = moma_core::Mask::new(depth.depth_m.mapv(|z| z < 0.68));
        Scene::build(&depth, &k, Some(&mask), &SceneConfig::default()).unwrap()
    }

    #[test]
    fn the_opening_margin_clears_an_object_wider_than_the_planning_depth_shows() {
        // Truth: a 60 mm wide box. Planning depth: the same box 36 mm wide (12 mm short of each
        // side, more than the jaw's 10 mm opening clearance): planned as exact, a finger lands
        // on the true box; with a 6 mm margin both fingers clear it and the grasp holds.
        let (truth, planned) = (long_box(0.06), long_box(0.036));
        let jaw = ParallelJaw::default();
        let gripper = crate::gripper::Gripper::Parallel(jaw);
        let outcome = |margin: f32| {
            let config = ParallelConfig {
                opening_margin_m: margin,
                ..ParallelConfig::default()
            };
            let plan = plan_parallel(&planned, &jaw, &config).unwrap();
            let grasp = plan
                .grasps
                .first()
                .copied()
                .expect("a grasp on the planning depth");
            let Grasp::Parallel(g) = grasp else {
                unreachable!()
            };
            let score = crate::score::score_grasp(
                &truth,
                &grasp,
                &gripper,
                &crate::score::ScoreConfig::default(),
            )
            .unwrap();
            (g.pose.width_m, score.failure)
        };
        let (w0, f0) = outcome(0.0);
        let (w6, f6) = outcome(0.006);
        assert!((w0 - 0.056).abs() < 0.003, "width {w0}");
        assert_eq!(f0, Some(FailureReason::Collision), "width {w0}");
        assert!((w6 - 0.068).abs() < 0.003, "width {w6}");
        assert_eq!(f6, None, "width {w6}");
        // a margin that is not a length is refused
        let bad = ParallelConfig {
            opening_margin_m: f32::NAN,
            ..ParallelConfig::default()
        };
        assert!(plan_parallel(&planned, &jaw, &bad).is_err());
    }

    #[test]
    fn closing_line_starting_off_the_object_is_centred_on_the_part_inside_it() {
        // Regression (m2t2-table, tilted candidates): the sampled contact moved along the
        // approach may lie off the object; the grasp must span the object part of the closing
        // line, not start at that point (which found no near-side contact: missed_object).
        let (scene, k) = box_scene();
        // A table pixel 60 mm left of the box's −x side (at 0.7 m), closing towards +x.
        let u = (k.cx + (-0.08) / 0.7 * k.fx).round() as usize;
        let v = k.cy.round() as usize;
        let i = scene.cloud.index(u, v);
        assert!(!scene.is_object(i));
        let config = ParallelConfig {
            contact_depth_m: 0.02 + 0.003,
            ..ParallelConfig::default()
        };
        let jaw = ParallelJaw::default();
        let a = Vec3::new(0.0, 0.0, 1.0);
        let b = Vec3::new(1.0, 0.0, 0.0);
        // Move that pixel's point up so that the closing line starts in free space above the
        // table, 3 mm below the box top, 60 mm before the box.
        let start = Vec3::new(-0.08, 0.0, 0.65 + 0.003) - a * config.contact_depth_m;
        let mut shifted = scene.clone();
        shifted.cloud.points[i] = start;
        let c = candidate(&shifted, i, a, b, 0.0, &jaw, &config, None).unwrap();
        // Centred on the box (x = 0) within 2 mm, width = 40 mm + 2 × 10 mm clearance.
        assert!(c.pose.center.x.abs() < 0.002, "{:?}", c.pose);
        assert!((c.pose.width - 0.06).abs() < 0.003, "{:?}", c.pose);
    }
}
