//! The grasp check of a frame whose truth is known: the grasps planned on its aligned depth, as
//! [`plan_grasps`] plans them for a robot, executed on its sensor depth by the scorer's rules
//! ([`score_grasp`], the PROXY of docs/method.md §8).
//!
//! The one frame of a fixed cell with both a prediction and a truth is the calibration frame,
//! so this is what the cell can say, at calibration time, about grasping from RGB there: how many
//! of the grasps hold and how their `success_prob` compares. It is in-sample for the alignment
//! (the calibration was fitted on this frame). On the SIMULATED shared sets its suction rate
//! orders the sets as the robot's top-1 rates do and sits 0.04–0.22 under them; its parallel-jaw
//! rate does not order them (docs/grasping.md, "What runs"): a look at the grasps and their
//! failures on one's own cell, not a forecast.

use std::collections::BTreeMap;

use moma_core::{AlignOptions, Calibration, Intrinsics, Mask, MetricDepth, PredictionInput};
use serde::{Deserialize, Serialize};

use crate::error::{GraspError, Result};
use crate::grasp::FailureReason;
use crate::gripper::Gripper;
use crate::robust::{GraspRequest, plan_grasps};
use crate::scene::Scene;
use crate::score::score_grasp;

/// The outcome of [`grasp_check`] (PROXY scores, not robot trials); its JSON is what `moma
/// calibrate --grasp-check --json` and Python's `grasp_check` give.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GraspCheck {
    /// `parallel` or `suction`.
    pub gripper: String,
    /// Always `proxy`: executed by the scorer's rules on a depth map, not by a robot.
    pub scores: String,
    /// Grasps planned on the aligned depth (at most the request's `top_k`).
    pub grasps: usize,
    /// Of those, the grasps that succeed on the truth.
    pub successes: usize,
    /// successes / grasps (`None` without a grasp).
    pub success_rate: Option<f64>,
    /// Mean `success_prob` of the planned grasps (`None` without an error model or a grasp).
    pub mean_success_prob: Option<f64>,
    /// The failures on the truth, by reason (`seal_broken`, `collision`, …).
    pub failures: BTreeMap<String, usize>,
    /// Why the planner returned no grasp, when it returned none.
    pub no_grasp_reason: Option<String>,
    /// What the planning scene left out, as `moma grasp` notes it: regions dropped for touching
    /// the image border ([`Scene::border_note`]) or for enclosing a container's opening
    /// ([`Scene::container_note`]). Without a mask the check counts only the grasps on the
    /// objects the planner keeps, so these say which were not tried. Empty when nothing was
    /// dropped (and in files written before the field existed).
    #[serde(default)]
    pub notes: Vec<String>,
}

/// Plans on `aligned` as `request` says ([`plan_grasps`], object `mask` if given) and executes
/// every returned grasp on `truth` (the same camera and `mask`) with `request.score`.
///
/// # Errors
/// An invalid request; a scene that cannot be built from `aligned` or `truth` (sizes that do
/// not match `intrinsics`, no valid depth). Callers name the files (`moma calibrate` does).
pub fn grasp_check(
    aligned: &MetricDepth,
    truth: &MetricDepth,
    intrinsics: &Intrinsics,
    mask: Option<&Mask>,
    request: &GraspRequest,
) -> Result<GraspCheck> {
    let truth_scene = Scene::build(truth, intrinsics, mask, &request.scene)?;
    grasp_check_on(aligned, &truth_scene, intrinsics, mask, request)
}

/// The calibration frame's check: `pred` aligned one-shot by `calibration` (no re-alignment:
/// the calibration frame is its anchors' own frame), planned with `gripper` under the frame's
/// error model (robust where the calibration has one, nominal otherwise), the default request
/// otherwise but `seed`, and checked on `truth` ([`grasp_check`]). What `moma calibrate
/// --grasp-check` and Python's `grasp_check` run.
///
/// # Errors
/// [`GraspError::Align`] when `pred` does not fit the calibration (size, kind); as
/// [`grasp_check`].
#[allow(clippy::too_many_arguments)] // the check's inputs, each a different thing
pub fn calibration_frame_check<'p>(
    calibration: &Calibration,
    pred: impl Into<PredictionInput<'p>>,
    truth: &MetricDepth,
    intrinsics: &Intrinsics,
    mask: Option<&Mask>,
    gripper: Gripper,
    seed: u64,
) -> Result<GraspCheck> {
    let aligned = calibration
        .aligned(pred, &AlignOptions::default())
        .map_err(GraspError::Align)?;
    let mut request = GraspRequest::new(gripper).with_error_model(aligned.error_model);
    request.seed = seed;
    grasp_check(&aligned.depth, truth, intrinsics, mask, &request)
}

/// [`grasp_check`] on a truth scene already built (with the same `mask` and `request.scene`),
/// for a caller that checks one frame many times (`moma grasp-eval`: every calibration of a
/// set checks its calibration frame).
///
/// # Errors
/// An invalid request; a planning scene that cannot be built from `aligned`.
pub fn grasp_check_on(
    aligned: &MetricDepth,
    truth_scene: &Scene,
    intrinsics: &Intrinsics,
    mask: Option<&Mask>,
    request: &GraspRequest,
) -> Result<GraspCheck> {
    let (scene, outcome) = plan_grasps(aligned, intrinsics, mask, request)?;
    let mut successes = 0;
    let mut failures = BTreeMap::new();
    for g in &outcome.grasps {
        let score = score_grasp(truth_scene, g, &request.gripper, &request.score)?;
        if score.success {
            successes += 1;
        } else {
            let reason = score.failure.unwrap_or(FailureReason::NoGrasp);
            *failures.entry(reason.to_string()).or_default() += 1;
        }
    }
    let probs: Vec<f64> = outcome
        .grasps
        .iter()
        .filter_map(|g| g.success_prob().map(f64::from))
        .collect();
    let grasps = outcome.grasps.len();
    Ok(GraspCheck {
        gripper: request.gripper.kind_name().to_string(),
        scores: "proxy".to_string(),
        grasps,
        successes,
        success_rate: (grasps > 0).then(|| successes as f64 / grasps as f64),
        mean_success_prob: (!probs.is_empty())
            .then(|| probs.iter().sum::<f64>() / probs.len() as f64),
        failures,
        no_grasp_reason: outcome.no_grasp_reason.as_ref().map(ToString::to_string),
        notes: scene.notes().into_iter().map(|(_, note)| note).collect(),
    })
}
