//! `grasp_evaluate` end to end on a real set (docs/method.md §8): SIMULATED inverse-depth predictions of
//! graspnet6dof-table, calibrated and aligned on the library path, the top-1 grasp per object
//! planned on the aligned depth and executed on the ground truth (PROXY scores, not robot trials).

mod common;

use common::{shared_set, simulated_inverse_depth};
use moma_core::align::Method;
use moma_eval::grasp_eval::{
    GraspEvalConfig, GripperKind, brier_base_rate, grasp_evaluate, grasp_table,
};
use moma_eval::protocol::EvalConfig;
use moma_grasp::GraspQuality;

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn grasps_on_aligned_simulated_depth_succeed_by_proxy() {
    let set = shared_set("graspnet6dof-table");
    let preds = simulated_inverse_depth(&set, 0);
    let config = GraspEvalConfig {
        eval: EvalConfig {
            methods: vec![Method::Ssra(Default::default())],
            // 3 sampling seeds: 21 trials, so that one trial is not a 14 % step
            seeds: 3,
            ..Default::default()
        },
        qualities: vec![GraspQuality::Nominal, GraspQuality::Robust],
        ..Default::default()
    };
    let result = grasp_evaluate(&set, &preds, &config).unwrap();
    let rows = result.rows;
    eprintln!("{}", grasp_table(&rows).to_text());
    let rate = |method: &str, g: GripperKind| {
        rows.iter()
            .find(|r| r.method == method && r.gripper == g)
            .map(|r| (r.success_rate, r.trials))
            .unwrap()
    };
    // every robust row of the aligned depth has success probabilities, a Brier score in [0, 1]
    // and a reliability table whose counts add up to the trials with a probability
    let (mut held_p, mut held_n, mut failed_p, mut failed_n) = (0.0, 0.0, 0.0, 0.0);
    for r in rows.iter().filter(|r| r.method == "ssra") {
        let b = r.brier.unwrap();
        assert!((0.0..=1.0).contains(&b), "{r:?}");
        for bin in &r.reliability {
            if let (Some(p), Some(a)) = (bin.predicted, bin.achieved) {
                let n = bin.grasps as f64;
                held_p += p * a * n;
                held_n += a * n;
                failed_p += p * (1.0 - a) * n;
                failed_n += (1.0 - a) * n;
            }
        }
        let n: usize = r.reliability.iter().map(|b| b.grasps).sum();
        assert!(n > 0 && n <= r.trials, "{r:?}");
        // the base rate's Brier score from the same grasps, counted through the bins
        let held: f64 = r
            .reliability
            .iter()
            .filter_map(|b| b.achieved.map(|a| a * b.grasps as f64))
            .sum();
        let rate = held / n as f64;
        let base = r.brier_base_rate.unwrap();
        assert!((base - rate * (1.0 - rate)).abs() < 1e-9, "{r:?}");
    }
    // the probabilities tell grasps apart: over the four rows (both grippers, both rankings),
    // the grasps that held on the truth were given more than those that failed (measured 0.51
    // against 0.33 with the default normalisation, minmax-unit; how well they are calibrated
    // is measured, not asserted: on these one-shot frames they are under-confident,
    // docs/grasping.md, "The fit's optimism")
    let (held_mean, failed_mean) = (held_p / held_n, failed_p / failed_n);
    eprintln!("mean success_prob: held {held_mean:.3}, failed {failed_mean:.3}");
    assert!(
        held_mean > failed_mean + 0.05,
        "held {held_mean:.3} failed {failed_mean:.3}"
    );
    for r in rows.iter().filter(|r| r.method == "gt") {
        assert!(r.brier.is_none() && r.brier_base_rate.is_none(), "{r:?}");
        assert!(r.calibration_frame_check.is_none(), "{r:?}");
    }
    // every calibration's check of its calibration frame: at most 10 grasps each (3 seeds),
    // counts that add up, probabilities where the grasps were planned with the error model
    for r in rows.iter().filter(|r| r.method == "ssra") {
        let c = r.calibration_frame_check.unwrap();
        assert!(c.successes <= c.grasps && c.grasps <= 30, "{r:?}");
        if r.grasp_quality == GraspQuality::Robust && c.grasps > 0 {
            assert!(
                c.mean_success_prob.is_some_and(|p| p > 0.0 && p < 1.0),
                "{r:?}"
            );
        }
    }
    // the best of the candidates: no ranking does better than a perfect one, or worse than
    // none; on the ground truth every suction candidate the planner keeps has passed the
    // scorer's own rules on that very scene (the same depth, mask and settings), so each trial
    // with a grasp has one that holds
    for r in &rows {
        assert!(
            r.successes <= r.best_of_candidates && r.best_of_candidates <= r.trials,
            "{r:?}"
        );
    }
    let gt_suction = rows
        .iter()
        .find(|r| r.method == "gt" && r.gripper == GripperKind::Suction)
        .unwrap();
    let no_grasp = gt_suction.failures.get("no_grasp").copied().unwrap_or(0);
    assert_eq!(gt_suction.best_of_candidates, gt_suction.trials - no_grasp);
    // on aligned depth the ranking loses grasps that another candidate would have won
    assert!(
        rows.iter()
            .any(|r| r.method == "ssra" && r.best_of_candidates > r.successes),
        "{rows:?}"
    );
    // the error model's σ covers the true errors in a plausible share: measured 80 / 93 / 76 %
    // within ±1σ and 99.3 / 99.9 / 98.9 % within ±2σ (all pixels / masks / edges; inside the
    // masks too wide, as issue 22's coverage table says: docs/grasping.md); a σ twice too wide
    // (> 95 % within ±1σ) or too narrow (< 30 %) fails
    for c in &result.coverage {
        assert!(
            (0.3..=0.95).contains(&c.within_1sigma)
                && (0.8..=0.9995).contains(&c.within_2sigma)
                && c.within_2sigma > c.within_1sigma,
            "{c:?}"
        );
    }
    // 6 evaluated frames, at least one object each; the planner's ceiling on ground truth
    for g in GripperKind::ALL {
        let (gt, trials) = rate("gt", g);
        assert!(trials >= 6, "{trials} trials");
        assert!(gt >= 0.9, "{g} on ground truth: {gt}");
    }
    // on aligned (simulated) depth the parallel jaw still finds grasps that hold (nominal
    // ranking: the first row of the method), in over a quarter of the trials (10 of 21 one-shot
    // with the default normalisation, minmax-unit; the ground truth, planned once, 7 of 7)
    let (ssra, trials) = rate("ssra", GripperKind::Parallel);
    assert_eq!(trials, 21);
    assert!(ssra >= 0.25, "parallel on SSRA-aligned depth: {ssra}");
    assert!(grasp_table(&rows).title.contains("PROXY"));
    assert!(grasp_table(&rows).title.contains("SIMULATED"));
}

#[test]
fn the_base_rate_brier_score_is_the_best_constant_forecasts() {
    // 3 of 5 grasps hold: the constant 0.6 scores 0.6 · 0.4² + 0.4 · 0.6² = 0.24
    let probs = [
        (0.9, true),
        (0.2, false),
        (0.6, true),
        (0.5, false),
        (0.7, true),
    ];
    let base = brier_base_rate(&probs).unwrap();
    assert!((base - 0.24).abs() < 1e-12, "{base}");
    // no other constant forecast does better on these outcomes
    let brier_of = |c: f64| {
        probs
            .iter()
            .map(|&(_, s)| (c - if s { 1.0 } else { 0.0 }).powi(2))
            .sum::<f64>()
            / probs.len() as f64
    };
    assert!((brier_of(0.6) - base).abs() < 1e-12);
    for c in [0.0, 0.3, 0.55, 0.65, 0.9, 1.0] {
        assert!(brier_of(c) > base, "{c}");
    }
    // outcomes that all agree need no forecast at all; nothing to score gives none
    assert_eq!(brier_base_rate(&[(0.3, true), (0.8, true)]), Some(0.0));
    assert_eq!(brier_base_rate(&[(0.3, false)]), Some(0.0));
    assert_eq!(brier_base_rate(&[]), None);
}

#[test]
fn the_reliability_table_bins_by_fifths_with_the_last_closed() {
    let probs = [
        (0.0, false),
        (0.2, true), // an edge belongs to the bin above it
        (0.39, false),
        (0.6, true),
        (0.6, false),
        (0.79, true),
        (1.0, true), // the last bin holds 1
    ];
    let t = moma_eval::grasp_eval::reliability_table(&probs);
    let bins: Vec<[f64; 2]> = t.iter().map(|b| b.bin).collect();
    assert_eq!(
        bins,
        [[0.0, 0.2], [0.2, 0.4], [0.4, 0.6], [0.6, 0.8], [0.8, 1.0]]
    );
    let counts: Vec<usize> = t.iter().map(|b| b.grasps).collect();
    assert_eq!(counts, [1, 2, 0, 3, 1]);
    assert_eq!(t[2].predicted, None);
    assert_eq!(t[2].achieved, None);
    assert!((t[1].predicted.unwrap() - 0.295).abs() < 1e-12);
    assert!((t[1].achieved.unwrap() - 0.5).abs() < 1e-12);
    assert!((t[3].achieved.unwrap() - 2.0 / 3.0).abs() < 1e-12);
    assert_eq!((t[4].predicted, t[4].achieved), (Some(1.0), Some(1.0)));
}
