//! Per-frame re-alignment on static anchors: a synthetic fixed-camera scene whose test frame
//! adds an object and whose depth model output changes its global scale and shift.

mod common;

use moma_core::align::Method;
use moma_core::normalise::{AlignSpace, Normalisation};
use moma_core::realign::{
    AnchorStore, AnchorTarget, CorrectionModel, RealignConfig, RealignReport, find_anchors,
};
use moma_core::{AlignOptions, CalibrationFrame, PredictionInput};
use moma_core::{Calibration, CoreError, MetricDepth, Prediction, PredictionKind, calibrate};
use ndarray::{Array2, Array3, ArrayView3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const W: usize = 160;
const H: usize = 120;
/// The object added in the test frame: columns 50..100, rows 40..80, at 0.6 m.
fn in_object(u: usize, v: usize) -> bool {
    (50..100).contains(&u) && (40..80).contains(&v)
}

fn table_m(v: usize) -> f32 {
    0.8 + 0.001 * v as f32
}

fn gt(with_object: bool) -> MetricDepth {
    MetricDepth::new(Array2::from_shape_fn((H, W), |(v, u)| {
        if with_object && in_object(u, v) {
            0.6
        } else {
            table_m(v)
        }
    }))
}

/// Background grey: smooth texture in 50–170.
fn background(u: usize, v: usize) -> f32 {
    let (x, y) = (u as f32, v as f32);
    110.0 + 35.0 * (x / 6.0).sin() * (y / 9.0).cos() + 25.0 * ((x + 2.0 * y) / 13.0).sin()
}

/// RGB of a frame: the background (and the object, a texture of its own in the same grey range),
/// brightness ×`gain`, white noise σ = 2 grey levels, shifted right by `shift_px` pixels.
fn rgb(with_object: bool, gain: f32, shift_px: usize, seed: u64) -> Array3<u8> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut img = Array3::<u8>::zeros((H, W, 3));
    for v in 0..H {
        for u in 0..W {
            let us = u.saturating_sub(shift_px);
            let g = if with_object && in_object(u, v) {
                110.0 + 50.0 * ((u as f32) / 3.0).cos() * ((v as f32) / 4.0).sin()
            } else {
                background(us, v)
            };
            for (c, tint) in [0.9f32, 1.0, 1.1].iter().enumerate() {
                let noise: f32 = (rng.random::<f32>() - 0.5) * 2.0 * 3.46; // σ = 2
                img[[v, u, c]] = (gain * g * tint + noise).round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    img
}

/// Disparity a/z + b of a depth map.
fn disparity(z: &MetricDepth, a: f32, b: f32) -> Prediction {
    Prediction::new(
        z.depth_m.mapv(|z| a / z + b),
        PredictionKind::RelativeDisparity,
    )
}

fn calibration() -> Calibration {
    calibration_with(Method::Gssa)
}

fn calibration_with(method: Method) -> Calibration {
    calibration_on(method, &gt(false))
}

/// A table tilted along both image axes (SSRA's features need depth varying with u and v).
fn gt_tilted(with_object: bool) -> MetricDepth {
    MetricDepth::new(Array2::from_shape_fn((H, W), |(v, u)| {
        if with_object && in_object(u, v) {
            0.6
        } else {
            table_m(v) + 0.0015 * u as f32
        }
    }))
}

fn calibration_on(method: Method, g: &MetricDepth) -> Calibration {
    calibration_from(method, g, &disparity(g, 2.0, 0.0))
}

/// The calibration of `method` on ground truth `g` and the depth model's output `pred`, with
/// the anchor store of the background's RGB.
fn calibration_from(method: Method, g: &MetricDepth, pred: &Prediction) -> Calibration {
    let config =
        common::calibration_config(method, Normalisation::None, AlignSpace::Inverse, 100, 3);
    calibrate(&[CalibrationFrame::new(pred, g)], &config)
        .unwrap()
        .with_anchors(&grey(rgb(false, 1.0, 0, 1).view()), g, pred)
        .unwrap()
}

/// The test frame's RGB: the object added, brightness and position unchanged.
fn test_rgb() -> Array3<u8> {
    rgb(true, 1.0, 0, 2)
}

/// The GSSA calibration on the flat table, the test frame's truth (the object added), the depth
/// model's output for it with scale `a` and shift `b` (2 and 0 at calibration), and the one-shot
/// result.
struct TestFrame {
    cal: Calibration,
    truth: MetricDepth,
    pred: Prediction,
    one_shot: MetricDepth,
}

fn test_frame(a: f32, b: f32) -> TestFrame {
    let cal = calibration();
    let truth = gt(true);
    let pred = disparity(&truth, a, b);
    let one_shot = cal.aligned(&pred, &AlignOptions::default()).unwrap().depth;
    TestFrame {
        cal,
        truth,
        pred,
        one_shot,
    }
}

/// Re-alignment of `pred` with the test frame's RGB ([`test_rgb`]).
fn realigned(
    cal: &Calibration,
    pred: &Prediction,
    config: &RealignConfig,
) -> (MetricDepth, RealignReport) {
    align_realigned(cal, pred, test_rgb().view(), config).unwrap()
}

/// Mean absolute error (metres) over pixels where `region` holds.
fn mae_m(d: &MetricDepth, truth: &MetricDepth, region: impl Fn(usize, usize) -> bool) -> f64 {
    let mut s = 0.0;
    let mut n = 0usize;
    for ((v, u), &z) in d.depth_m.indexed_iter() {
        if region(u, v) {
            s += (z as f64 - truth.depth_m[[v, u]] as f64).abs();
            n += 1;
        }
    }
    s / n as f64
}

#[test]
fn recovers_global_change_on_background_and_improves_the_object() {
    // the depth model's output for the same scene changed: scale ×1.15 and a shift
    let TestFrame {
        cal,
        truth,
        pred,
        one_shot,
    } = test_frame(2.3, 0.2);
    for target in [AnchorTarget::CalibrationOutput, AnchorTarget::GroundTruth] {
        let config = RealignConfig {
            ridge: 0.0,
            target,
            ..Default::default()
        };
        let (re, report) = realigned(&cal, &pred, &config);
        assert!(report.accepted, "{report:?}");
        let before = report.held_out_rmse_before_m.unwrap();
        let after = report.held_out_rmse_after_m.unwrap();
        assert!(before > 0.05, "one-shot held-out RMSE {before}");
        // GT stored in whole millimetres: recovered to the quantisation
        assert!(after < 0.5e-3, "held-out RMSE after {after}");
        let bg = |u, v| !in_object(u, v);
        let obj = |u, v| in_object(u, v);
        assert!(mae_m(&one_shot, &truth, bg) > 0.05);
        assert!(
            mae_m(&re, &truth, bg) < 0.5e-3,
            "{}",
            mae_m(&re, &truth, bg)
        );
        // the object never served as anchor, yet the correction of the model's global change fixes it
        let (ob, oa) = (mae_m(&one_shot, &truth, obj), mae_m(&re, &truth, obj));
        assert!(ob > 0.03 && oa < 0.5e-3, "object MAE {ob} -> {oa}");
        // the object is not an anchor: anchors cover at most the background
        // anchor candidates: every 2nd interior half-resolution pixel
        let background_half_px = (1..H / 2 - 1)
            .step_by(2)
            .flat_map(|i| (1..W / 2 - 1).step_by(2).map(move |j| (2 * j, 2 * i)))
            .filter(|&(u, v)| !in_object(u, v))
            .count();
        assert!(report.anchors <= background_half_px, "{}", report.anchors);
        assert!(
            report.anchors > background_half_px * 8 / 10,
            "{}",
            report.anchors
        );
    }
}

#[test]
fn default_ridge_shrinks_but_still_improves() {
    let TestFrame {
        cal,
        truth,
        pred,
        one_shot,
    } = test_frame(2.3, 0.2);
    let (re, report) = realigned(&cal, &pred, &RealignConfig::default());
    assert!(report.accepted);
    let obj = |u, v| in_object(u, v);
    // on a flat background scale and shift are nearly collinear: the (strong, default) ridge
    // shrinks the ill-determined part, so the nearer object is corrected by most, not all, of it
    let (b, a) = (mae_m(&one_shot, &truth, obj), mae_m(&re, &truth, obj));
    assert!(a < 0.3 * b, "object MAE {b} -> {a}");
    // a huge ridge keeps the correction at the identity: rejected (no held-out gain) or tiny
    let stiff = RealignConfig {
        ridge: 1e12,
        ..Default::default()
    };
    let (re2, _) = realigned(&cal, &pred, &stiff);
    assert!((mae_m(&re2, &truth, obj) - mae_m(&one_shot, &truth, obj)).abs() < 1e-4);
}

#[test]
fn planar_correction_recovers_a_tilt() {
    let cal = calibration();
    let truth = gt(true);
    // a change that grows from left to right: disparity × (1 + 0.2·u/W)
    let pred = Prediction::new(
        Array2::from_shape_fn((H, W), |(v, u)| {
            2.0 / truth.depth_m[[v, u]] * (1.0 + 0.2 * u as f32 / W as f32)
        }),
        PredictionKind::RelativeDisparity,
    );
    let one_shot = cal.aligned(&pred, &AlignOptions::default()).unwrap().depth;
    let run = |model| {
        let c = RealignConfig {
            model,
            ridge: 10.0,
            max_anchors: 2000,
            ..Default::default()
        };
        realigned(&cal, &pred, &c)
    };
    let (ss, _) = run(CorrectionModel::ScaleShift);
    let (pl, rep) = run(CorrectionModel::Planar);
    assert!(rep.accepted);
    let obj = |u, v| in_object(u, v);
    let (e0, e1, e2) = (
        mae_m(&one_shot, &truth, obj),
        mae_m(&ss, &truth, obj),
        mae_m(&pl, &truth, obj),
    );
    assert!(
        e2 < e1 && e2 < 0.5 * e0,
        "one-shot {e0}, scale-shift {e1}, planar {e2}"
    );
}

#[test]
fn brightness_and_vibration_keep_the_anchors() {
    let cal = calibration();
    let store = cal.anchor_store().unwrap();
    let base = find_anchors(store, &grey(test_rgb().view()), &Default::default())
        .unwrap()
        .pixels
        .len();
    for (gain, shift) in [(0.8f32, 0usize), (1.2, 0), (1.0, 2), (0.8, 1)] {
        let a = find_anchors(
            store,
            &grey(rgb(true, gain, shift, 5).view()),
            &Default::default(),
        )
        .unwrap();
        assert!(
            a.pixels.len() * 10 >= base * 8,
            "gain {gain}, shift {shift}: {} anchors vs {base}",
            a.pixels.len()
        );
        let k = a.gain.unwrap();
        assert!((k - gain as f64).abs() < 0.03, "gain {k} for {gain}");
        // and no anchor on the object (up to a shift of the test image)
        let on_object = a
            .pixels
            .iter()
            .filter(|&&(u, v, _, _)| in_object(u as usize, v as usize))
            .count();
        assert!(
            on_object * 100 <= a.pixels.len(),
            "{on_object} on the object"
        );
    }
    // the re-alignment itself under brightness 0.8
    let truth = gt(true);
    let pred = disparity(&truth, 2.3, 0.2);
    let (_, report) = align_realigned(
        &cal,
        &pred,
        rgb(true, 0.8, 0, 7).view(),
        &RealignConfig::default(),
    )
    .unwrap();
    assert!(report.accepted, "{report:?}");
}

#[test]
fn fully_covered_background_falls_back_cleanly() {
    let TestFrame {
        cal,
        truth: _,
        pred,
        one_shot,
    } = test_frame(2.3, 0.2);
    // a frame whose every pixel changed: another texture everywhere
    let mut covered = Array3::<u8>::zeros((H, W, 3));
    for ((v, u, _), x) in covered.indexed_iter_mut() {
        *x = (110.0 + 50.0 * ((u as f32) / 3.0).cos() * ((v as f32) / 4.0).sin()) as u8;
    }
    let (re, report) =
        align_realigned(&cal, &pred, covered.view(), &RealignConfig::default()).unwrap();
    assert!(!report.accepted);
    let valid = cal.anchor_store().unwrap().candidate_px();
    assert!(report.anchors * 20 < valid, "{} of {valid}", report.anchors);
    assert!(report.reason.contains("anchor"), "{}", report.reason);
    assert!(
        report.reason.contains("camera moved") && !report.reason.contains("saturated"),
        "{}",
        report.reason
    );
    assert!(report.held_out_rmse_before_m.is_none() && report.held_out_rmse_after_m.is_none());
    assert_eq!(re, one_shot);
    // the report serialises without NaN
    let json = serde_json::to_string(&report).unwrap();
    assert!(!json.contains("NaN") && json.contains("null"), "{json}");
    // a uniform dark frame (lens covered, lights off): the gain k = 0.06 is implausible, so no
    // pixel may match the gain-compressed background
    let dark = Array3::<u8>::from_elem((H, W, 3), 7);
    let (re, r) = align_realigned(&cal, &pred, dark.view(), &RealignConfig::default()).unwrap();
    assert!(!r.accepted && r.anchors == 0, "{r:?}");
    assert!(r.brightness_gain.unwrap() < 0.1);
    assert_eq!(re, one_shot);
    // an over-exposed frame (the table blown out, a review's scene): the reason says so,
    // not that the camera moved
    let mut blown = test_rgb();
    for ((v, _, _), x) in blown.indexed_iter_mut() {
        if v < H - H / 20 {
            *x = 255;
        }
    }
    let (_, r) = align_realigned(&cal, &pred, blown.view(), &RealignConfig::default()).unwrap();
    assert!(!r.accepted, "{r:?}");
    assert!(
        r.reason.contains("% of the frame's image is saturated") && r.reason.contains("exposure"),
        "{}",
        r.reason
    );
    // a black frame: no brightness gain can be estimated, no anchor
    let black = Array3::<u8>::zeros((H, W, 3));
    let (_, r) = align_realigned(&cal, &pred, black.view(), &RealignConfig::default()).unwrap();
    assert!(!r.accepted && r.brightness_gain.is_none() && r.anchors == 0);
}

#[test]
fn rejected_when_the_correction_does_not_help() {
    // the prediction did not change: the one-shot result is already right on the anchors; a
    // correction fitted to millimetre quantisation must not be applied blindly
    let TestFrame {
        cal,
        truth,
        pred,
        one_shot,
    } = test_frame(2.0, 0.0);
    let (re, report) = realigned(&cal, &pred, &RealignConfig::default());
    let obj = |u, v| in_object(u, v);
    // accepted or not, it never makes the frame worse by more than the quantisation
    assert!(mae_m(&re, &truth, obj) <= mae_m(&one_shot, &truth, obj) + 0.5e-3);
    assert!(!report.accepted, "{report:?}");
    assert!(
        report.reason.contains("does not lower"),
        "{}",
        report.reason
    );
    assert_eq!(re, one_shot);
}

/// The calibration as its file holds it (moma-io writes the anchor store as `anchors`).
fn file_json(cal: &Calibration) -> serde_json::Value {
    let file = moma_io::CalibrationFile::new(cal.clone(), None, moma_io::CreationInfo::now());
    serde_json::to_value(file).unwrap()["calibration"].clone()
}

/// [`file_json`] read back through the calibration file.
fn from_file_json(json: serde_json::Value) -> Result<Calibration, String> {
    let mut v = serde_json::to_value(moma_io::CalibrationFile::new(
        calibration(),
        None,
        moma_io::CreationInfo::now(),
    ))
    .unwrap();
    v["calibration"] = json;
    serde_json::from_value::<moma_io::CalibrationFile>(v)
        .map(|f| f.calibration)
        .map_err(|e| e.to_string())
}

#[test]
fn anchor_store_file_round_trip_and_bad_input() {
    let cal = calibration();
    let json = file_json(&cal);
    let back = from_file_json(json.clone()).unwrap();
    assert_eq!(back, cal);
    back.validate().unwrap();
    let store = cal.anchor_store().unwrap();
    // grey, ground truth, the calibration's own result and its normalised prediction: 9 bytes
    // per half-resolution pixel
    assert!(store.has_normalised());
    assert_eq!(store.stored_bytes(), (W / 2) * (H / 2) * 9);
    // at 640×480: 320·240·3 bytes, ≈ 4/3 of that in base64
    let big = AnchorStore::new(
        &grey(Array3::<u8>::zeros((480, 640, 3)).view()),
        &MetricDepth::new(Array2::from_elem((480, 640), 1.0)),
    )
    .unwrap();
    assert_eq!(big.stored_bytes(), 230_400);
    let mut with_big = cal.clone();
    with_big.anchors = Some(std::sync::Arc::new(big));
    let big_json = file_json(&with_big)["anchors"].to_string();
    assert!(
        (307_000..310_000).contains(&big_json.len()),
        "{}",
        big_json.len()
    );
    // the core calibration serialises no anchors itself; without a store the file has no
    // `anchors` key and reads back without one
    assert!(!serde_json::to_string(&cal).unwrap().contains("grey_b64"));
    let mut plain = cal.clone();
    plain.anchors = None;
    let pj = file_json(&plain);
    assert!(pj.get("anchors").is_none());
    assert_eq!(from_file_json(pj).unwrap(), plain);
    // corrupted stores are refused with a message naming the field
    let mut bad = json.clone();
    bad["anchors"]["grey_b64"] = "AAAA".into();
    let e = from_file_json(bad).unwrap_err();
    assert!(e.contains("grey_b64"), "{e}");
    let mut bad = json.clone();
    bad["anchors"]["depth_mm_b64"] = "A*==".into();
    let e = from_file_json(bad).unwrap_err();
    assert!(e.contains("depth_mm_b64"), "{e}");
    let mut bad = json;
    bad["anchors"]["extra"] = 1.into();
    assert!(from_file_json(bad).is_err());
}

#[test]
fn no_anchor_store_is_a_clear_error() {
    let mut cal = calibration();
    cal.anchors = None;
    let truth = gt(true);
    let e = align_realigned(
        &cal,
        &disparity(&truth, 2.0, 0.0),
        test_rgb().view(),
        &RealignConfig::default(),
    )
    .unwrap_err();
    assert!(matches!(e, CoreError::InvalidParameter(_)));
    assert!(e.to_string().contains("no anchor store"), "{e}");
    // wrong RGB size and channel count
    let cal = calibration();
    let pred = disparity(&truth, 2.0, 0.0);
    let small = Array3::<u8>::zeros((H / 2, W, 3));
    assert!(matches!(
        align_realigned(&cal, &pred, small.view(), &RealignConfig::default()),
        Err(CoreError::SizeMismatch { .. })
    ));
    // a store without the calibration's own result cannot serve the calibration-output target
    let mut gt_only = cal.clone();
    gt_only.anchors = Some(std::sync::Arc::new(
        AnchorStore::new(&grey(rgb(false, 1.0, 0, 1).view()), &gt(false)).unwrap(),
    ));
    let e = align_realigned(
        &gt_only,
        &pred,
        test_rgb().view(),
        &RealignConfig::default(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("calibration-output"), "{e}");
    let gt_target = RealignConfig {
        target: AnchorTarget::GroundTruth,
        ..Default::default()
    };
    assert!(align_realigned(&gt_only, &pred, test_rgb().view(), &gt_target).is_ok());
    let grey = Array3::<u8>::zeros((H, W, 1));
    assert!(align_realigned(&cal, &pred, grey.view(), &RealignConfig::default()).is_err());
    let bad = RealignConfig {
        holdout_fraction: 1.0,
        ..Default::default()
    };
    assert!(align_realigned(&cal, &pred, test_rgb().view(), &bad).is_err());
}

/// The prediction-affine correction is exact for every method when the prediction of the
/// whole scene changed by an affine map in its own space: the result is the calibration's model
/// applied to the prediction as it would have been without the change (an independent
/// expectation), on the background and on the object that never served as anchor.
#[test]
fn prediction_affine_is_exact_for_every_method() {
    let truth = gt_tilted(true);
    let changed = disparity(&truth, 2.3, 0.2);
    let unchanged = disparity(&truth, 2.0, 0.0);
    let config = RealignConfig {
        model: CorrectionModel::PredictionAffine,
        ridge: 0.0,
        max_anchors: 2000,
        ..Default::default()
    };
    // LWLR and the local variant vary over the image: an output-space scale/shift is not exact
    // for them, the prediction-space map is
    for method in ["gssa", "lwlr", "gssa-local"] {
        let cal = calibration_on(method.parse().unwrap(), &gt_tilted(false));
        let expected = cal
            .aligned(&unchanged, &AlignOptions::default())
            .unwrap()
            .depth;
        let one_shot = cal
            .aligned(&changed, &AlignOptions::default())
            .unwrap()
            .depth;
        let (re, report) = realigned(&cal, &changed, &config);
        assert!(report.accepted, "{method}: {report:?}");
        assert_eq!(report.correction, Some(CorrectionModel::PredictionAffine));
        // ẑ_new = 1.15·ẑ_cal + 0.2 (no normalisation): the map back is a = 1/1.15, b = −0.2/1.15
        let [a, b] = report.prediction_affine.unwrap();
        assert!((a - 1.0 / 1.15).abs() < 1e-4, "{method}: a = {a}");
        assert!((b + 0.2 / 1.15).abs() < 1e-4, "{method}: b = {b}");
        let mut worst = 0.0f32;
        for (z, e) in re.depth_m.iter().zip(expected.depth_m.iter()) {
            if e.is_finite() {
                worst = worst.max((z - e).abs());
            }
        }
        assert!(worst < 1e-4, "{method}: largest difference {worst} m");
        // the frame's own error against the calibration's truth at the held-out anchors: the
        // corrected depth's (the exact calibration, to the truth's whole millimetres), not the
        // one-shot result's
        let truth_m = report.held_out_truth_rmse_m.unwrap();
        let bg = |u, v| !in_object(u, v);
        assert!(
            truth_m < 1e-3 && mae_m(&one_shot, &truth, bg) > 0.01,
            "{method}: held-out truth RMSE {truth_m} m"
        );
        let obj = |u, v| in_object(u, v);
        assert!(
            mae_m(&one_shot, &truth, obj) > 0.03,
            "{method}: the change must matter"
        );
    }
    // the same from the normalised prediction (as the evaluation gives it), into a buffer
    let cal = calibration_on("lwlr".parse().unwrap(), &gt_tilted(false));
    let normalised = cal.normalise(&changed).unwrap();
    let mut buf = MetricDepth::new(Array2::zeros(changed.values.raw_dim()));
    let r = cal
        .align(
            PredictionInput::normalised(&normalised, changed.kind),
            &AlignOptions::realigned(&grey(test_rgb().view()), &config),
            &mut buf.depth_m.view_mut(),
        )
        .unwrap();
    assert!(r.realign.is_some_and(|r| r.accepted));
    let expected = cal
        .aligned(&unchanged, &AlignOptions::default())
        .unwrap()
        .depth;
    let d = buf
        .depth_m
        .iter()
        .zip(expected.depth_m.iter())
        .filter(|(_, e)| e.is_finite())
        .map(|(z, e)| (z - e).abs())
        .fold(0.0f32, f32::max);
    assert!(d < 1e-4, "{d}");
}

#[test]
fn prediction_affine_needs_the_stored_prediction_and_the_normalised_map() {
    let cal = calibration();
    let truth = gt(true);
    let pred = disparity(&truth, 2.3, 0.2);
    let pa = RealignConfig {
        model: CorrectionModel::PredictionAffine,
        ..Default::default()
    };
    // an output-space entry point cannot run it
    let mut d = cal.aligned(&pred, &AlignOptions::default()).unwrap().depth;
    let store = cal.anchor_store().unwrap();
    let e = moma_core::realign::realign_in_place(
        store,
        &grey(test_rgb().view()),
        cal.space(),
        &pa,
        &mut d.depth_m.view_mut(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("normalised prediction"), "{e}");
    // a store written before the prediction-affine correction (no normalised_b64) still reads,
    // serves scale-shift, and refuses prediction-affine with a clear message
    let mut v = file_json(&cal);
    assert!(v["anchors"]["normalised_b64"].is_string());
    v["anchors"]
        .as_object_mut()
        .unwrap()
        .remove("normalised_b64");
    let old = from_file_json(v).unwrap();
    assert!(!old.anchor_store().unwrap().has_normalised());
    let e = align_realigned(&old, &pred, test_rgb().view(), &pa).unwrap_err();
    assert!(e.to_string().contains("calibrate again"), "{e}");
    let (_, r) =
        align_realigned(&old, &pred, test_rgb().view(), &RealignConfig::default()).unwrap();
    assert!(r.accepted, "{r:?}");
    // target ground-truth is refused for prediction-affine
    let e = align_realigned(
        &cal,
        &pred,
        test_rgb().view(),
        &RealignConfig {
            target: AnchorTarget::GroundTruth,
            ..pa
        },
    )
    .unwrap_err();
    assert!(e.to_string().contains("ground-truth"), "{e}");
    // a corrupted normalised_b64 is refused naming the field
    let mut v = file_json(&cal);
    v["anchors"]["normalised_b64"] = "AAAA".into();
    let e = from_file_json(v).unwrap_err();
    assert!(e.contains("normalised_b64"), "{e}");
    // a fully covered background falls back with the reason, depth = one-shot
    let covered = Array3::from_shape_fn((H, W, 3), |(v, u, _)| {
        (110.0 + 50.0 * ((u as f32) / 3.0).cos() * ((v as f32) / 4.0).sin()) as u8
    });
    let (re, r) = align_realigned(&cal, &pred, covered.view(), &pa).unwrap();
    assert!(!r.accepted && r.reason.contains("anchor"), "{r:?}");
    assert_eq!(
        re,
        cal.aligned(&pred, &AlignOptions::default()).unwrap().depth
    );
}

/// The acceptance margin: a correction whose held-out gain is not beyond its standard error is
/// rejected; with an unreachable margin nothing is accepted.
#[test]
fn acceptance_margin_rejects_with_the_gain_in_the_report() {
    let TestFrame {
        cal,
        truth: _,
        pred,
        one_shot,
    } = test_frame(2.3, 0.2);
    let (_, ok) = realigned(&cal, &pred, &RealignConfig::default());
    assert!(ok.accepted);
    let (g, se) = (ok.held_out_gain_m.unwrap(), ok.held_out_gain_se_m.unwrap());
    assert!(g > se && g > 0.0, "gain {g}, se {se}");
    let strict = RealignConfig {
        acceptance_se: 1e9,
        ..Default::default()
    };
    let (re, r) = realigned(&cal, &pred, &strict);
    assert!(!r.accepted && r.reason.contains("does not lower"), "{r:?}");
    assert_eq!(re, one_shot);
    let bad = RealignConfig {
        acceptance_se: -1.0,
        ..Default::default()
    };
    assert!(bad.validate().is_err());
}

/// One frame aligned and re-aligned through the one path ([`Calibration::aligned`]): metres and
/// the re-alignment report.
/// The grey that re-alignment compares, of an RGB image (`moma_io::grey_half`).
fn grey(rgb: ArrayView3<'_, u8>) -> moma_core::realign::GreyHalf {
    moma_io::grey_half(rgb).unwrap()
}

fn align_realigned(
    cal: &Calibration,
    pred: &Prediction,
    rgb: ArrayView3<'_, u8>,
    config: &RealignConfig,
) -> moma_core::Result<(MetricDepth, RealignReport)> {
    let grey = moma_io::grey_half(rgb)?;
    let a = cal.aligned(pred, &AlignOptions::realigned(&grey, config))?;
    let report = a.realign.expect("re-alignment was asked for");
    Ok((a.depth, report))
}

/// The frame's error model follows what the anchors measured (docs/grasping.md, "The re-aligned
/// frame's σ"): its flat σ is the held-out anchors' error against the calibration frame's ground
/// truth, at the model's reference depth, whatever the correction's target, with the
/// calibration's short-range fields kept. A report written before that residual existed falls
/// back to the target's RMSE: onto the calibration's own output it adds to the calibration
/// frame's own error; onto the ground truth it replaces it. A report without `target` reads as
/// the default target.
#[test]
fn the_frame_error_model_follows_what_the_anchors_measured() {
    let TestFrame { cal, pred, .. } = test_frame(2.3, 0.2);
    let model = cal
        .error_model
        .clone()
        .expect("calibrate fits an error model");
    let dense = model
        .sigma_dense_m
        .expect("a fitted model records its dense part");
    assert!(dense <= model.sigma_flat_m);
    assert_eq!(model.depth_exponent, 2.0, "inverse space: σ grows as z²");
    let fields2 = dense * dense * model.variance_shares[1..].iter().sum::<f64>();
    for target in [AnchorTarget::CalibrationOutput, AnchorTarget::GroundTruth] {
        let config = RealignConfig {
            ridge: 0.0,
            target,
            ..Default::default()
        };
        let (_, report) = realigned(&cal, &pred, &config);
        assert_eq!(report.target, target);
        assert!(report.accepted, "{report:?}");
        let after = report.held_out_rmse_after_m.unwrap();
        let truth = report.held_out_truth_rmse_m.unwrap();
        let inverse = report.held_out_truth_inverse_rmse_per_m.unwrap();
        // the exact calibration: both measure the truth's whole millimetres (the truth RMSE on
        // the anchors no fit used, the target's on the held-out ones)
        assert!(
            truth < 0.5e-3 && after < 0.5e-3,
            "{target:?}: {truth} m, {after} m"
        );
        let at_ref = inverse * model.depth_ref_m * model.depth_ref_m;
        let expected = (at_ref * at_ref)
            .max(fields2)
            .max((0.25 * dense).powi(2))
            .sqrt();
        let sigma = cal.frame_error_model(Some(&report)).unwrap().sigma_flat_m;
        assert!(
            (sigma - expected).abs() <= 1e-12 * expected.max(1e-3),
            "{target:?}: σ {sigma} m, expected {expected} m (dense {dense}, inverse {inverse})"
        );
        // a report written before the truth residual existed: the target's RMSE
        let mut json = serde_json::to_value(&report).unwrap();
        let fields = json.as_object_mut().unwrap();
        fields.remove("held_out_truth_rmse_m").unwrap();
        fields.remove("held_out_truth_inverse_rmse_per_m").unwrap();
        let old: RealignReport = serde_json::from_value(json).unwrap();
        let sigma = cal.frame_error_model(Some(&old)).unwrap().sigma_flat_m;
        let expected = match target {
            AnchorTarget::CalibrationOutput => (dense * dense + after * after).sqrt(),
            AnchorTarget::GroundTruth => after.max(0.25 * model.sigma_flat_m),
        };
        assert!(
            (sigma - expected).abs() <= 1e-12 * expected.max(1e-3),
            "{target:?}, older report: σ {sigma} m, expected {expected} m"
        );
        // without re-alignment, the calibration's model
        assert_eq!(cal.frame_error_model(None), Some(model.clone()));
    }
    let (_, report) = realigned(&cal, &pred, &RealignConfig::default());
    let mut json = serde_json::to_value(&report).unwrap();
    json.as_object_mut().unwrap().remove("target");
    let old: RealignReport = serde_json::from_value(json).unwrap();
    assert_eq!(old.target, AnchorTarget::CalibrationOutput);
}

/// The depth model's output with a ripple that no global fit follows: disparity `a/z + b` plus
/// 0.02·sin(u/4 + v/7) (about 7 mm at the table's 0.85 m).
fn rippled(z: &MetricDepth, a: f32, b: f32) -> Prediction {
    Prediction::new(
        Array2::from_shape_fn(z.depth_m.dim(), |(v, u)| {
            a / z.depth_m[[v, u]] + b + 0.02 * (u as f32 / 4.0 + v as f32 / 7.0).sin()
        }),
        PredictionKind::RelativeDisparity,
    )
}

/// Re-aligned onto the calibration's own output, the held-out RMSE measures only what changed
/// since calibration; the truth residual measures the frame's error on the background, which
/// here is the ripple the calibration itself could not fit: checked against the dense error of
/// the re-aligned depth over the whole background, in metres and in inverse depth, and the
/// frame's σ map covers those errors as a σ should.
#[test]
fn the_held_out_truth_residual_is_the_frames_error_on_the_background() {
    let table = gt(false);
    let cal = calibration_from(Method::Gssa, &table, &rippled(&table, 2.0, 0.0));
    let truth = gt(true);
    let pred = rippled(&truth, 2.3, 0.2);
    let (re, report) = realigned(
        &cal,
        &pred,
        &RealignConfig {
            ridge: 0.0,
            ..Default::default()
        },
    );
    assert!(report.accepted, "{report:?}");
    // the background's dense error, away from the object's border
    let (mut e2, mut i2, mut n) = (0.0, 0.0, 0usize);
    let mut errors = Vec::new();
    for ((v, u), &z) in re.depth_m.indexed_iter() {
        let near_object = (45..105).contains(&u) && (35..85).contains(&v);
        if near_object {
            continue;
        }
        let t = truth.depth_m[[v, u]] as f64;
        let e = z as f64 - t;
        e2 += e * e;
        i2 += (1.0 / z as f64 - 1.0 / t).powi(2);
        n += 1;
        errors.push((v, u, e.abs()));
    }
    let (rms_m, rms_inv) = ((e2 / n as f64).sqrt(), (i2 / n as f64).sqrt());
    assert!(
        rms_m > 3e-3,
        "the ripple leaves {rms_m} m on the background"
    );
    let truth_m = report.held_out_truth_rmse_m.unwrap();
    let truth_inv = report.held_out_truth_inverse_rmse_per_m.unwrap();
    // ~60 held-out anchors, their largest 10 % trimmed
    for (got, dense) in [(truth_m, rms_m), (truth_inv, rms_inv)] {
        assert!(
            (0.6 * dense..=1.1 * dense).contains(&got),
            "held-out {got} against the background's {dense}"
        );
    }
    let drift = report.held_out_rmse_after_m.unwrap();
    assert!(
        drift < 0.3 * truth_m,
        "the drift residual {drift} m is not the frame's error {truth_m} m"
    );
    // the frame's σ map: the background's errors within ±1σ and ±2σ near a Gaussian's shares
    let model = cal.frame_error_model(Some(&report)).unwrap();
    let sigma = model.sigma_map(&re);
    let within = |k: f64| {
        errors
            .iter()
            .filter(|&&(v, u, e)| e <= k * sigma[[v, u]] as f64)
            .count() as f64
            / errors.len() as f64
    };
    let (one, two) = (within(1.0), within(2.0));
    assert!(
        (0.5..=0.85).contains(&one) && two >= 0.9,
        "±1σ {one}, ±2σ {two}"
    );
}
