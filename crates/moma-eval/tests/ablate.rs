//! The ablations with `calib_frames` (`moma ablate --calib-frames K`), and the evaluation's
//! sharing across variants (one normalised copy per normalisation and space, one anchor store
//! per set) checked bit-identical against rows computed from scratch.

mod common;

use common::*;
use moma_core::align::Method;
use moma_core::align::robust::{Robust, RobustKind};
use moma_core::normalise::{AlignSpace, Normalisation, NormalisationConfig};
use moma_core::pipeline::{CalibrationConfig, calibrate};
use moma_core::realign::AnchorStore;
use moma_core::sampling::SamplingConfig;
use moma_core::{CalibrationFrame, PredictionInput};
use moma_core::{ImageSize, MetricDepth};
use moma_eval::EvalError;
use moma_eval::ablate;
use moma_eval::data::LoadedSet;
use moma_eval::demo::{DemoScene, build_demo};
use moma_eval::protocol::{
    EvalConfig, EvalNote, EvalResult, PredictionSet, Prepared, Variant, evaluate,
    evaluate_few_shot, evaluate_one, evaluate_variant, variant_name,
};
use moma_eval::realign::{RealignEval, evaluate_realign};
use moma_eval::scene::DemoSceneConfig;
use ndarray::ArrayView3;

fn config(methods: &[&str], norms: &[Normalisation], seeds: usize) -> EvalConfig {
    EvalConfig {
        methods: methods.iter().map(|s| s.parse().unwrap()).collect(),
        norms: norms.to_vec(),
        samples: 30,
        seeds,
        ..Default::default()
    }
}

/// The row without its fit time (a wall-clock measurement, never reproducible).
fn timeless(r: &EvalResult) -> EvalResult {
    EvalResult {
        fit_time_median_s: 0.0,
        ..r.clone()
    }
}

fn assert_rows_eq(got: &[EvalResult], want: &[EvalResult]) {
    assert_eq!(got.len(), want.len());
    for (g, w) in got.iter().zip(want) {
        assert_eq!(timeless(g), timeless(w), "{} {}", g.method, g.variant);
    }
}

/// The small fixed-camera demo scene with RGB (SIMULATED inverse-depth predictions).
fn demo(frames: usize) -> (LoadedSet, PredictionSet) {
    let demo = DemoScene {
        scene: DemoSceneConfig {
            size: ImageSize::new(96, 72),
            focal_px: 90.0,
            frames,
            ..Default::default()
        },
        ..Default::default()
    };
    build_demo(&demo, None).unwrap()
}

/// `moma eval` with robust and re-alignment variants shares one normalised copy per
/// (normalisation, space) and one anchor store per set across its rows: every row equals the
/// row computed alone, from a fresh preparation (nothing shared), to the bit.
#[test]
fn shared_normalisation_and_anchor_store_change_no_number() {
    let (set, preds) = demo(4);
    let cfg = EvalConfig {
        robust: vec![
            Robust::new(RobustKind::Huber),
            Robust::new(RobustKind::Ransac),
        ],
        realign: Some(RealignEval {
            brightness: vec![1.0, 0.8],
            ..Default::default()
        }),
        ..config(
            &["gssa", "ssra", "lwlr"],
            &[Normalisation::Minmax, Normalisation::Median],
            2,
        )
    };
    let rows = evaluate(&set, &preds, &cfg).unwrap();
    // one-shot + 2 robust for gssa and ssra, one-shot for lwlr, per normalisation; then
    // 2 brightness rows per (method, normalisation)
    assert_eq!(rows.len(), 2 * (3 + 3 + 1) + 2 * 3 * 2);

    let mut want = Vec::new();
    let fresh = || Prepared::new(&set, &preds, &cfg).unwrap();
    let jobs: Vec<(Method, Normalisation)> = ["gssa", "ssra", "lwlr"]
        .iter()
        .flat_map(|m| {
            [Normalisation::Minmax, Normalisation::Median].map(|n| (m.parse().unwrap(), n))
        })
        .collect();
    for (m, n) in &jobs {
        let prep = fresh();
        let norm = prep.normalisation_for(m, *n);
        want.push(evaluate_one(&prep, m, &norm, cfg.samples).unwrap());
        for r in &cfg.robust {
            if r.check_method(m).is_ok() {
                let prep = fresh();
                want.push(
                    evaluate_variant(
                        &prep,
                        m,
                        &norm,
                        cfg.samples,
                        Variant {
                            name: &variant_name(Some(r)),
                            calib: &[prep.calib],
                            eval_idx: &prep.eval_indices(),
                            robust: Some(r),
                        },
                    )
                    .unwrap(),
                );
            }
        }
    }
    let realign = cfg.realign.as_ref().unwrap();
    for (m, n) in &jobs {
        for &b in &realign.brightness {
            let prep = fresh();
            let norm = prep.normalisation_for(m, *n);
            want.push(evaluate_realign(&prep, m, &norm, cfg.samples, realign, b).unwrap());
        }
    }
    assert_rows_eq(&rows, &want);
    // the normalisations differ, so a cache keyed on the wrong thing would have shown
    assert_ne!(rows[0].per_image, rows[3].per_image);
    assert_eq!(
        (rows[0].norm.as_str(), rows[3].norm.as_str()),
        ("minmax", "median")
    );
}

/// The anchor store built once and completed per calibration is the one `with_anchors`
/// builds from scratch, also when the shared store already held another calibration's result.
#[test]
fn anchor_store_built_once_equals_the_store_built_per_calibration() {
    let (set, preds) = demo(2);
    let f = &set.frames[0];
    let img = f.rgb.as_ref().unwrap();
    let rgb = ArrayView3::from_shape(
        (img.height() as usize, img.width() as usize, 3),
        img.as_raw(),
    )
    .unwrap();
    let cal = |seed: u64, method: Method| {
        let config = CalibrationConfig {
            method,
            normalisation: NormalisationConfig {
                method: Normalisation::Minmax,
                space: AlignSpace::Inverse,
            },
            sampling: SamplingConfig {
                seed,
                ..Default::default()
            },
            robust: None,
            workspace: None,
        };
        calibrate(&[CalibrationFrame::new(&preds.maps[0], &f.gt)], &config).unwrap()
    };
    let grey = moma_io::grey_half(rgb).unwrap();
    let store = AnchorStore::new(&grey, &f.gt).unwrap();
    for (seed, method) in [(0, Method::Gssa), (5, Method::Ssra(Default::default()))] {
        let c = cal(seed, method);
        let map = c.normalise(&preds.maps[0]).unwrap();
        let map = PredictionInput::normalised(&map, preds.maps[0].kind);
        let scratch = c.clone().with_anchors(&grey, &f.gt, map).unwrap();
        let shared = c.clone().with_anchor_store(&store, map).unwrap();
        assert!(shared.anchor_store().unwrap().has_one_shot());
        assert_eq!(shared.anchors, scratch.anchors);
        // a store holding another calibration's one-shot result gets this one's
        let other = cal(seed + 1, Method::Gssa)
            .with_anchor_store(&store, map)
            .unwrap();
        assert_ne!(other.anchors, scratch.anchors);
        let again = c
            .with_anchor_store(other.anchor_store().unwrap(), map)
            .unwrap();
        assert_eq!(again.anchors, scratch.anchors);
    }
    // a store of another size is refused, naming it
    let small = AnchorStore::new(
        &moma_io::grey_half(ndarray::Array3::<u8>::zeros((16, 16, 3)).view()).unwrap(),
        &MetricDepth::new(ndarray::Array2::from_elem((16, 16), 0.8)),
    )
    .unwrap();
    let c = cal(0, Method::Gssa);
    let e = c.with_anchor_store(&small, &preds.maps[0]).unwrap_err();
    assert!(e.to_string().contains("anchor store"), "{e}");
}

/// K = 1 is the one-shot protocol (every current number unchanged); K = 2 calibrates on the
/// first two frames and scores the rest, as `evaluate_few_shot`.
#[test]
fn ablations_calibrate_on_the_first_k_frames() {
    let set = set(5);
    let preds = preds(5);
    let norms = [Normalisation::Minmax, Normalisation::Median];
    let cfg = config(&["gssa", "ssra"], &[Normalisation::Minmax], 2);
    let cfg_norms = EvalConfig {
        norms: norms.to_vec(),
        ..cfg.clone()
    };

    // (b) normalisation
    let one = ablate::norms(&set, &preds, &cfg, &norms, 1).unwrap();
    assert_rows_eq(&one, &evaluate(&set, &preds, &cfg_norms).unwrap());
    // K = 1 is also few-shot calibration on one frame: the same numbers
    assert_rows_eq(
        &one,
        &evaluate_few_shot(&set, &preds, &cfg_norms, &[1]).unwrap(),
    );
    let two = ablate::norms(&set, &preds, &cfg, &norms, 2).unwrap();
    assert_rows_eq(
        &two,
        &evaluate_few_shot(&set, &preds, &cfg_norms, &[2]).unwrap(),
    );
    for r in &two {
        assert_eq!(r.variant, "few-shot-2");
        assert_eq!(r.calib_frame, "f0+f1");
        assert_eq!(r.eval_frames, 3);
        assert_eq!(r.frames[0].frame, "f2");
    }
    assert_ne!(one[0].per_image, two[0].per_image);

    // (a) samples: each n as the few-shot evaluation with that n
    let counts = [20, 40];
    let a1 = ablate::samples(&set, &preds, &cfg, &counts, 1).unwrap();
    let a2 = ablate::samples(&set, &preds, &cfg, &counts, 2).unwrap();
    assert_eq!(a2.len(), counts.len() * 2);
    for (k, rows) in [(1, &a1), (2, &a2)] {
        for (i, &n) in counts.iter().enumerate() {
            let c = EvalConfig {
                samples: n,
                ..cfg.clone()
            };
            let want = if k == 1 {
                evaluate(&set, &preds, &c).unwrap()
            } else {
                evaluate_few_shot(&set, &preds, &c, &[k]).unwrap()
            };
            assert_rows_eq(&rows[2 * i..2 * i + 2], &want);
        }
    }

    // (c) sources: a second source gets its own rows with the same frames
    let mut other = preds.clone();
    other.label = "other".into();
    let c2 = ablate::sources(&set, &[preds.clone(), other], &cfg, 2).unwrap();
    assert_eq!(c2.len(), 4);
    let want2 = evaluate_few_shot(&set, &preds, &cfg, &[2]).unwrap();
    assert_rows_eq(&c2[..2], &want2);
    assert_eq!(c2[2].source, "other");
    assert_eq!(c2[2].per_image, want2[0].per_image);
    assert_eq!(timeless(&c2[0]), timeless(&two[0]));

    // tables: the K = 1 title as before, the K = 2 title says what was calibrated on
    let tmp = tempfile::tempdir().unwrap();
    let md = |rows: &[EvalResult], notes: &[EvalNote], sub: &str| {
        let dir = tmp.path().join(sub);
        std::fs::create_dir_all(&dir).unwrap();
        let out = ablate::write_norms(&dir, rows, notes).unwrap();
        std::fs::read_to_string(&out.tables[0]).unwrap()
    };
    let t1 = md(&one, &[], "one");
    assert!(!t1.contains("few-shot"), "{t1}");
    let t2 = md(&two, &[], "two");
    assert!(
        t2.contains("few-shot: calibrated on the first 2 frames")
            && t2.contains("scored on the frames after the first 2"),
        "{t2}"
    );
}

/// A set with too few frames for K: an error the caller turns into a row of the table.
#[test]
fn too_few_frames_for_k_is_a_noted_row() {
    let set = set(3);
    let preds = preds(3);
    let cfg = config(&["gssa"], &[Normalisation::Minmax], 1);
    let e = ablate::norms(&set, &preds, &cfg, &[Normalisation::Minmax], 3).unwrap_err();
    assert!(
        matches!(e, EvalError::TooFewFrames { needed: 4, .. }),
        "{e}"
    );
    let e = ablate::samples(&set, &preds, &cfg, &[20], 3).unwrap_err();
    assert!(
        matches!(e, EvalError::TooFewFrames { needed: 4, .. }),
        "{e}"
    );
    let note = EvalNote::from_error(&e, "few-shot-3").unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let ok = ablate::samples(&set, &preds, &cfg, &[20], 2).unwrap();
    let out = ablate::write_samples(tmp.path(), &ok, &[note]).unwrap();
    let md = std::fs::read_to_string(&out.tables[0]).unwrap();
    let last = md.lines().last().unwrap();
    assert!(
        last.starts_with("| synthetic | — | — | few-shot-3: too few frames: 3, needs at least 4"),
        "{md}"
    );
    // every row has the header's number of cells
    let cells = |l: &str| l.matches(" | ").count();
    assert_eq!(cells(last), cells(md.lines().nth(2).unwrap()));
    // K = 0 and K with a calibration frame are refused
    let e = ablate::norms(&set, &preds, &cfg, &[Normalisation::Minmax], 0).unwrap_err();
    assert!(e.to_string().contains("at least 1"), "{e}");
    let with_frame = EvalConfig {
        calib_frame: Some("f1".into()),
        ..cfg.clone()
    };
    let e = ablate::samples(&set, &preds, &with_frame, &[20], 2).unwrap_err();
    assert!(e.to_string().contains("calibration frame"), "{e}");
}
