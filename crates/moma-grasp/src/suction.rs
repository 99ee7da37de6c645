//! Suction planning: seal, flatness, edge distance and a collision-free approach (docs/method.md §8).
//!
//! Candidates are object pixels with a surface normal on a `candidate_stride_px` grid (at most
//! `max_candidates`, seeded); the approach is the inward normal `−n`. Each candidate's score is
//! `seal quality × flatness × d / (d + r) × (1 + cos θ_up) / 2`, `d` the metric distance to the
//! nearest depth edge and `r` the cup radius, `θ_up` the angle between the approach and straight
//! down (−up): top-down picks are preferred to side picks. In score order, a candidate is kept when its execution on the
//! planning scene succeeds (the scorer's rules), the tool cylinder behind the cup is free, and no
//! kept grasp lies within `nms_distance_m`.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::cloud::{OrganisedCloud, Vec3};
use crate::contact::{ExecConfig, perpendiculars};
use crate::error::{GraspError, Result, positive};
use crate::grasp::{
    FailureReason, Grasp, NoGraspReason, PlanOutcome, SuctionGrasp, SuctionPose, arr, tally,
};
use crate::gripper::SuctionCup;
use crate::nms::{greedy, rank, subsample};
use crate::scene::Scene;

/// Suction planner settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SuctionConfig {
    /// Execution rules shared with the scorer.
    pub exec: ExecConfig,
    /// Candidate grid step, pixels. Default 2.
    pub candidate_stride_px: usize,
    /// At most this many candidates (seeded subsample of the grid). Default 1500.
    pub max_candidates: usize,
    /// Grasps returned at most. Default 10.
    pub top_k: usize,
    /// NMS: a grasp within this distance of a kept one is suppressed, metres. Default 0.02 m.
    pub nms_distance_m: f32,
    /// Seed of the candidate subsampling. Default 0.
    pub seed: u64,
    /// RMS of the planning depth's error within a patch of each radius of [`PATCH_RADII`]
    /// (metres). All 0 (exact depth): the approach is the pixel's normal. Otherwise it is the
    /// normal of the largest patch that is planar within that noise and
    /// [`PATCH_FLATNESS_M`]: a tilt that the depth's bumps put into a small patch breaks the
    /// seal on the true surface. Set by [`crate::plan_on_scene`] from the error model
    /// ([`moma_core::DepthErrorModel::noise_within_m`]; all 0 where the model's noise needs no
    /// guard, [`crate::suction_noise_guard`]). Default 0.
    #[serde(default)]
    pub patch_noise_m: [f32; 4],
    /// The planning depth's error where it matters to a cup; `None` (exact depth): the score
    /// above. Otherwise each candidate's score is also weighted for that error
    /// ([`DepthUncertainty`]). Set by [`crate::plan_on_scene`] from the error model. Default
    /// `None`.
    #[serde(default)]
    pub uncertainty: Option<DepthUncertainty>,
}

/// The error of an uncertain planning depth, as the suction score weighs it (metres). With it a
/// candidate's score is also multiplied by:
/// - **the ring's clearance**: the edge distance `d` counts less [`Self::edge_margin_m`]
///   (the aligned silhouettes, and the position the cup reaches on the true surface, are
///   off by a few millimetres);
/// - **the wider patch's flatness** `exp(−rms / `[`PATCH_FLATNESS_M`]`)`, `rms` the RMS
///   distance to its plane of the surface within [`PATCH_RADII`]`[0]` cup radii: a cup that
///   lands a few millimetres off still seals on a flat neighbourhood;
/// - **the chance of reaching within the cup's compliance** `c`: `erf(c / (√2 σ_z))`, with
///   `σ_z = hypot(`[`Self::flat_sigma_m`]`, `[`Self::relief_sigma`]` · h)` at the point's
///   height `h` above the support plane (depth models flatten objects; the error grows with
///   the height).
///
/// Measured in docs/grasping.md ("Suction candidates for an uncertain depth").
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DepthUncertainty {
    /// σ of the depth error shared by the frame and its smooth fields, at the objects' depth
    /// (metres).
    pub flat_sigma_m: f32,
    /// σ of the relief factor: the depth error per metre of height above the support plane
    /// (dimensionless).
    pub relief_sigma: f32,
    /// Subtracted from the edge distance of every candidate (metres). Default
    /// [`SUCTION_EDGE_MARGIN_M`]; [`crate::plan_on_scene`] scales it by
    /// [`crate::suction_noise_guard`].
    pub edge_margin_m: f32,
}

/// Default [`DepthUncertainty::edge_margin_m`]: 8 mm (docs/grasping.md, chosen among 5–15 mm on
/// SIMULATED predictions).
pub const SUCTION_EDGE_MARGIN_M: f32 = 0.008;

impl DepthUncertainty {
    /// The factor of a candidate with edge distance `d_m`, whose wider patch is planar to
    /// `patch_rms_m`, at `height_m` above the support plane (all metres; the documentation of
    /// [`DepthUncertainty`]).
    pub fn weight(&self, d_m: f32, patch_rms_m: f32, height_m: f32, cup: &SuctionCup) -> f32 {
        let d = (d_m - self.edge_margin_m).max(0.0);
        let clearance = d / (d + cup.radius_m);
        let flat = (-patch_rms_m / PATCH_FLATNESS_M).exp();
        let sigma_z = self
            .flat_sigma_m
            .hypot(self.relief_sigma * height_m.max(0.0))
            .max(1e-4);
        let reach = libm::erff(cup.compliance_m / (std::f32::consts::SQRT_2 * sigma_z));
        clearance * flat * reach
    }
}

/// Patch radii, in cup radii, tried for the approach normal on a noisy depth (largest first).
pub const PATCH_RADII: [f32; 4] = [3.0, 2.0, 1.5, 1.0];

/// Flatness allowed of a patch beyond the depth's noise (metres, RMS to its plane).
pub const PATCH_FLATNESS_M: f32 = 0.002;

impl Default for SuctionConfig {
    fn default() -> Self {
        Self {
            exec: ExecConfig::default(),
            candidate_stride_px: 2,
            max_candidates: 1500,
            top_k: 10,
            nms_distance_m: 0.02,
            seed: 0,
            patch_noise_m: [0.0; 4],
            uncertainty: None,
        }
    }
}

impl SuctionConfig {
    /// Checks the settings.
    ///
    /// # Errors
    /// [`GraspError::InvalidConfig`] naming the field.
    pub fn validate(&self) -> Result<()> {
        self.exec.validate()?;
        positive(
            "nms_distance_m",
            self.nms_distance_m,
            GraspError::InvalidConfig,
        )?;
        if self.candidate_stride_px == 0 || self.max_candidates == 0 || self.top_k == 0 {
            return Err(GraspError::InvalidConfig(
                "candidate_stride_px, max_candidates and top_k must be >= 1".into(),
            ));
        }
        Ok(())
    }
}

/// Chamfer (3-4) distance in pixels from every pixel to the nearest edge: a depth-edge pixel,
/// or a pixel that is not an object's (the object's border, which a soft silhouette of aligned
/// depth may not mark as a depth edge).
fn edge_distance_px(scene: &Scene) -> Vec<f32> {
    let cloud = &scene.cloud;
    let (w, h) = (cloud.width, cloud.height);
    let big = u32::MAX / 4;
    let mut d: Vec<u32> = (0..w * h)
        .map(|i| {
            if cloud.near_edge[i] || !scene.is_object(i) {
                0
            } else {
                big
            }
        })
        .collect();
    for v in 0..h {
        for u in 0..w {
            let i = v * w + u;
            let mut best = d[i];
            if u > 0 {
                best = best.min(d[i - 1] + 3);
            }
            if v > 0 {
                best = best.min(d[i - w] + 3);
                if u > 0 {
                    best = best.min(d[i - w - 1] + 4);
                }
                if u + 1 < w {
                    best = best.min(d[i - w + 1] + 4);
                }
            }
            d[i] = best;
        }
    }
    for v in (0..h).rev() {
        for u in (0..w).rev() {
            let i = v * w + u;
            let mut best = d[i];
            if u + 1 < w {
                best = best.min(d[i + 1] + 3);
            }
            if v + 1 < h {
                best = best.min(d[i + w] + 3);
                if u + 1 < w {
                    best = best.min(d[i + w + 1] + 4);
                }
                if u > 0 {
                    best = best.min(d[i + w - 1] + 4);
                }
            }
            d[i] = best;
        }
    }
    d.into_iter().map(|x| x as f32 / 3.0).collect()
}

impl Scene {
    /// Whether the tool cylinder (radius `cup.radius_m`, from `seal_max_bump_m` to
    /// `cup.tool_length_m` behind the surface point `p`, along `−a`) holds no scene point.
    pub(crate) fn suction_path_clear(
        &self,
        p: &Vec3,
        a: &Vec3,
        cup: &SuctionCup,
        exec: &ExecConfig,
    ) -> bool {
        let cloud = &self.cloud;
        let (t0, t1, r) = (exec.seal_max_bump_m, cup.tool_length_m, cup.radius_m);
        let (e1, e2) = perpendiculars(a);
        let (mut u0, mut u1, mut v0, mut v1) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
        let mut full = false;
        for t in [t0, t1] {
            for e in [e1, -e1, e2, -e2] {
                match cloud.project_uv(&(p - a * t + e * r)) {
                    Some((u, v)) => {
                        u0 = u0.min(u);
                        u1 = u1.max(u);
                        v0 = v0.min(v);
                        v1 = v1.max(v);
                    }
                    None => full = true,
                }
            }
        }
        let (w, h) = (cloud.width as f32, cloud.height as f32);
        if full {
            (u0, u1, v0, v1) = (0.0, w - 1.0, 0.0, h - 1.0);
        }
        let u0 = (u0.floor() - 1.0).clamp(0.0, w - 1.0) as usize;
        let u1 = (u1.ceil() + 1.0).clamp(0.0, w - 1.0) as usize;
        let v0 = (v0.floor() - 1.0).clamp(0.0, h - 1.0) as usize;
        let v1 = (v1.ceil() + 1.0).clamp(0.0, h - 1.0) as usize;
        for v in v0..=v1 {
            let row = v * cloud.width;
            for i in row + u0..=row + u1 {
                if !cloud.valid[i] {
                    continue;
                }
                let d = p - cloud.points[i];
                let t = d.dot(a);
                if t < t0 || t > t1 {
                    continue;
                }
                if (a * t - d).norm_squared() < r * r {
                    return false;
                }
            }
        }
        true
    }
}

/// The surface normal a cup of radius `radius_m` is aimed along at pixel `i`
/// ([`SuctionConfig::patch_noise_m`]).
fn approach_normal(
    cloud: &OrganisedCloud,
    i: usize,
    radius_m: f32,
    noise_m: &[f32; 4],
) -> Option<Vec3> {
    let n = cloud.normal(i)?;
    if noise_m.iter().all(|&s| s <= 0.0) {
        return Some(n);
    }
    PATCH_RADII
        .iter()
        .zip(noise_m)
        .find_map(|(&k, &noise)| {
            cloud
                .patch_plane(i, k * radius_m)
                .filter(|&(_, rms)| rms <= noise.hypot(PATCH_FLATNESS_M))
                .map(|(n, _)| n)
        })
        .or(Some(n))
}

/// Plans suction grasps on `scene` (camera frame), best first, at most `config.top_k`.
/// Deterministic for a given `config.seed`, with any number of rayon threads.
///
/// # Errors
/// Invalid cup or config. No grasp is not an error: see [`PlanOutcome::no_grasp_reason`].
pub fn plan_suction(
    scene: &Scene,
    cup: &SuctionCup,
    config: &SuctionConfig,
) -> Result<PlanOutcome> {
    cup.validate()?;
    config.validate()?;
    if scene.plane.is_none() {
        return Ok(PlanOutcome::none(NoGraspReason::NoSupportPlane));
    }
    if scene.components().is_empty() {
        return Ok(PlanOutcome::none(NoGraspReason::NoObject));
    }
    let cloud = &scene.cloud;
    let s = config.candidate_stride_px;
    let grid: Vec<usize> = (0..cloud.height)
        .step_by(s)
        .flat_map(|v| (0..cloud.width).step_by(s).map(move |u| (u, v)))
        .map(|(u, v)| cloud.index(u, v))
        .filter(|&i| scene.is_object(i) && cloud.normal(i).is_some())
        .collect();
    if grid.is_empty() {
        return Ok(PlanOutcome::none(NoGraspReason::NoCandidate));
    }
    let samples = subsample(grid, config.max_candidates, config.seed);
    let dist_px = edge_distance_px(scene);
    let exec = &config.exec;
    let up = scene.up();
    let results: Vec<std::result::Result<(usize, f32, Vec3), FailureReason>> = samples
        .par_iter()
        .map(|&i| {
            let p = cloud.points[i];
            let n = approach_normal(cloud, i, cup.radius_m, &config.patch_noise_m)
                .ok_or(FailureReason::ApproachAngle)?;
            let a = -n;
            let (quality, flatness) = scene.seal(&p, &a, cup, exec)?;
            let d_m = dist_px[i] * cloud.metres_per_px(p.z);
            let edge = d_m / (d_m + cup.radius_m);
            let reach = (1.0 + a.dot(&-up)) / 2.0;
            let uncertain = config.uncertainty.map_or(1.0, |u| {
                let rms = cloud
                    .patch_plane(i, PATCH_RADII[0] * cup.radius_m)
                    .map_or(f32::INFINITY, |(_, rms)| rms);
                let h = scene.plane.map_or(0.0, |pl| pl.height_m(&p));
                u.weight(d_m, rms, h, cup)
            });
            Ok((i, quality * flatness * edge * reach * uncertain, a))
        })
        .collect();
    let n_candidates = results.len();
    let mut failures = Vec::new();
    let mut cands = Vec::new();
    for r in results {
        match r {
            Ok(c) => cands.push(c),
            Err(f) => failures.push(f),
        }
    }
    let scores: Vec<f32> = cands.iter().map(|c| c.1).collect();
    let order = rank(&scores);
    let pose = |k: usize| {
        let (i, _, a) = cands[k];
        (cloud.points[i], a)
    };
    let mut late_failures = Vec::new();
    let kept = greedy(
        &order,
        config.top_k,
        |k| {
            let (p, a) = pose(k);
            let failure = scene.execute_suction(&p, &a, cup, exec).or_else(|| {
                (!scene.suction_path_clear(&p, &a, cup, exec)).then_some(FailureReason::Collision)
            });
            if let Some(f) = failure {
                late_failures.push(f);
            }
            failure.is_none()
        },
        |a, b| (pose(a).0 - pose(b).0).norm() < config.nms_distance_m,
    );
    let grasps: Vec<Grasp> = kept
        .iter()
        .map(|&k| {
            let (p, a) = pose(k);
            Grasp::Suction(SuctionGrasp {
                success_prob: None,
                score: cands[k].1,
                pose: SuctionPose {
                    point_m: arr(&p),
                    approach: arr(&a),
                },
                base: None,
            })
        })
        .collect();
    let no_grasp_reason = grasps.is_empty().then(|| NoGraspReason::AllRejected {
        candidates: n_candidates,
        failures: tally(failures.into_iter().chain(late_failures)),
    });
    Ok(PlanOutcome {
        grasps,
        no_grasp_reason,
        candidates: n_candidates,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f32, b: f32) -> bool {
        (a - b).abs() <= 1e-5
    }

    /// Each factor of [`DepthUncertainty::weight`] against its closed form (erf values from
    /// tables: erf(2.121320) = 0.997300, erf(0.948683) = 0.820288).
    #[test]
    fn the_uncertainty_weight_is_its_closed_form() {
        let cup = SuctionCup::default(); // r = 10 mm, compliance 15 mm
        let u = DepthUncertainty {
            flat_sigma_m: 0.005,
            relief_sigma: 0.0,
            edge_margin_m: 0.008,
        };
        // the ring's clearance: none within the margin; (18 − 8) / (10 + 10) beyond it
        assert_eq!(u.weight(0.008, 0.0, 0.0, &cup), 0.0);
        assert_eq!(u.weight(0.005, 0.0, 0.0, &cup), 0.0);
        let reach = 0.997_300;
        assert!(close(u.weight(0.018, 0.0, 0.0, &cup), 0.5 * reach));
        // the wider patch's flatness: exp(−rms / 2 mm)
        let w = u.weight(0.018, 0.002, 0.0, &cup);
        assert!(close(w, 0.5 * reach * (-1.0f32).exp()), "{w}");
        // reaching within the compliance at 0.1 m height with a relief σ of 0.1:
        // σ_z = hypot(5, 10) mm, erf(15 / (√2 · 11.18)) = erf(0.948683)
        let tall = DepthUncertainty {
            relief_sigma: 0.1,
            ..u
        };
        let w = tall.weight(0.018, 0.0, 0.1, &cup);
        assert!(close(w, 0.5 * 0.820_288), "{w}");
        // below the plane counts as on it
        assert!(close(tall.weight(0.018, 0.0, -0.05, &cup), 0.5 * reach));
    }
}
