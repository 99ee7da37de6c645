//! Proxy scoring: a planned grasp executed "in imagination" on the ground-truth depth of the same
//! frame (docs/method.md §8, graspnetAPI / suctionnetAPI rules). A proxy, not a robot.

use serde::{Deserialize, Serialize};

use crate::cloud::Vec3;
use crate::contact::{ExecConfig, JawPose};
use crate::error::{GraspError, Result, positive};
use crate::grasp::{FailureReason, Grasp, ParallelPose, SuctionPose};
use crate::gripper::{Gripper, ParallelJaw, SuctionCup};
use crate::scene::Scene;

/// Scoring settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ScoreConfig {
    /// Execution rules (the same the planners use).
    pub exec: ExecConfig,
    /// Friction coefficient at which a parallel grasp counts as a success. Default 0.8.
    pub mu: f32,
}

impl Default for ScoreConfig {
    fn default() -> Self {
        Self {
            exec: ExecConfig::default(),
            mu: 0.8,
        }
    }
}

/// The outcome of one proxy execution.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GraspScore {
    /// Whether the grasp succeeds.
    pub success: bool,
    /// Why it fails; `None` on success.
    pub failure: Option<FailureReason>,
    /// Parallel grasps: the smallest μ in {0.2, 0.4, …, 1.2} at which the contacts are antipodal,
    /// when the fingers are collision-free, non-empty and on the object; `None` otherwise.
    pub min_mu: Option<f32>,
}

fn unit(name: &str, v: [f32; 3]) -> Result<Vec3> {
    let v = Vec3::from(v);
    let n = v.norm();
    if !(n.is_finite() && n > 1e-6) {
        return Err(GraspError::InvalidGrasp(format!(
            "{name} {v:?} is zero or not finite"
        )));
    }
    Ok(v / n)
}

fn point(name: &str, v: [f32; 3]) -> Result<Vec3> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(Vec3::from(v))
    } else {
        Err(GraspError::InvalidGrasp(format!(
            "{name} {v:?} is not finite"
        )))
    }
}

/// Executes a parallel-jaw pose on `gt`.
///
/// # Errors
/// Invalid gripper/config, or a malformed pose (zero vectors, approach ∥ closing, width ≤ 0).
pub fn score_parallel(
    gt: &Scene,
    pose: &ParallelPose,
    jaw: &ParallelJaw,
    config: &ScoreConfig,
) -> Result<GraspScore> {
    jaw.validate()?;
    config.exec.validate()?;
    positive("mu", config.mu, GraspError::InvalidConfig)?;
    // The fingers march over the width: bounded like every gripper size (no jaw opens wider).
    crate::gripper::gripper_size("width_m", pose.width_m, GraspError::InvalidGrasp)?;
    let a = unit("approach", pose.approach)?;
    let b = unit("closing", pose.closing)?;
    let b = b - a * a.dot(&b);
    if b.norm() < 1e-3 {
        return Err(GraspError::InvalidGrasp(
            "closing is parallel to approach".into(),
        ));
    }
    let jp = JawPose {
        center: point("center_m", pose.center_m)?,
        approach: a,
        closing: b.normalize(),
        width: pose.width_m,
    };
    let run = gt.execute_parallel(&jp, jaw, &config.exec, config.mu, false, None);
    Ok(GraspScore {
        success: run.failure.is_none(),
        failure: run.failure,
        min_mu: run.min_mu,
    })
}

/// Executes a suction pose on `gt`.
///
/// # Errors
/// Invalid cup/config, or a malformed pose.
pub fn score_suction(
    gt: &Scene,
    pose: &SuctionPose,
    cup: &SuctionCup,
    config: &ScoreConfig,
) -> Result<GraspScore> {
    cup.validate()?;
    config.exec.validate()?;
    let a = unit("approach", pose.approach)?;
    let p = point("point_m", pose.point_m)?;
    let failure = gt.execute_suction(&p, &a, cup, &config.exec);
    Ok(GraspScore {
        success: failure.is_none(),
        failure,
        min_mu: None,
    })
}

/// Executes `grasp` on `gt` with the matching gripper.
///
/// # Errors
/// A grasp kind that does not match `gripper`, or the errors of [`score_parallel`] /
/// [`score_suction`].
pub fn score_grasp(
    gt: &Scene,
    grasp: &Grasp,
    gripper: &Gripper,
    config: &ScoreConfig,
) -> Result<GraspScore> {
    match (grasp, gripper) {
        (Grasp::Parallel(g), Gripper::Parallel(j)) => score_parallel(gt, &g.pose, j, config),
        (Grasp::Suction(g), Gripper::Suction(c)) => score_suction(gt, &g.pose, c, config),
        (Grasp::Parallel(_), Gripper::Suction(_)) => Err(GraspError::InvalidGripper(
            "a parallel grasp cannot be scored with a suction cup".into(),
        )),
        (Grasp::Suction(_), Gripper::Parallel(_)) => Err(GraspError::InvalidGripper(
            "a suction grasp cannot be scored with a parallel jaw".into(),
        )),
    }
}

/// The result of a trial where the planner found no grasp: a failure with
/// [`FailureReason::NoGrasp`].
pub fn no_grasp() -> GraspScore {
    GraspScore {
        success: false,
        failure: Some(FailureReason::NoGrasp),
        min_mu: None,
    }
}
