//! Robust variants in the evaluation: rows `robust-<kind>` next to the one-shot rows, only for
//! methods that support robust fitting, and SIMULATED ground-truth outliers on the calibration
//! frame that hurt the least-squares fit more than the robust ones.

mod common;

use common::*;
use moma_core::align::robust::{Robust, RobustKind};
use moma_core::normalise::Normalisation;
use moma_eval::protocol::{EvalConfig, corrupt_ground_truth, evaluate};

fn config(methods: &[&str], robust: &[RobustKind], outliers: Option<f64>) -> EvalConfig {
    EvalConfig {
        methods: methods.iter().map(|s| s.parse().unwrap()).collect(),
        norms: vec![Normalisation::Minmax],
        samples: 60,
        seeds: 3,
        // threshold above GSSA's own misfit on these predictions (a ±3 % sine distortion, up to
        // ±2 cm), below the injected errors (0.1–0.5 m)
        robust: robust
            .iter()
            .map(|&k| Robust::new(k).with_threshold_m(0.03))
            .collect(),
        gt_outliers: outliers,
        ..Default::default()
    }
}

#[test]
fn robust_rows_follow_each_supported_method() {
    let res = evaluate(
        &set(3),
        &preds(3),
        &config(
            &["gssa", "lwlr"],
            &[RobustKind::Huber, RobustKind::Ransac],
            None,
        ),
    )
    .unwrap();
    let rows: Vec<(&str, &str)> = res
        .iter()
        .map(|r| (r.method.as_str(), r.variant.as_str()))
        .collect();
    assert_eq!(
        rows,
        [
            ("gssa", "one-shot"),
            ("gssa", "robust-huber"),
            ("gssa", "robust-ransac"),
            ("lwlr", "one-shot"),
        ]
    );
    let json = moma_eval::report::contract_json(&res).unwrap();
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!(v[1]["variant"], "robust-huber");
    assert_eq!(v[0]["variant"], "one-shot");
    let md = moma_eval::report::eval_table(&res, false).to_markdown();
    assert!(
        md.contains("| variant |") && md.contains("robust-ransac"),
        "{md}"
    );
    let csv = moma_eval::report::eval_csv(&res);
    assert!(csv.lines().next().unwrap().contains("method,variant,norm"));
}

/// Each variant on corrupted ground truth against the same variant on the true ground truth:
/// least squares moves by > 5 mm, Tukey and RANSAC by < 1 mm, Huber less than least squares.
#[test]
fn injected_outliers_hurt_least_squares_not_robust_fits() {
    let set = set(3);
    let preds = preds(3);
    let kinds = [RobustKind::Huber, RobustKind::Tukey, RobustKind::Ransac];
    let clean = evaluate(&set, &preds, &config(&["gssa"], &kinds, None)).unwrap();
    let bad = evaluate(&set, &preds, &config(&["gssa"], &kinds, Some(0.2))).unwrap();
    let mae = |res: &[moma_eval::protocol::EvalResult], v: &str| {
        res.iter()
            .find(|r| r.variant == v)
            .unwrap()
            .per_image
            .mae
            .mean
    };
    let shift = |v: &str| (mae(&bad, v) - mae(&clean, v)).abs();
    assert!(
        shift("one-shot") > 0.005,
        "least squares moved {}",
        shift("one-shot")
    );
    for v in ["robust-tukey", "robust-ransac"] {
        assert!(shift(v) < 0.001, "{v} moved {}", shift(v));
    }
    assert!(shift("robust-huber") < shift("one-shot"));
}

#[test]
fn corruption_is_seeded_and_hits_the_asked_fraction() {
    let g = gt(0);
    let a = corrupt_ground_truth(&g, 0.2, 5);
    assert_eq!(a.depth_m, corrupt_ground_truth(&g, 0.2, 5).depth_m);
    assert_ne!(a.depth_m, corrupt_ground_truth(&g, 0.2, 6).depth_m);
    let (mut valid, mut changed) = (0usize, 0usize);
    for (x, y) in g.depth_m.iter().zip(&a.depth_m) {
        if *x > 0.0 && x.is_finite() {
            valid += 1;
            if x != y {
                changed += 1;
                let d = (x - y).abs();
                assert!((0.1..0.5).contains(&d) && *y >= 0.05, "{x} -> {y}");
            }
        } else {
            assert!(x == y || (x.is_nan() && y.is_nan()));
        }
    }
    let frac = changed as f64 / valid as f64;
    assert!((frac - 0.2).abs() < 0.02, "{frac} of {valid}");
}

/// Regression (found by the check over simulator seeds): on gqcnn-primesense, simulator seed 8,
/// sampling seed 3, 20 % outliers, the robust local fit's second start (the robust inliers joined
/// by the plain local fit's) let 4 outliers into the global least squares; its inlier set
/// collapsed (82 → 33) and the masked MAE was 196 mm against 23 mm for robust GSSA. The kept
/// model is now the one with the largest consensus over both starts' rounds.
#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn robust_local_fit_keeps_the_larger_consensus() {
    let set = shared_set("gqcnn-primesense");
    let preds = simulated_inverse_depth(&set, 8);
    let config = EvalConfig {
        methods: vec!["gssa".parse().unwrap(), "gssa-local".parse().unwrap()],
        seeds: 1,
        seed_base: 3,
        robust: vec![Robust::new(RobustKind::Huber)],
        gt_outliers: Some(0.2),
        ..Default::default()
    };
    let res = evaluate(&set, &preds, &config).unwrap();
    let mae = |m: &str| {
        res.iter()
            .find(|r| r.method == m && r.variant == "robust-huber")
            .unwrap()
            .per_image
            .mae
            .mean
    };
    // measured after the fix: gssa 22.6 mm, gssa-local 21.8 mm
    assert!(
        mae("gssa-local") < mae("gssa") + 0.002,
        "robust gssa-local {} m vs robust gssa {} m",
        mae("gssa-local"),
        mae("gssa")
    );
}
