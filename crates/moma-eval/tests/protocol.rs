//! The evaluation protocol against an independent implementation of docs/method.md §3, and bad input.

mod common;

use common::*;
use moma_core::normalise::Normalisation;
use moma_core::sampling::{SamplingConfig, sample_pixels};
use moma_eval::EvalError;
use moma_eval::protocol::{EvalConfig, PredictionSet, evaluate};
use ndarray::Array2;

fn config(methods: &[&str], norm: Normalisation, seeds: usize) -> EvalConfig {
    EvalConfig {
        methods: methods.iter().map(|s| s.parse().unwrap()).collect(),
        norms: vec![norm],
        samples: 30,
        seeds,
        ..Default::default()
    }
}

fn close(a: f64, b: f64, what: &str) {
    assert!((a - b).abs() <= 1e-6, "{what}: moma {a} vs reference {b}");
}

/// The error and its sources joined by ": ", as the CLI prints them.
fn chain(e: &dyn std::error::Error) -> String {
    let mut parts = vec![e.to_string()];
    let mut source = e.source();
    while let Some(s) = source {
        parts.push(s.to_string());
        source = s.source();
    }
    parts.join(": ")
}

#[test]
fn raw_metrics_match_reference_per_image_mean() {
    let set = set(4);
    let preds = preds(4);
    let res = evaluate(&set, &preds, &config(&["raw"], Normalisation::Minmax, 3)).unwrap();
    assert_eq!(res.len(), 1);
    let r = &res[0];
    assert_eq!((r.method.as_str(), r.norm.as_str()), ("raw", "none"));
    assert_eq!(r.calib_frame, "f0");
    assert_eq!(r.eval_frames, 3);
    let per: Vec<[f64; 6]> = (1..4)
        .map(|k| {
            let m = set.frames[k].mask.as_ref().unwrap().data().clone();
            reference_metrics(&preds.maps[k].values, &set.frames[k].gt.depth_m, &m)
        })
        .collect();
    let mean = |i: usize| per.iter().map(|p| p[i]).sum::<f64>() / per.len() as f64;
    let s = &r.per_image;
    for (i, (name, stat)) in [
        ("d105", s.d105),
        ("d110", s.d110),
        ("d125", s.d125),
        ("rel", s.rel),
        ("rmse", s.rmse),
        ("mae", s.mae),
    ]
    .into_iter()
    .enumerate()
    {
        close(stat.mean, mean(i), name);
        close(stat.std, 0.0, name);
    }
}

/// Independent GSSA with the paper's min-max normalisation on the same sampled pixels.
fn reference_gssa(
    set: &moma_eval::data::LoadedSet,
    preds: &PredictionSet,
    seed: u64,
    n: usize,
) -> Vec<[f64; 6]> {
    let norm = |a: &Array2<f32>| -> Array2<f64> {
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for &x in a {
            lo = lo.min(x as f64);
            hi = hi.max(x as f64);
        }
        a.mapv(|x| (x as f64 - lo) / (hi - lo) + lo)
    };
    let calib = norm(&preds.maps[0].values);
    let px = sample_pixels(
        &set.frames[0].gt,
        &SamplingConfig {
            n,
            seed,
            ..Default::default()
        },
        None,
    )
    .unwrap();
    let (mut sx, mut sy, mut sxx, mut sxy, mut k) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for p in &px {
        let x = calib[[p.v as usize, p.u as usize]];
        let y = set.frames[0].gt.depth_m[[p.v as usize, p.u as usize]] as f64;
        sx += x;
        sy += y;
        sxx += x * x;
        sxy += x * y;
        k += 1.0;
    }
    let s = (k * sxy - sx * sy) / (k * sxx - sx * sx);
    let t = (sy - s * sx) / k;
    (1..set.frames.len())
        .map(|i| {
            let aligned = norm(&preds.maps[i].values).mapv(|x| (s * x + t) as f32);
            let m = set.frames[i].mask.as_ref().unwrap().data().clone();
            reference_metrics(&aligned, &set.frames[i].gt.depth_m, &m)
        })
        .collect()
}

#[test]
fn gssa_metrics_match_independent_fit_and_metrics() {
    let set = set(3);
    let preds = preds(3);
    let seeds = 4;
    let res = evaluate(
        &set,
        &preds,
        &config(&["gssa"], Normalisation::Minmax, seeds),
    )
    .unwrap();
    let r = &res[0];
    let mut per_seed_means = Vec::new();
    for s in 0..seeds {
        let refm = reference_gssa(&set, &preds, s as u64, 30);
        for (fi, fr) in r.frames.iter().enumerate() {
            let m = fr.per_seed[s];
            for (i, got) in [m.d105, m.d110, m.d125, m.rel, m.rmse, m.mae]
                .into_iter()
                .enumerate()
            {
                // the fit is done in f64 by both; aligned maps are f32, so allow f32 rounding
                assert!(
                    (got - refm[fi][i]).abs() <= 1e-6,
                    "seed {s} frame {} metric {i}: {got} vs {}",
                    fr.frame,
                    refm[fi][i]
                );
            }
        }
        per_seed_means.push(refm.iter().map(|m| m[5]).sum::<f64>() / refm.len() as f64);
    }
    let mean = per_seed_means.iter().sum::<f64>() / seeds as f64;
    let std = (per_seed_means
        .iter()
        .map(|x| (x - mean).powi(2))
        .sum::<f64>()
        / seeds as f64)
        .sqrt();
    close(r.per_image.mae.mean, mean, "mae mean over seeds");
    close(r.per_image.mae.std, std, "mae std over seeds");
}

#[test]
fn every_method_runs_and_json_contract_has_the_keys() {
    let set = set(3);
    let preds = preds(3);
    let res = evaluate(
        &set,
        &preds,
        &config(&["ssra", "gssa", "lwlr", "raw"], Normalisation::Minmax, 2),
    )
    .unwrap();
    assert_eq!(res.len(), 4);
    let json = moma_eval::report::contract_json(&res).unwrap();
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    let arr = v.as_array().unwrap();
    assert_eq!(arr.len(), 4);
    for o in arr {
        for k in ["set", "method", "norm", "samples", "seeds", "calib_frame"] {
            assert!(o.get(k).is_some(), "missing {k}");
        }
        for k in ["d105", "d110", "d125", "rel", "rmse", "mae"] {
            assert!(o[k]["mean"].is_number() && o[k]["std"].is_number(), "{k}");
        }
    }
    let md = moma_eval::report::eval_table(&res, false).to_markdown();
    assert!(md.contains("SSRA") && md.contains("δ1.05"));
}

#[test]
fn one_frame_set_is_an_error() {
    let e = evaluate(
        &set(1),
        &preds(1),
        &config(&["gssa"], Normalisation::Minmax, 1),
    )
    .unwrap_err();
    assert!(matches!(e, EvalError::Set { .. }), "{e}");
    assert!(chain(&e).contains("synthetic"), "{e}");
}

#[test]
fn mask_without_valid_ground_truth_names_the_frame() {
    let mut s = set(3);
    s.frames[2].mask = Some(moma_core::Mask::new(Array2::from_shape_fn(
        (H, W),
        |(v, u)| u < 3 && v < 3,
    )));
    let e = evaluate(&s, &preds(3), &config(&["gssa"], Normalisation::Minmax, 1)).unwrap_err();
    let msg = chain(&e);
    assert!(
        msg.contains("f2") && msg.contains("no pixel with valid ground truth"),
        "{msg}"
    );
}

#[test]
fn size_mismatch_names_the_frame() {
    let mut p = preds(3);
    p.maps[1] = moma_core::Prediction::new(
        Array2::from_elem((H, W + 1), 1.0),
        moma_core::PredictionKind::MetricDepth,
    );
    let e = evaluate(&set(3), &p, &config(&["gssa"], Normalisation::Minmax, 1)).unwrap_err();
    let msg = chain(&e);
    assert!(
        msg.contains("'f1'") && msg.contains("prediction is"),
        "{msg}"
    );
}

#[test]
fn missing_prediction_file_names_the_frame() {
    let dir = tempfile::tempdir().unwrap();
    let s = set(3);
    moma_io::write_npy_f32(dir.path().join("f0.npy"), preds(1).maps[0].values.view()).unwrap();
    let e = PredictionSet::read(&s, dir.path(), Some(moma_core::PredictionKind::MetricDepth))
        .unwrap_err();
    let msg = chain(&e);
    assert!(
        msg.contains("'f1'") && msg.contains("missing prediction file"),
        "{msg}"
    );
}

#[test]
fn unknown_calibration_frame_is_an_error() {
    let mut c = config(&["gssa"], Normalisation::Minmax, 1);
    c.calib_frame = Some("nope".into());
    let e = evaluate(&set(3), &preds(3), &c).unwrap_err();
    assert!(chain(&e).contains("nope"));
    c.calib_frame = Some("f2".into());
    let r = evaluate(&set(3), &preds(3), &c).unwrap();
    assert_eq!(r[0].calib_frame, "f2");
    assert_eq!(
        r[0].frames
            .iter()
            .map(|f| f.frame.as_str())
            .collect::<Vec<_>>(),
        vec!["f0", "f1"]
    );
}

#[test]
fn depth_range_limits_scored_pixels() {
    let mut c = config(&["raw"], Normalisation::Minmax, 1);
    let all = evaluate(&set(3), &preds(3), &c).unwrap();
    c.depth_range_m = Some((0.0, 0.69));
    let near = evaluate(&set(3), &preds(3), &c).unwrap();
    let n_all: usize = all[0].frames.iter().map(|f| f.per_seed[0].n).sum();
    let n_near: usize = near[0].frames.iter().map(|f| f.per_seed[0].n).sum();
    assert!(n_near < n_all && n_near > 0);
}

#[test]
fn set_round_trips_through_the_layout() {
    let dir = tempfile::tempdir().unwrap();
    let s = set(2);
    moma_eval::data::write_set(dir.path(), &s).unwrap();
    let back = moma_eval::data::load_set(dir.path()).unwrap();
    assert_eq!(back.frames.len(), 2);
    assert_eq!(back.intrinsics, s.intrinsics);
    for (a, b) in back.frames.iter().zip(&s.frames) {
        assert_eq!(a.mask, b.mask);
        for (x, y) in a.gt.depth_m.iter().zip(b.gt.depth_m.iter()) {
            // invalid depth (0 here) reads back as NaN, moma's one convention
            let (vx, vy) = (moma_core::is_valid_depth(*x), moma_core::is_valid_depth(*y));
            assert_eq!(vx, vy);
            assert!(!vx || (x - y).abs() <= 0.0005 + 1e-6);
        }
    }
}

/// A workspace: the right two thirds of the image (holds part of every frame's bump).
fn workspace() -> moma_core::Mask {
    moma_core::Mask::new(Array2::from_shape_fn((H, W), |(_, u)| u >= W / 3))
}

#[test]
fn workspace_normalises_over_the_fixed_region_in_every_frame() {
    use moma_core::normalise::{NormalisationConfig, normalise};
    use moma_eval::protocol::Prepared;
    let (s, p) = (set(3), preds(3));
    let mut c = config(&["gssa"], Normalisation::Minmax, 2);
    c.workspace = Some(workspace());
    let prep = Prepared::new(&s, &p, &c).unwrap();
    let norm = NormalisationConfig {
        method: Normalisation::Minmax,
        space: moma_core::AlignSpace::Depth,
    };
    let ws = workspace();
    for i in 0..3 {
        let got = prep.normalised(i, &norm).unwrap();
        let want = normalise(&p.maps[i], &norm, Some(&ws)).unwrap();
        assert_eq!(got.values, want.values, "frame {i}");
        // paper min-max over the workspace: z -> (z - min)/(max - min) + min, so the values
        // inside it span exactly 1 (outside they may leave that range)
        let inside: Vec<f32> = got
            .values
            .iter()
            .zip(ws.data().iter())
            .filter(|(_, m)| **m)
            .map(|(v, _)| *v)
            .collect();
        let lo = inside.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = inside.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        assert!((hi - lo - 1.0).abs() < 1e-5, "{lo} {hi}");
        let whole = normalise(&p.maps[i], &norm, None).unwrap();
        assert_ne!(got.values, whole.values, "frame {i}");
    }
}

#[test]
fn workspace_changes_results_and_full_workspace_does_not() {
    let (s, p) = (set(3), preds(3));
    let base = config(&["gssa", "ssra"], Normalisation::Minmax, 2);
    let plain = evaluate(&s, &p, &base).unwrap();
    let mut full = base.clone();
    full.workspace = Some(moma_core::Mask::full(s.size()));
    let same = evaluate(&s, &p, &full).unwrap();
    assert_eq!(same.len(), plain.len());
    for (a, b) in same.iter().zip(&plain) {
        assert_eq!(
            (&a.method, a.per_image, a.pooled),
            (&b.method, b.per_image, b.pooled)
        );
        assert_eq!(a.frames, b.frames);
    }
    let mut part = base.clone();
    part.workspace = Some(workspace());
    let ws = evaluate(&s, &p, &part).unwrap();
    assert_eq!(ws.len(), plain.len());
    assert_ne!(ws[0].per_image.mae.mean, plain[0].per_image.mae.mean);
    assert!(ws.iter().all(|r| r.per_image.mae.mean.is_finite()));
}

#[test]
fn workspace_of_the_wrong_size_or_empty_is_an_error() {
    let (s, p) = (set(3), preds(3));
    let mut c = config(&["gssa"], Normalisation::Minmax, 1);
    c.workspace = Some(moma_core::Mask::full(moma_core::ImageSize::new(W + 1, H)));
    let msg = chain(&evaluate(&s, &p, &c).unwrap_err());
    assert!(
        msg.contains("workspace") && msg.contains("synthetic"),
        "{msg}"
    );
    c.workspace = Some(moma_core::Mask::new(Array2::from_elem((H, W), false)));
    let msg = chain(&evaluate(&s, &p, &c).unwrap_err());
    assert!(msg.contains("workspace") && msg.contains("empty"), "{msg}");
}

#[test]
fn load_errors_name_the_frame_and_file() {
    let dir = tempfile::tempdir().unwrap();
    moma_eval::data::write_set(dir.path(), &set(2)).unwrap();
    let bad = dir.path().join("frames").join("f1").join("depth.png");
    std::fs::write(&bad, b"not a png").unwrap();
    let msg = chain(&moma_eval::data::load_set(dir.path()).unwrap_err());
    assert!(msg.contains("f1") && msg.contains("depth.png"), "{msg}");
}

/// `norms` empty: each set's predictions take their kind's default
/// (`moma_core::policy::default_normalisation`, as `moma calibrate` takes it): the rows are those
/// of that normalisation given explicitly, and the one normalisation a grasp evaluation and the
/// demo's figures use (`Prepared::first_norm`) is the same.
#[test]
fn without_norms_each_kind_takes_its_default() {
    use moma_core::{ImageSize, PredictionKind};
    use moma_eval::demo::{DemoScene, build_demo};
    use moma_eval::protocol::Prepared;
    use moma_eval::scene::DemoSceneConfig;
    for (kind, want) in [
        (PredictionKind::MetricDepth, Normalisation::MinmaxUnit),
        (PredictionKind::RelativeDepth, Normalisation::MinmaxUnit),
        (PredictionKind::RelativeDisparity, Normalisation::MinmaxUnit),
    ] {
        let demo = DemoScene {
            scene: DemoSceneConfig {
                size: ImageSize::new(96, 72),
                focal_px: 90.0,
                frames: 3,
                ..Default::default()
            },
            kind,
            ..Default::default()
        };
        let (set, preds) = build_demo(&demo, None).unwrap();
        let default = EvalConfig {
            norms: Vec::new(),
            ..config(&["gssa", "ssra"], want, 2)
        };
        let rows = evaluate(&set, &preds, &default).unwrap();
        let explicit = evaluate(&set, &preds, &config(&["gssa", "ssra"], want, 2)).unwrap();
        assert_eq!(rows.len(), 2, "{kind:?}");
        for (r, e) in rows.iter().zip(&explicit) {
            assert_eq!(r.norm, want.name(), "{kind:?}");
            assert_eq!(r.per_image.mae.mean, e.per_image.mae.mean, "{kind:?}");
        }
        let prep = Prepared::new(&set, &preds, &default).unwrap();
        assert_eq!((prep.norms(), prep.first_norm()), (vec![want], want));
        // given, the configuration's own
        let given = config(&["gssa"], Normalisation::Median, 1);
        let prep = Prepared::new(&set, &preds, &given).unwrap();
        assert_eq!(prep.first_norm(), Normalisation::Median);
    }
}
