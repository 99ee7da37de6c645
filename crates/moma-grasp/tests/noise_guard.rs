//! The suction planner's guards against short-range noise follow the noise the error model
//! expects within one cup radius (`suction_noise_guard`): none under 0.5 mm (the depth is
//! planned as exact), all of them from 1.5 mm on, in proportion between. Closed forms on a
//! model whose short-range noise is one field: the noise within a patch is then σ itself.

mod common;

use common::intrinsics;
use moma_core::error_model::Roi;
use moma_core::{DepthErrorModel, MetricDepth};
use moma_grasp::{
    GraspRequest, Gripper, NOISE_GUARD_FROM_M, NOISE_GUARD_FULL_M, ParallelJaw, SuctionCup,
    planning_depth, suction_noise_guard,
};
use ndarray::Array2;

/// All of σ in the fine field (2 px): the noise within any patch of ≥ 2 px is σ.
fn model(sigma_m: f64) -> DepthErrorModel {
    DepthErrorModel {
        sigma_flat_m: sigma_m,
        sigma_dense_m: Some(sigma_m),
        depth_ref_m: 0.7,
        depth_exponent: 0.0,
        variance_shares: [0.0, 1.0, 0.0, 0.0],
        scales_px: [2.0, 8.0, 32.0],
        ..DepthErrorModel::default()
    }
}

/// A 0.7 m plane with ±2 mm of alternating bumps (what the smoothing averages out) and a
/// 40 mm step (an edge it keeps).
fn rough_depth() -> MetricDepth {
    let (h, w) = (common::H, common::W);
    MetricDepth::new(Array2::from_shape_fn((h, w), |(v, u)| {
        let bump = if (u / 3 + v / 3) % 2 == 0 {
            0.002
        } else {
            -0.002
        };
        let step = if u > w / 2 { -0.04 } else { 0.0 };
        0.7 + bump + step
    }))
}

#[test]
fn the_guard_follows_the_noise_within_a_cup_radius() {
    let cup = SuctionCup::default();
    // a 10 mm cup at 0.7 m under fx = 600 px: 8.6 px, more than the field's 2 px
    let fx = intrinsics().fx;
    let at = |sigma_m: f64| suction_noise_guard(&model(sigma_m), 0.7, &cup, fx);
    assert_eq!(at(0.0), 0.0);
    assert_eq!(at(0.0004), 0.0);
    assert_eq!(at(NOISE_GUARD_FROM_M), 0.0);
    for sigma in [0.00075, 0.001, 0.00125] {
        let expected =
            ((sigma - NOISE_GUARD_FROM_M) / (NOISE_GUARD_FULL_M - NOISE_GUARD_FROM_M)) as f32;
        assert!(
            (at(sigma) - expected).abs() < 1e-6,
            "{sigma}: {}",
            at(sigma)
        );
    }
    assert_eq!(at(NOISE_GUARD_FULL_M), 1.0);
    assert_eq!(at(0.004), 1.0);
    // only the noise within the patch counts: the same σ as an offset (it moves the whole
    // patch and tilts nothing) needs no guard
    let offset = DepthErrorModel {
        variance_shares: [1.0, 0.0, 0.0, 0.0],
        ..model(0.004)
    };
    assert_eq!(suction_noise_guard(&offset, 0.7, &cup, fx), 0.0);
    // the bounds, written out: 0.5 mm and 1.5 mm (docs/grasping.md)
    assert_eq!((NOISE_GUARD_FROM_M, NOISE_GUARD_FULL_M), (0.0005, 0.0015));
    // a field longer than the cup's radius: only its variation within the radius counts,
    // σ·√(r / s) with r = 0.01 m · 600 px / 0.7 m = 8.571 px and s = 32 px. At σ = 2 mm that
    // is 1.035 mm of noise, a guard of 0.535 (a diameter instead of a radius would give 0.964)
    let long = DepthErrorModel {
        variance_shares: [0.0, 0.0, 0.0, 1.0],
        ..model(0.002)
    };
    let r_px = 0.01 * fx / 0.7;
    let noise = 0.002 * (r_px / 32.0).sqrt();
    let want = ((noise - 0.0005) / 0.001) as f32;
    let got = suction_noise_guard(&long, 0.7, &cup, fx);
    assert!(
        (got - want).abs() < 1e-5 && (got - 0.535).abs() < 1e-3,
        "{got} vs {want}"
    );
}

#[test]
fn the_suction_planning_depth_is_smoothed_in_proportion_to_the_guard() {
    let depth = rough_depth();
    let (h, w) = depth.depth_m.dim();
    let suction = |sigma_m: f64| {
        GraspRequest::new(Gripper::Suction(SuctionCup::default()))
            .with_error_model(Some(model(sigma_m)))
    };
    let planned = |sigma_m: f64| {
        planning_depth(&depth, &intrinsics(), &suction(sigma_m))
            .depth_m
            .clone()
    };
    // under the guard: the expected truth without smoothing, which for this model (no relief,
    // no edge share) is the depth itself
    let exact = planned(0.0003);
    assert_eq!(exact, depth.depth_m);
    // from the full guard on: today's smoothing, bit for bit
    let m = model(0.003);
    let smooth_full = m.expected_truth_map(depth.depth_m.view(), true);
    assert_eq!(planned(0.003), smooth_full);
    assert_ne!(
        smooth_full, depth.depth_m,
        "the control: the bumps are smoothed"
    );
    // against the scene itself: away from the step and the borders the ±2 mm bumps are
    // averaged to within 0.5 mm of the 0.7 m plane, and the 40 mm step stays where it is
    let margin = 12;
    for ((v, u), &z) in smooth_full.indexed_iter() {
        if v < margin || v + margin >= h || u < margin || u + margin >= w {
            continue;
        }
        let plane = if u > w / 2 { 0.66 } else { 0.7 };
        if u.abs_diff(w / 2) > margin {
            assert!((z - plane).abs() < 0.0005, "({u}, {v}): {z}");
        }
    }
    let row = h / 2;
    assert!(smooth_full[[row, w / 2]] > 0.69 && smooth_full[[row, w / 2 + 1]] < 0.67);
    // between: the blend, with the model's own smoothing at that σ
    let sigma = 0.001;
    let guard = suction_noise_guard(&model(sigma), 0.7, &SuctionCup::default(), intrinsics().fx);
    assert!((guard - 0.5).abs() < 1e-6, "{guard}");
    let smooth = model(sigma).expected_truth(depth.depth_m.view(), Roi::full(w, h));
    let half = planned(sigma);
    for ((&got, &z), &s) in half.iter().zip(&depth.depth_m).zip(&smooth) {
        let want = z + 0.5 * (s - z);
        assert!((got - want).abs() < 1e-6, "{got} vs {want}");
    }
    assert_ne!(half, depth.depth_m);
    assert_ne!(half, smooth);
    // the parallel jaw never plans on a smoothed depth
    let jaw = GraspRequest::new(Gripper::Parallel(ParallelJaw::default()))
        .with_error_model(Some(model(0.003)));
    assert_eq!(
        planning_depth(&depth, &intrinsics(), &jaw).depth_m,
        depth.depth_m
    );
}
