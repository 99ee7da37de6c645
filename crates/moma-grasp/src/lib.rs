//! # moma-grasp: grasps from (aligned) metric depth, and their proxy scoring
//!
//! Geometry only, no file I/O. One frame flows: [`MetricDepth`](moma_core::MetricDepth) +
//! [`Intrinsics`](moma_core::Intrinsics) (+ optional object [`Mask`](moma_core::Mask)) →
//! [`Scene`] (organised cloud, normals, silhouette edges, support plane, object components) →
//! [`plan_parallel`] / [`plan_suction`] → [`PlanOutcome`] (grasps best first, or a reason) →
//! optionally [`PlanOutcome::set_base`] with [`Extrinsics`] → [`score_grasp`] against a scene
//! built from the ground-truth depth of the same frame (with the same mask).
//!
//! ## Conventions
//! - **Frames.** Camera frame: x right, y down, z forward, metres. Pixel `(u, v)` = (column, row).
//!   "Up" is the unit normal of the dominant support plane (table / tote floor), pointing towards
//!   the camera. The base frame is `p_base = R p_cam + t` from a checked rigid [`Extrinsics`].
//! - **Objects.** With a mask: masked pixels with valid depth. Without: pixels more than
//!   [`SceneConfig::min_object_height_m`] (10 mm) above the plane in 8-connected regions of at
//!   least [`SceneConfig::min_object_px`] (200) pixels that do not touch the image border (unless
//!   [`SceneConfig::keep_border_objects`]) and do not enclose an opening of a container's size
//!   ([`SceneConfig::container_opening_m2`]: a bin's walls). A grasp is never planned on the
//!   bare table.
//! - **Scene volume (2.5-D).** A 3-D point is inside the scene when it lies at or behind the
//!   observed surface at its pixel (tolerance [`ExecConfig::occupancy_tol_m`], 2 mm); holes in the
//!   depth and rays leaving the image are free space.
//! - **Contacts and normals (docs/method.md §8, shared by planner and scorer).** A finger closing along
//!   the closing line (through the grasp centre) touches where the line first enters the scene
//!   from free space. If the free sample before lies on a farther pixel (or a hole), the contact is
//!   on a silhouette and its normal is the horizontal (⟂ up) direction of the depth-image
//!   gradient across the edge, pointing out of the object; otherwise it is the observed surface
//!   normal there. A contact is on the object when an object pixel lies within
//!   [`ExecConfig::object_tolerance_px`] (2 px) of it. The contacts are antipodal at μ when both normals lie within `atan μ` of the
//!   contact line (pointing out of the object); the smallest passing μ of
//!   {0.2, 0.4, …, 1.2} is reported, success at μ = 0.8 ([`ScoreConfig::mu`]).
//! - **Parallel jaw** ([`ParallelJaw`], Robotiq 2F-85 defaults): grasp frame x = approach,
//!   y = closing, z = x × y, origin at the midpoint of the two contacts (`center_m`); the
//!   fingertips reach `contact_to_tip_m` (10 mm) past the contact line. Fails on any point in a
//!   finger or the palm (collision), fewer than 10 points between the fingers (empty), no object
//!   point between them or a contact off the object (missed object), or non-antipodal contacts.
//! - **Planning on aligned depth.** Depth aligned from a depth-model prediction has soft
//!   silhouettes (spread over 3–5 px), normals rotating across them and a few mm of correlated
//!   noise (docs/method.md §6). [`plan_parallel`] first applies the scorer's rules to the planning
//!   depth (then again with the steeper [`ParallelConfig::fallback_tilt_angles_deg`], for objects
//!   whose top is blocked); when that finds no grasp, a tolerant pass
//!   ([`ParallelConfig::tolerant_pass`]) detects silhouettes as a depth drop over a small window,
//!   averages their normals over a larger disc, shortens the fingertips by a collision margin,
//!   ignores mixed silhouette pixels (blends of object and background in mid-air behind the
//!   object) as obstacles beside the fingers (not in the palm), and adds top-down footprint
//!   candidates ([`FootprintConfig`]). The
//!   scorer's rules never change.
//! - **Suction** ([`SuctionCup`], r = 10 mm, compliance 15 mm): `approach` points into the
//!   surface. Seal: 72 ring points at the cup radius in the plane ⟂ approach, each within 5 mm of
//!   the contact plane, nothing inside the ring more than 5 mm above it; quality
//!   exp(−1e5·var(heights)). Execution: the hit along the approach ray must be on an object,
//!   within ±compliance of the planned point, seal on the hit, approach ≤ 30° from its normal.
//! - **Determinism.** Every random choice uses a `seed` field (ChaCha8); parallel loops collect in
//!   input order, so results do not depend on the number of rayon threads.
//!
//! Scores from [`score_grasp`] are a *proxy* for robot success, not robot results.
//!
//! ```
//! use moma_core::{Intrinsics, MetricDepth};
//! use moma_grasp::{Grasp, GraspRequest, Gripper, SuctionCup, plan_grasps};
//! use ndarray::Array2;
//!
//! // A 5 cm tall box on a table 0.70 m in front of the camera (metric depth, metres).
//! let cam = Intrinsics { width: 160, height: 120, fx: 150.0, fy: 150.0, cx: 79.5, cy: 59.5 };
//! let depth = MetricDepth::new(Array2::from_shape_fn((120, 160), |(v, u)| {
//!     if (60..100).contains(&u) && (40..80).contains(&v) { 0.65 } else { 0.70 }
//! }));
//! let request = GraspRequest::new(Gripper::Suction(SuctionCup::default()));
//! let (_scene, outcome) = plan_grasps(&depth, &cam, None, &request)?;
//! let Some(Grasp::Suction(best)) = outcome.grasps.first() else { panic!("no grasp") };
//! // on the box's top, approached along the optical axis
//! assert!((best.pose.point_m[2] - 0.65).abs() < 0.005);
//! assert!(best.pose.approach[2] > 0.95);
//! # Ok::<(), moma_grasp::GraspError>(())
//! ```
//!
//! Known limitation: without a mask, anything more than 10 mm above the support plane is an
//! object, but for regions touching the image border and the walls of a container fully in view
//! ([`SceneConfig::container_opening_m2`]): robot parts, a wall beside the table, an object
//! touching a bin's wall without a flat top below its rim (dropped with the wall); pass a mask
//! on such scenes.

pub mod check;
pub mod cloud;
pub mod contact;
pub mod error;
pub mod extrinsics;
pub mod footprint;
pub mod grasp;
pub mod gripper;
pub mod nms;
pub mod objects;
pub mod parallel;
pub mod plane;
pub mod render;
pub mod robust;
pub mod scene;
pub mod score;
pub mod suction;

pub use check::{GraspCheck, calibration_frame_check, grasp_check, grasp_check_on};
pub use cloud::{CloudConfig, OrganisedCloud, Vec3};
pub use contact::{ExecConfig, MU_GRID};
pub use error::{GraspError, Result};
pub use extrinsics::Extrinsics;
pub use footprint::FootprintConfig;
pub use grasp::{
    FailureReason, Grasp, NoGraspReason, ParallelGrasp, ParallelPose, PlanOutcome, SuctionGrasp,
    SuctionPose,
};
pub use gripper::{Gripper, GripperKind, ParallelJaw, SuctionCup};
pub use objects::{MIN_TRIAL_COMPONENT_PX, components_8, mask_components};
pub use parallel::{ParallelConfig, plan_parallel, plan_parallel_tolerant};
pub use plane::{PlaneConfig, SupportPlane, fit_support_plane};
pub use robust::{
    DEFAULT_GRASP_DRAWS, DEFAULT_ROBUST_CANDIDATES, DEFAULT_SUCTION_TIE_TOLERANCE,
    DEFAULT_TIE_TOLERANCE, GraspQuality, GraspRequest, NOISE_GUARD_FROM_M, NOISE_GUARD_FULL_M,
    default_tie_tolerance, draw_region, plan_grasps, plan_on_scene, planning_depth,
    posterior_success_prob, rank, share_of_draws, success_probabilities, suction_noise_guard,
};
pub use scene::{ObjectComponent, Scene, SceneConfig};
pub use score::{GraspScore, ScoreConfig, no_grasp, score_grasp, score_parallel, score_suction};
pub use suction::{DepthUncertainty, SUCTION_EDGE_MARGIN_M, SuctionConfig, plan_suction};
