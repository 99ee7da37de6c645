//! Grasping under depth uncertainty: negative controls (a planning depth that is wrong by a
//! known amount must lose grasps) and the ordering of `success_prob` on a scene with a known
//! answer. Scenes are rendered by exact ray casting (tests/common).

mod common;

use common::{BoxSpec, Scene as Synth, intrinsics};
use moma_core::{DepthErrorModel, MetricDepth};
use moma_grasp::{
    FailureReason, Grasp, GraspQuality, GraspRequest, Gripper, ParallelGrasp, ParallelJaw,
    ParallelPose, Scene, SceneConfig, ScoreConfig, SuctionCup, plan_grasps, posterior_success_prob,
    rank, score_grasp, success_probabilities,
};

const DIST_M: f64 = 0.7;

fn boxes(layout: usize) -> [BoxSpec; 2] {
    // two boxes 0.44 m apart along the table's y axis (the tilt axis is x), 30–60 mm tall
    let b = |y: f64, h: f64, yaw: f64| BoxSpec {
        x_m: 0.02 * layout as f64 - 0.03,
        y_m: y,
        long_m: 0.07,
        short_m: 0.04,
        height_m: h,
        yaw_rad: yaw,
    };
    [
        b(0.22, 0.03 + 0.01 * layout as f64, 0.3 * layout as f64),
        b(
            -0.22,
            0.06 - 0.01 * layout as f64,
            1.2 - 0.3 * layout as f64,
        ),
    ]
}

fn synth(layout: usize, tilt_deg: f64) -> Synth {
    let [a, b] = boxes(layout);
    let mut s = Synth::tilted(DIST_M, tilt_deg.to_radians(), Some(a));
    s.boxes[1] = Some(b);
    s
}

/// Top-1 grasp planned on `planning`, executed on the ground-truth scene: success?
fn top1_succeeds(planning: &MetricDepth, gt: &Scene, gripper: &Gripper, seed: u64) -> bool {
    let mut request = GraspRequest::new(*gripper);
    request.top_k = 1;
    request.seed = seed;
    let (_, outcome) = plan_grasps(planning, &intrinsics(), None, &request).unwrap();
    outcome.grasps.first().is_some_and(|g| {
        score_grasp(gt, g, gripper, &ScoreConfig::default())
            .unwrap()
            .success
    })
}

#[test]
fn a_shifted_or_tilted_planning_depth_loses_a_third_of_the_grasps() {
    let grippers = [
        Gripper::Parallel(ParallelJaw::default()),
        Gripper::Suction(SuctionCup::default()),
    ];
    for seed in 0..3u64 {
        let (mut exact, mut shifted, mut tilted) = (0usize, 0usize, 0usize);
        for layout in 0..3 {
            let gt_depth = synth(layout, 0.0).render();
            let gt = Scene::build(&gt_depth, &intrinsics(), None, &SceneConfig::default()).unwrap();
            let plus_30mm = MetricDepth::new(
                gt_depth
                    .depth_m
                    .mapv(|z| if z > 0.0 { z + 0.03 } else { z }),
            );
            let tilt_5deg = synth(layout, 5.0).render();
            for g in &grippers {
                exact += usize::from(top1_succeeds(&gt_depth, &gt, g, seed));
                shifted += usize::from(top1_succeeds(&plus_30mm, &gt, g, seed));
                tilted += usize::from(top1_succeeds(&tilt_5deg, &gt, g, seed));
            }
        }
        assert!(
            exact >= 5,
            "seed {seed}: the exact depth wins only {exact} of 6"
        );
        for (what, n) in [("+30 mm", shifted), ("5° tilt", tilted)] {
            assert!(
                3 * n <= 2 * exact,
                "seed {seed}: planned on the depth with a {what} error, {n} of the {exact} \
                 successes remain (at most two thirds may)"
            );
        }
    }
}

/// A top-down parallel grasp across the short side of box `b`, its centre `below_top_m` under
/// the box's top face.
fn grasp_on(s: &Synth, b: &BoxSpec, below_top_m: f64) -> Grasp {
    let top = s.box_top_centre(b);
    let (_, short) = s.box_axes(b);
    let c = [
        top[0] - s.up[0] * below_top_m,
        top[1] - s.up[1] * below_top_m,
        top[2] - s.up[2] * below_top_m,
    ];
    let f = |v: [f64; 3]| [v[0] as f32, v[1] as f32, v[2] as f32];
    Grasp::Parallel(ParallelGrasp {
        score: 1.0,
        success_prob: None,
        pose: ParallelPose {
            center_m: f(c),
            approach: f([-s.up[0], -s.up[1], -s.up[2]]),
            closing: f(short),
            width_m: (b.short_m + 0.02) as f32,
        },
        base: None,
    })
}

#[test]
fn a_grasp_that_survives_a_20mm_offset_gets_a_higher_success_prob() {
    // a tall (60 mm) box grasped 25 mm under its top, a low (15 mm) one 4 mm under its top
    let tall = BoxSpec {
        x_m: 0.0,
        y_m: 0.12,
        height_m: 0.06,
        ..BoxSpec::standard()
    };
    let low = BoxSpec {
        x_m: 0.0,
        y_m: -0.12,
        height_m: 0.015,
        ..BoxSpec::standard()
    };
    let mut s = Synth::top_down(DIST_M, Some(tall));
    s.boxes[1] = Some(low);
    let depth = s.render();
    let k = intrinsics();
    let jaw = Gripper::Parallel(ParallelJaw::default());
    let cfg = ScoreConfig::default();
    let (g_tall, g_low) = (grasp_on(&s, &tall, 0.025), grasp_on(&s, &low, 0.004));
    // independent check of the premise: both succeed on the truth; under a +20 mm offset of the
    // scene (everything 20 mm farther) the low one fails and the tall one survives
    let scene = |d: &MetricDepth| Scene::build(d, &k, None, &SceneConfig::default()).unwrap();
    let gt = scene(&depth);
    let far = scene(&MetricDepth::new(depth.depth_m.mapv(|z| z + 0.02)));
    let run = |sc: &Scene, g: &Grasp| score_grasp(sc, g, &jaw, &cfg).unwrap();
    assert!(run(&gt, &g_tall).success, "{:?}", run(&gt, &g_tall));
    assert!(run(&gt, &g_low).success, "{:?}", run(&gt, &g_low));
    assert!(run(&far, &g_tall).success, "{:?}", run(&far, &g_tall));
    assert_eq!(
        run(&far, &g_low)
            .failure
            .map(|f| f != FailureReason::NoGrasp),
        Some(true)
    );
    // an error model of a 20 mm offset: the survivor is the more probable
    let model = DepthErrorModel {
        sigma_flat_m: 0.02,
        variance_shares: [1.0, 0.0, 0.0, 0.0],
        ..DepthErrorModel::default()
    };
    let mut request = GraspRequest::new(jaw).with_error_model(Some(model.clone()));
    request.draws = 64;
    let p = success_probabilities(&[g_tall, g_low], &gt, &depth, &k, &model, &request).unwrap();
    assert!(
        p[0] > p[1] + 0.2,
        "success_prob tall {} vs low {}",
        p[0],
        p[1]
    );
    // it falls as σ grows, to the end: a draw that puts the surface at or behind the camera
    // has no depth there (kept as the exact depth, σ = 5 m gave the tall box's grasp about 0.45:
    // P(offset < −0.7 m), every such draw "succeeding")
    let tall_at = |sigma_m: f64| {
        let m = DepthErrorModel {
            sigma_flat_m: sigma_m,
            ..model.clone()
        };
        let g = [grasp_on(&s, &tall, 0.025)];
        success_probabilities(&g, &gt, &depth, &k, &m, &request).unwrap()[0]
    };
    let falls = [0.02, 0.2, 5.0].map(tall_at);
    assert!(
        falls[0] > falls[1] && falls[1] >= falls[2] && falls[2] < 0.05,
        "success_prob of the tall box's grasp at σ 0.02, 0.2, 5 m: {falls:?}"
    );
    // a robust request ranks by it and says so in the JSON
    assert_eq!(request.quality, GraspQuality::Robust);
    let (_, out) = plan_grasps(&depth, &k, None, &request).unwrap();
    let json = serde_json::to_value(&out.grasps).unwrap();
    let probs: Vec<f64> = json
        .as_array()
        .unwrap()
        .iter()
        .map(|g| g["success_prob"].as_f64().unwrap())
        .collect();
    assert!(!probs.is_empty());
    // each is (k + 1) / (N + 2) for k of the N draws: strictly inside (0, 1)
    let n = request.draws as f64;
    for p in &probs {
        let k = p * (n + 2.0) - 1.0;
        assert!(
            (k - k.round()).abs() < 1e-3 && (0.0..=n).contains(&k.round()),
            "success_prob {p} is not (k + 1) / ({n} + 2)"
        );
    }
}

/// Expected Brier score of the estimator `estimate(k)` of a grasp's success probability from
/// `n` draws, when the true probability p is uniform on [0, 1] and k ~ Binomial(n, p):
/// ∫ Σ_k C(n, k) pᵏ (1 − p)ⁿ⁻ᵏ (e(k)² − 2 e(k) p + p) dp, by the midpoint rule.
fn expected_brier(n: u32, estimate: impl Fn(u32) -> f64) -> f64 {
    let steps = 20_000;
    let choose = |k: u32| (0..k).fold(1.0, |c, i| c * f64::from(n - i) / f64::from(i + 1));
    (0..steps)
        .map(|i| {
            let p = (f64::from(i) + 0.5) / f64::from(steps);
            (0..=n)
                .map(|k| {
                    let w = choose(k) * p.powi(k as i32) * (1.0 - p).powi((n - k) as i32);
                    let e = estimate(k);
                    w * (e * e - 2.0 * e * p + p)
                })
                .sum::<f64>()
        })
        .sum::<f64>()
        / f64::from(steps)
}

#[test]
fn success_prob_is_the_posterior_mean_that_minimises_the_brier_score() {
    // closed form: Laplace's rule of succession
    for (share, n, want) in [
        (1.0, 4, 5.0 / 6.0),
        (0.0, 4, 1.0 / 6.0),
        (0.5, 4, 0.5),
        (0.25, 8, 0.3),
    ] {
        let got = f64::from(posterior_success_prob(share, n));
        assert!(
            (got - want).abs() < 1e-6,
            "share {share} of {n}: {got} vs {want}"
        );
    }
    // independently: with an unknown (uniform) true probability, no other estimate from 4 draws
    // has a lower expected Brier score. Closed forms (k is then uniform on 0..=n): the posterior
    // mean's is 1/2 − E[e²] = 1/2 − (2n + 3) / (6 (n + 2)) = 7/36; the plain share's is
    // 1/2 − 2/3 + (2n + 1) / (6n) = 5/24.
    let n = 4;
    let post = |k: u32| f64::from(posterior_success_prob(k as f32 / n as f32, n as usize));
    let best = expected_brier(n, post);
    let share = expected_brier(n, |k| f64::from(k) / f64::from(n));
    assert!((best - 7.0 / 36.0).abs() < 1e-6, "posterior mean: {best}");
    assert!((share - 5.0 / 24.0).abs() < 1e-6, "share: {share}");
    for k0 in 0..=n {
        for d in [-0.02, 0.02] {
            let moved = expected_brier(n, |k| post(k) + if k == k0 { d } else { 0.0 });
            assert!(moved > best, "k {k0} moved by {d}: {moved} vs {best}");
        }
    }
}

#[test]
fn bad_requests_are_errors_and_an_impossible_minimum_empties_the_list_with_a_reason() {
    let depth = Synth::top_down(DIST_M, Some(BoxSpec::standard())).render();
    let k = intrinsics();
    let base = GraspRequest::new(Gripper::Suction(SuctionCup::default()))
        .with_error_model(Some(DepthErrorModel::uniform(0.003).unwrap()));
    // each refused as a bad configuration, naming what is wrong
    let config_error = |r: &GraspRequest, says: &str| match plan_grasps(&depth, &k, None, r) {
        Err(e @ moma_grasp::GraspError::InvalidConfig(_)) => {
            assert!(e.to_string().contains(says), "{e}");
        }
        other => panic!("{says}: {other:?}"),
    };
    let mut zero = base.clone();
    zero.draws = 0;
    config_error(&zero, "depth draws must be at least 1");
    for p in [-0.1, 1.5, f64::NAN] {
        let mut r = base.clone();
        r.min_success_prob = Some(p);
        config_error(&r, "minimum success probability");
    }
    let mut robust_without_model = GraspRequest::new(Gripper::Suction(SuctionCup::default()));
    robust_without_model.quality = GraspQuality::Robust;
    config_error(&robust_without_model, "needs an error model");
    // without a model: no probability
    let (_, plain) = plan_grasps(
        &depth,
        &k,
        None,
        &GraspRequest::new(Gripper::Suction(SuctionCup::default())),
    )
    .unwrap();
    assert!(plain.grasps.iter().all(|g| g.success_prob().is_none()));
    // a minimum no grasp reaches: empty, with the reason
    let mut strict = base;
    strict.min_success_prob = Some(1.0);
    strict.error_model = Some(DepthErrorModel::uniform(0.05).unwrap());
    let (_, out) = plan_grasps(&depth, &k, None, &strict).unwrap();
    assert!(out.grasps.is_empty());
    let reason = out.no_grasp_reason.unwrap().to_string();
    assert!(reason.contains("below the minimum"), "{reason}");
}

/// The robust ranking on given shares: grasps within the tie tolerance of the best share keep the
/// planner's order, the others follow by share (stable); nominal keeps the planner's order.
#[test]
fn the_robust_ranking_ties_within_the_tolerance_and_sorts_the_rest_by_share() {
    let depth = Synth::top_down(DIST_M, Some(BoxSpec::standard())).render();
    let request = GraspRequest::new(Gripper::Suction(SuctionCup::default()));
    let (_, out) = plan_grasps(&depth, &intrinsics(), None, &request).unwrap();
    // four grasps told apart by their scores (the ranking reads only the shares and the order)
    let g: Vec<Grasp> = (0..4)
        .map(|k| {
            let mut v = serde_json::to_value(out.grasps[0]).unwrap();
            v["score"] = (0.9 - 0.1 * f64::from(k)).into();
            serde_json::from_value(v).unwrap()
        })
        .collect();
    assert!(g.windows(2).all(|w| w[0] != w[1]));
    let order = |shares: [f32; 4], quality: GraspQuality, tol: f32| -> Vec<usize> {
        let mut v: Vec<(Grasp, f32)> = g.iter().copied().zip(shares).collect();
        rank(&mut v, quality, tol);
        v.iter()
            .map(|(x, _)| g.iter().position(|y| y == x).unwrap())
            .collect()
    };
    let shares = [0.85, 0.9, 0.5, 0.2];
    // 0.85 is within 0.1 of the best 0.9: the planner's first stays first
    assert_eq!(order(shares, GraspQuality::Robust, 0.1), [0, 1, 2, 3]);
    // without a tolerance the higher share wins
    assert_eq!(order(shares, GraspQuality::Robust, 0.0), [1, 0, 2, 3]);
    // below the tie the shares order, highest first
    assert_eq!(
        order([0.2, 0.5, 0.9, 0.85], GraspQuality::Robust, 0.1),
        [2, 3, 1, 0]
    );
    assert_eq!(
        order([0.2, 0.5, 0.9, 0.85], GraspQuality::Nominal, 0.1),
        [0, 1, 2, 3]
    );
}

/// `min_success_prob` filters the ranked list (every candidate, before the top-K cut) and
/// nothing else; when it drops them all, the reason counts them and gives the best probability.
#[test]
fn a_minimum_success_probability_keeps_exactly_the_grasps_at_or_above_it() {
    let depth = Synth::top_down(DIST_M, Some(BoxSpec::standard())).render();
    let k = intrinsics();
    let mut base = GraspRequest::new(Gripper::Suction(SuctionCup::default()))
        .with_error_model(Some(DepthErrorModel::uniform(0.02).unwrap()));
    base.top_k = 1000;
    base.draws = 8;
    let (_, all) = plan_grasps(&depth, &k, None, &base).unwrap();
    let probs: Vec<f32> = all
        .grasps
        .iter()
        .map(|g| g.success_prob().unwrap())
        .collect();
    let (lo, hi) = probs
        .iter()
        .fold((1.0f32, 0.0f32), |(a, b), &p| (a.min(p), b.max(p)));
    assert!(lo < hi, "every grasp at {lo}: no spread to filter");
    let m = 0.5 * (f64::from(lo) + f64::from(hi));
    let mut strict = base.clone();
    strict.min_success_prob = Some(m);
    let (_, kept) = plan_grasps(&depth, &k, None, &strict).unwrap();
    let want: Vec<Grasp> = all
        .grasps
        .iter()
        .filter(|g| f64::from(g.success_prob().unwrap()) >= m)
        .copied()
        .collect();
    assert!(!want.is_empty() && want.len() < all.grasps.len());
    assert_eq!(kept.grasps, want);
    assert!(kept.no_grasp_reason.is_none());
    // none reach 1: the reason says how many were dropped and the best probability
    strict.min_success_prob = Some(1.0);
    let (_, none) = plan_grasps(&depth, &k, None, &strict).unwrap();
    assert!(none.grasps.is_empty());
    match none.no_grasp_reason {
        Some(moma_grasp::NoGraspReason::BelowMinSuccessProb {
            candidates,
            best_success_prob,
            min_success_prob,
            draws,
        }) => {
            assert_eq!(candidates, all.grasps.len());
            assert_eq!(best_success_prob, hi);
            assert_eq!(min_success_prob, 1.0);
            assert_eq!(draws, 8);
        }
        other => panic!("{other:?}"),
    }
    // 1 is beyond what 8 draws can give ((8 + 1) / (8 + 2) = 0.9): the reason says so
    let reason = none.no_grasp_reason.unwrap().to_string();
    assert!(
        reason.contains("with 8 depth draws no grasp can exceed 0.90"),
        "{reason}"
    );
    // a reachable minimum that no grasp reaches asks for another image instead
    let reachable = moma_grasp::NoGraspReason::BelowMinSuccessProb {
        candidates: 3,
        best_success_prob: 0.5,
        min_success_prob: 0.8,
        draws: 8,
    }
    .to_string();
    assert!(reachable.contains("re-image"), "{reachable}");
    // 5/6 with 4 draws: the f32 5/6 a grasp holding on every draw gets is below the f64 5/6
    // asked, so no grasp can reach it, and the reason says so
    let edge = moma_grasp::NoGraspReason::BelowMinSuccessProb {
        candidates: 3,
        best_success_prob: moma_grasp::posterior_success_prob(1.0, 4),
        min_success_prob: 5.0 / 6.0,
        draws: 4,
    }
    .to_string();
    assert!(edge.contains("no grasp can exceed"), "{edge}");
    assert!(f64::from(moma_grasp::posterior_success_prob(1.0, 4)) < 5.0 / 6.0);
}
