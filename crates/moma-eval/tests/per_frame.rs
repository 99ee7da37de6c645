//! The per-frame (sparse-to-dense) protocol, `moma eval --protocol per-frame`, and the scoring
//! cap (`--score-max-gt-depth`): rows against calibrations made by hand, a scene whose frames
//! each have their own exact affine prediction, and the combinations refused.

mod common;

use common::*;
use moma_core::AlignOptions;
use moma_core::metrics::DepthMetrics;
use moma_core::normalise::{AlignSpace, Normalisation, NormalisationConfig};
use moma_core::pipeline::{CalibrationConfig, CalibrationFrame, calibrate};
use moma_core::sampling::SamplingConfig;
use moma_core::{Mask, Prediction, PredictionKind};
use moma_eval::EvalError;
use moma_eval::protocol::{
    EvalConfig, JsonRow, PER_FRAME_CALIB, PredictionSet, Protocol, evaluate, evaluate_few_shot,
};
use ndarray::Array2;

fn config(methods: &[&str], protocol: Protocol) -> EvalConfig {
    EvalConfig {
        methods: methods.iter().map(|s| s.parse().unwrap()).collect(),
        norms: vec![Normalisation::None],
        samples: 40,
        seeds: 3,
        protocol,
        ..Default::default()
    }
}

/// Frame `k` aligned by `method` calibrated on its own 40 samples (seed `seed`, no
/// normalisation, depth space), through the library calibration.
fn aligned_alone(
    set: &moma_eval::data::LoadedSet,
    preds: &PredictionSet,
    k: usize,
    method: &moma_core::align::Method,
    seed: u64,
) -> moma_core::MetricDepth {
    let cal = calibrate(
        &[CalibrationFrame {
            pred: (&preds.maps[k]).into(),
            gt: &set.frames[k].gt,
            sample_region: None,
        }],
        &CalibrationConfig {
            method: method.clone(),
            normalisation: NormalisationConfig {
                method: Normalisation::None,
                space: AlignSpace::Depth,
            },
            sampling: SamplingConfig {
                n: 40,
                seed,
                ..Default::default()
            },
            robust: None,
            workspace: None,
        },
    )
    .unwrap();
    cal.aligned(&preds.maps[k], &AlignOptions::default())
        .unwrap()
        .depth
}

/// Each row's per-frame metrics are those of `calibrate` on that frame alone (same seed),
/// applied to it and scored inside its mask; every frame is scored, `calib_frame` is `each`.
#[test]
fn each_frame_is_calibrated_on_its_own_samples() {
    let (set, preds) = (set(3), preds(3));
    let cfg = config(&["gssa", "ssra"], Protocol::PerFrame);
    let rows = evaluate(&set, &preds, &cfg).unwrap();
    assert_eq!(rows.len(), 2);
    for r in &rows {
        assert_eq!(
            (r.protocol, r.calib_frame.as_str(), r.eval_frames),
            (Protocol::PerFrame, PER_FRAME_CALIB, 3)
        );
        let row = JsonRow::from(r);
        assert_eq!(serde_json::to_value(&row).unwrap()["protocol"], "per-frame");
        let method: moma_core::align::Method = r.method.parse().unwrap();
        let method = method.with_intrinsics(Some(intrinsics()));
        for (k, f) in r.frames.iter().enumerate() {
            assert_eq!(f.frame, format!("f{k}"));
            for (s, got) in f.per_seed.iter().enumerate() {
                let aligned = aligned_alone(&set, &preds, k, &method, s as u64);
                let want =
                    DepthMetrics::compute(&aligned, &set.frames[k].gt, set.frames[k].mask.as_ref())
                        .unwrap();
                assert_eq!(got.mae, want.mae, "{} frame {k} seed {s}", r.method);
            }
        }
    }
}

/// Frames whose prediction is an exact affine map of the truth, a different one per frame (a
/// camera that moves, a model whose scale changes): per frame, GSSA recovers every frame
/// (AbsRel ≈ 0); calibrated on frame 0 and applied to the others, it cannot.
#[test]
fn per_frame_recovers_frame_specific_scales_that_one_calibration_cannot() {
    let set = set(3);
    let preds = PredictionSet {
        label: "exact affine per frame".into(),
        simulated: false,
        maps: (0..3)
            .map(|k| {
                let (a, b) = (0.6 + 0.3 * k as f32, 0.1 * k as f32);
                let g = &set.frames[k].gt.depth_m;
                Prediction::new(
                    g.mapv(|z| if z > 0.0 { a * z + b } else { b }),
                    PredictionKind::MetricDepth,
                )
            })
            .collect(),
    };
    let per_frame = evaluate(&set, &preds, &config(&["gssa"], Protocol::PerFrame)).unwrap();
    assert!(
        per_frame[0].per_image.rel.mean < 1e-5,
        "{:?}",
        per_frame[0].per_image.rel
    );
    let fixed = evaluate(&set, &preds, &config(&["gssa"], Protocol::FixedCamera)).unwrap();
    assert_eq!(fixed[0].protocol, Protocol::FixedCamera);
    assert_eq!(fixed[0].eval_frames, 2);
    assert!(
        fixed[0].per_image.rel.mean > 0.05,
        "{:?}",
        fixed[0].per_image.rel
    );
}

/// The scoring cap removes far pixels from scoring only: the calibrations (their fit residuals)
/// are those of the uncapped run, and each frame's metrics are those of the uncapped run's
/// alignment scored inside mask ∧ truth ≤ cap.
#[test]
fn the_scoring_cap_leaves_sampling_alone() {
    let (set, preds) = (set(3), preds(3));
    let cap = 0.74;
    let uncapped = config(&["gssa"], Protocol::PerFrame);
    let capped = EvalConfig {
        score_max_depth_m: Some(cap),
        ..uncapped.clone()
    };
    let a = evaluate(&set, &preds, &uncapped).unwrap();
    let b = evaluate(&set, &preds, &capped).unwrap();
    assert_eq!(a[0].fit_rms_residual_m, b[0].fit_rms_residual_m);
    assert_ne!(a[0].per_image.mae.mean, b[0].per_image.mae.mean);
    // seed 0, frame 1 by hand
    let k = 1;
    let aligned = aligned_alone(&set, &preds, k, &moma_core::align::Method::Gssa, 0);
    let region = Mask::new(Array2::from_shape_fn((H, W), |(v, u)| {
        let z = set.frames[k].gt.depth_m[[v, u]];
        set.frames[k].mask.as_ref().unwrap().data()[[v, u]] && z > 0.0 && f64::from(z) <= cap
    }));
    let want = DepthMetrics::compute(&aligned, &set.frames[k].gt, Some(&region)).unwrap();
    assert_eq!(b[0].frames[k].per_seed[0].mae, want.mae);
}

#[test]
fn per_frame_refuses_what_needs_one_calibration_frame() {
    let (set, preds) = (set(3), preds(3));
    let base = config(&["gssa"], Protocol::PerFrame);
    let with_frame = EvalConfig {
        calib_frame: Some("f1".into()),
        ..base.clone()
    };
    let e = evaluate(&set, &preds, &with_frame).unwrap_err();
    assert!(matches!(e, EvalError::InvalidParameter(_)), "{e}");
    let realign = EvalConfig {
        realign: Some(Default::default()),
        ..base.clone()
    };
    assert!(
        evaluate(&set, &preds, &realign)
            .unwrap_err()
            .to_string()
            .contains("fixed-camera")
    );
    assert!(
        evaluate_few_shot(&set, &preds, &base, &[1, 2])
            .unwrap_err()
            .to_string()
            .contains("fixed-camera")
    );
    let bad_cap = EvalConfig {
        score_max_depth_m: Some(-1.0),
        ..base.clone()
    };
    assert!(evaluate(&set, &preds, &bad_cap).is_err());
    // one frame: per frame scores it; the fixed-camera protocol needs two
    let (one, one_pred) = (common::set(1), common::preds(1));
    let rows = evaluate(&one, &one_pred, &base).unwrap();
    assert_eq!(rows[0].eval_frames, 1);
    let fixed = config(&["gssa"], Protocol::FixedCamera);
    assert!(
        evaluate(&one, &one_pred, &fixed)
            .unwrap_err()
            .to_string()
            .contains("per-frame")
    );
}
