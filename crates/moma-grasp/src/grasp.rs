//! Grasp types, serialised exactly as `moma grasp --json` writes them, and the planners' outcome.

use serde::{Deserialize, Serialize};

use crate::cloud::Vec3;
use crate::extrinsics::Extrinsics;

/// A parallel-jaw pose: camera frame (or base frame under `"base"`), metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ParallelPose {
    /// Midpoint of the two planned contact points, metres.
    pub center_m: [f32; 3],
    /// Unit vector along which the gripper moves towards the object.
    pub approach: [f32; 3],
    /// Unit vector along which the fingers close (perpendicular to `approach`).
    pub closing: [f32; 3],
    /// Opening before closing, metres.
    pub width_m: f32,
}

/// A suction pose: camera frame (or base frame under `"base"`), metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SuctionPose {
    /// The planned contact point on the surface, metres.
    pub point_m: [f32; 3],
    /// Unit approach vector, pointing into the surface.
    pub approach: [f32; 3],
}

/// A planned parallel-jaw grasp.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ParallelGrasp {
    /// Planner score in `[0, 1]`, higher is better.
    pub score: f32,
    /// Estimated success probability in `(0, 1)` under the depth's error model (from the error
    /// model's depth draws on which the grasp succeeds by the scorer's rules: `(successes + 1)
    /// / (draws + 2)`, [`crate::posterior_success_prob`]); `null` when no error model was given.
    #[serde(default)]
    pub success_prob: Option<f32>,
    /// The pose in the camera frame.
    #[serde(flatten)]
    pub pose: ParallelPose,
    /// The same pose in the robot base frame, when extrinsics were given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub base: Option<ParallelPose>,
}

/// A planned suction grasp.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SuctionGrasp {
    /// Planner score in `[0, 1]`, higher is better.
    pub score: f32,
    /// Estimated success probability in `(0, 1)` under the depth's error model (from the error
    /// model's depth draws on which the grasp succeeds by the scorer's rules: `(successes + 1)
    /// / (draws + 2)`, [`crate::posterior_success_prob`]); `null` when no error model was given.
    #[serde(default)]
    pub success_prob: Option<f32>,
    /// The pose in the camera frame.
    #[serde(flatten)]
    pub pose: SuctionPose,
    /// The same pose in the robot base frame, when extrinsics were given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub base: Option<SuctionPose>,
}

/// A planned grasp; JSON `{"kind":"parallel",…}` or `{"kind":"suction",…}` (docs/grasping.md).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Grasp {
    /// Parallel jaw.
    Parallel(ParallelGrasp),
    /// Suction.
    Suction(SuctionGrasp),
}

impl Grasp {
    /// The planner score.
    pub fn score(&self) -> f32 {
        match self {
            Grasp::Parallel(g) => g.score,
            Grasp::Suction(g) => g.score,
        }
    }

    /// The estimated success probability, when an error model was given.
    pub fn success_prob(&self) -> Option<f32> {
        match self {
            Grasp::Parallel(g) => g.success_prob,
            Grasp::Suction(g) => g.success_prob,
        }
    }

    /// Sets the estimated success probability.
    pub fn set_success_prob(&mut self, p: Option<f32>) {
        match self {
            Grasp::Parallel(g) => g.success_prob = p,
            Grasp::Suction(g) => g.success_prob = p,
        }
    }

    /// The camera-frame grasp point (parallel centre or suction point), metres.
    pub fn point_m(&self) -> [f32; 3] {
        match self {
            Grasp::Parallel(g) => g.pose.center_m,
            Grasp::Suction(g) => g.pose.point_m,
        }
    }

    /// Fills `base` with the pose mapped by `extrinsics` (camera → base).
    pub fn set_base(&mut self, extrinsics: &Extrinsics) {
        let p = |a: [f32; 3]| arr(&extrinsics.point(&Vec3::from(a)));
        let d = |a: [f32; 3]| arr(&extrinsics.direction(&Vec3::from(a)));
        match self {
            Grasp::Parallel(g) => {
                g.base = Some(ParallelPose {
                    center_m: p(g.pose.center_m),
                    approach: d(g.pose.approach),
                    closing: d(g.pose.closing),
                    width_m: g.pose.width_m,
                });
            }
            Grasp::Suction(g) => {
                g.base = Some(SuctionPose {
                    point_m: p(g.pose.point_m),
                    approach: d(g.pose.approach),
                });
            }
        }
    }
}

#[inline]
pub(crate) fn arr(v: &Vec3) -> [f32; 3] {
    [v.x, v.y, v.z]
}

/// Why a planner returned no grasp (a normal result, not an error).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NoGraspReason {
    /// No support plane was found, so "up" and "above the table" are undefined.
    NoSupportPlane,
    /// No object pixel: nothing stands more than [`crate::SceneConfig::min_object_height_m`]
    /// above the support plane (or the mask is empty there).
    NoObject,
    /// Objects exist but no candidate could be formed on them (no silhouette edge for a parallel
    /// jaw, no pixel with a normal for suction).
    NoCandidate,
    /// Every grasp's success probability under the error model is below the minimum asked.
    BelowMinSuccessProb {
        /// Grasps below the minimum.
        candidates: usize,
        /// The best success probability found.
        best_success_prob: f32,
        /// The minimum asked.
        min_success_prob: f64,
        /// Depth draws per grasp: no probability exceeds `(draws + 1) / (draws + 2)`
        /// ([`crate::posterior_success_prob`]); 0 in reasons written before it was recorded.
        #[serde(default)]
        draws: usize,
    },
    /// Every candidate failed a check; the counts say which.
    AllRejected {
        /// Candidates examined.
        candidates: usize,
        /// Failure counts by reason, largest first.
        failures: Vec<(FailureReason, usize)>,
    },
}

impl std::fmt::Display for NoGraspReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            NoGraspReason::NoSupportPlane => write!(f, "no support plane found"),
            NoGraspReason::NoObject => {
                write!(
                    f,
                    "no object: nothing stands more than the object height (10 mm unless \
                     configured) above the support plane; objects thinner than that (a phone, \
                     a spatula) need an object mask"
                )
            }
            NoGraspReason::NoCandidate => write!(f, "no grasp candidate on the objects"),
            NoGraspReason::BelowMinSuccessProb {
                candidates,
                best_success_prob,
                min_success_prob,
                draws,
            } => {
                write!(
                    f,
                    "all {candidates} grasps have a success probability below the minimum \
                     {min_success_prob:.2} (best {best_success_prob:.2})"
                )?;
                // in f64, as the grasps are compared with the minimum (a minimum of 5/6 with 4
                // draws is not reached by the f32 5/6 that a grasp holding on every draw has)
                let highest = f64::from(crate::posterior_success_prob(1.0, *draws));
                if *draws > 0 && *min_success_prob > highest {
                    // a minimum no grasp can reach, however good: say so, not "re-image"
                    write!(
                        f,
                        ": with {draws} depth draws no grasp can exceed {highest:.2}; lower the \
                         minimum or raise the draws (`--grasp-draws`, Python's `grasp_draws`)"
                    )
                } else {
                    write!(
                        f,
                        ": re-image the scene, or lower the minimum (`--min-success-prob`, \
                         Python's `min_success_prob`)"
                    )
                }
            }
            NoGraspReason::AllRejected {
                candidates,
                failures,
            } => {
                write!(f, "all {candidates} candidates rejected (")?;
                for (k, (r, n)) in failures.iter().enumerate() {
                    if k > 0 {
                        write!(f, ", ")?;
                    }
                    write!(f, "{r}: {n}")?;
                }
                write!(f, ")")
            }
        }
    }
}

/// A planner's result: grasps best first (possibly none) and, when none, why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlanOutcome {
    /// Grasps, best first, at most the configured top-K.
    pub grasps: Vec<Grasp>,
    /// Why `grasps` is empty; `None` when it is not.
    pub no_grasp_reason: Option<NoGraspReason>,
    /// Candidates the planner evaluated.
    pub candidates: usize,
}

impl PlanOutcome {
    pub(crate) fn none(reason: NoGraspReason) -> Self {
        Self {
            grasps: Vec::new(),
            no_grasp_reason: Some(reason),
            candidates: 0,
        }
    }

    /// Fills every grasp's `base` pose (camera → base).
    pub fn set_base(&mut self, extrinsics: &Extrinsics) {
        for g in &mut self.grasps {
            g.set_base(extrinsics);
        }
    }
}

/// Why a grasp fails, in planning or in proxy execution (docs/method.md §8).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FailureReason {
    /// A point lies inside a finger, the palm or (suction) the tool cylinder.
    Collision,
    /// Fewer than the minimum points between the fingers.
    Empty,
    /// The closing region / the suction hit holds no object pixel (table only, or nothing).
    MissedObject,
    /// The contacts are not antipodal within the friction cone at the required μ.
    NotAntipodal,
    /// Suction: the surface was hit more than the compliance before the planned point.
    CupCrash,
    /// Suction: no surface within the compliance beyond the planned point.
    NotReached,
    /// Suction: the ring at the cup radius is incomplete, uneven, or something pokes into it.
    SealBroken,
    /// Suction: approach more than the allowed angle from the surface normal.
    ApproachAngle,
    /// A trial where the planner found no grasp.
    NoGrasp,
}

impl FailureReason {
    /// snake_case name, as in JSON.
    pub fn as_str(&self) -> &'static str {
        match self {
            FailureReason::Collision => "collision",
            FailureReason::Empty => "empty",
            FailureReason::MissedObject => "missed_object",
            FailureReason::NotAntipodal => "not_antipodal",
            FailureReason::CupCrash => "cup_crash",
            FailureReason::NotReached => "not_reached",
            FailureReason::SealBroken => "seal_broken",
            FailureReason::ApproachAngle => "approach_angle",
            FailureReason::NoGrasp => "no_grasp",
        }
    }
}

impl std::fmt::Display for FailureReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Counts failures by reason, largest count first (ties in enum order).
pub(crate) fn tally(failures: impl Iterator<Item = FailureReason>) -> Vec<(FailureReason, usize)> {
    let mut counts: std::collections::BTreeMap<FailureReason, usize> = Default::default();
    for f in failures {
        *counts.entry(f).or_default() += 1;
    }
    let mut v: Vec<_> = counts.into_iter().collect();
    v.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    v
}
