//! The error model's height part (`moma_core::height`): the support plane and the heights
//! above it in closed form on a tilted table with boxes, no plane where there is none, the σ map
//! and the draws of the part, and the calibration's object pull against least squares written
//! out here.

mod common;

use moma_core::align::Method;
use moma_core::height::{height_above_plane, support_plane};
use moma_core::normalise::{AlignSpace, Normalisation};
use moma_core::pipeline::{CalibrationConfig, CalibrationFrame, calibrate};
use moma_core::{DepthErrorModel, MetricDepth, Prediction, PredictionKind};
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const W: usize = 160;
const H: usize = 120;
/// The table in inverse depth over pixels: 1/z = A·u + B·v + C (1/m), 0.9 m at the top left,
/// about 0.68 m at the bottom right.
const A: f64 = 0.0005;
const B: f64 = 0.002646;
const C: f64 = 1.0 / 0.9;

/// Boxes: (u0, u1, v0, v1, height in metres along the ray).
const BOX_A: (usize, usize, usize, usize, f64) = (30, 60, 40, 70, 0.06);
const BOX_B: (usize, usize, usize, usize, f64) = (100, 140, 60, 100, 0.10);

fn table_z(u: usize, v: usize) -> f64 {
    1.0 / (A * u as f64 + B * v as f64 + C)
}

fn inside(b: (usize, usize, usize, usize, f64), u: usize, v: usize) -> bool {
    (b.0..b.1).contains(&u) && (b.2..b.3).contains(&v)
}

/// The scene's true depth with `boxes` standing on the table, metres; `flatten` keeps that share
/// of each box's height (1: the truth).
fn scene(boxes: &[(usize, usize, usize, usize, f64)], flatten: f64) -> Array2<f32> {
    Array2::from_shape_fn((H, W), |(v, u)| {
        let h = boxes
            .iter()
            .find(|b| inside(**b, u, v))
            .map_or(0.0, |b| b.4);
        (table_z(u, v) - flatten * h) as f32
    })
}

#[test]
fn the_support_plane_of_a_tilted_table_and_the_boxes_heights_in_closed_form() {
    let z = scene(&[BOX_A, BOX_B], 1.0);
    let p = support_plane(z.view()).expect("a table holds 87 % of the pixels");
    for (got, want) in [(p.a, A), (p.b, B), (p.c, C)] {
        assert!((got - want).abs() <= 1e-6 * C, "plane {p:?}");
    }
    let h = height_above_plane(z.view()).unwrap();
    for ((v, u), &hh) in h.indexed_iter() {
        let want = [BOX_A, BOX_B]
            .iter()
            .find(|b| inside(**b, u, v))
            .map_or(0.0, |b| b.4);
        assert!(
            (f64::from(hh) - want).abs() < 2e-5,
            "({u}, {v}): {hh} vs {want}"
        );
    }
    // a depth model's smooth bumps of 2 % on the table: still the plane, the boxes within a bump
    let bumpy = Array2::from_shape_fn((H, W), |(v, u)| {
        z[[v, u]] * (1.0 + 0.02 * ((u as f32 / 20.0).sin() * (v as f32 / 15.0).sin()))
    });
    let h = height_above_plane(bumpy.view()).expect("bumps of 2 % leave the plane");
    let box_b: Vec<f32> = h
        .indexed_iter()
        .filter(|((v, u), _)| inside(BOX_B, *u, *v))
        .map(|(_, &x)| x)
        .collect();
    let mean = box_b.iter().sum::<f32>() / box_b.len() as f32;
    assert!((mean - 0.1).abs() < 0.01, "box B's mean height {mean}");
}

#[test]
fn no_support_plane_where_no_plane_holds_the_scene() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let scattered = Array2::from_shape_fn((H, W), |_| rng.random_range(0.5f32..3.0));
    assert!(support_plane(scattered.view()).is_none());
    assert!(height_above_plane(scattered.view()).is_none());
    let empty = Array2::from_elem((H, W), f32::NAN);
    assert!(support_plane(empty.view()).is_none());
    // without a plane a model's height part adds nothing: σ map and draws as without it
    let model = DepthErrorModel {
        height_sigma: 0.3,
        ..DepthErrorModel::uniform(0.004).unwrap()
    };
    let plain = DepthErrorModel {
        height_sigma: 0.0,
        ..model.clone()
    };
    let d = MetricDepth::new(scattered);
    assert_eq!(model.sigma_map(&d), plain.sigma_map(&d));
    assert_eq!(model.draw(&d, 5, 2).depth_m, plain.draw(&d, 5, 2).depth_m);
}

#[test]
fn the_height_part_of_the_sigma_map_and_of_the_draws() {
    let d = MetricDepth::new(scene(&[BOX_A, BOX_B], 1.0));
    let only = DepthErrorModel {
        height_sigma: 0.2,
        ..DepthErrorModel::default()
    };
    let s = only.sigma_map(&d);
    for ((v, u), &x) in s.indexed_iter() {
        let want = [BOX_A, BOX_B]
            .iter()
            .find(|b| inside(**b, u, v))
            .map_or(0.0, |b| 0.2 * b.4);
        assert!(
            (f64::from(x) - want).abs() < 1e-5,
            "({u}, {v}): σ {x} vs {want}"
        );
    }
    // each draw scales every height by one factor k ~ N(0, 0.2²); the table stays
    let (pa, pb, pt) = ((45, 55), (120, 80), (10, 110));
    let mut ks = Vec::new();
    for k in 0..400 {
        let drawn = only.draw(&d, 11, k).depth_m;
        let dev = |(u, v): (usize, usize)| f64::from(drawn[[v, u]] - d.depth_m[[v, u]]);
        assert_eq!(dev(pt), 0.0);
        let (ka, kb) = (-dev(pa) / BOX_A.4, -dev(pb) / BOX_B.4);
        assert!((ka - kb).abs() < 2e-4, "draw {k}: {ka} vs {kb}");
        ks.push(kb);
    }
    let n = ks.len() as f64;
    let mean = ks.iter().sum::<f64>() / n;
    let sd = (ks.iter().map(|k| (k - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    assert!(
        mean.abs() < 0.03 && (sd / 0.2 - 1.0).abs() < 0.12,
        "k: mean {mean}, sd {sd}"
    );
    // a region's draws (what a grasp's success probability draws): the heights of the whole
    // map's plane, one factor for the region
    let roi = moma_core::error_model::Roi {
        u0: 90,
        v0: 50,
        width: 60,
        height: 60,
    };
    let draws = moma_core::error_model::Draws::new(&only, d.depth_m.view(), roi);
    for k in 0..20 {
        let drawn = draws.draw(3, k);
        let dev = |(u, v): (usize, usize)| f64::from(drawn[[v - 50, u - 90]] - d.depth_m[[v, u]]);
        assert_eq!(dev((95, 55)), 0.0, "the table in the region");
        let (k1, k2) = (-dev((120, 80)) / BOX_B.4, -dev((101, 99)) / BOX_B.4);
        assert!((k1 - k2).abs() < 2e-4, "draw {k}: {k1} vs {k2}");
    }
    // drawn after every other part: the other parts' draws are those of the model without it
    let flat = DepthErrorModel::uniform(0.005).unwrap();
    let both = DepthErrorModel {
        height_sigma: 0.2,
        ..flat.clone()
    };
    for k in 0..5 {
        let (x, y) = (both.draw(&d, 7, k).depth_m, flat.draw(&d, 7, k).depth_m);
        assert_eq!(x[[pt.1, pt.0]], y[[pt.1, pt.0]]);
        assert_ne!(x[[pb.1, pb.0]], y[[pb.1, pb.0]]);
    }
}

/// A calibration of `method` in inverse space, 100 samples drawn with `seed`.
fn inverse_space(method: Method, norm: Normalisation, seed: u64) -> CalibrationConfig {
    common::calibration_config(method, norm, AlignSpace::Inverse, 100, seed)
}

/// A prediction that does not follow depth at all (a depth model's random weights): the
/// left-out fits' slopes are noise, their ratios unbounded; the calibration stands and states
/// heights it does not know as σ 1, never more.
#[test]
fn a_prediction_that_does_not_follow_depth_gets_the_capped_height_sigma() {
    let gt = MetricDepth::new(scene(&[BOX_A, BOX_B], 1.0));
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let noise = Prediction::new(
        Array2::from_shape_fn((H, W), |_| rng.random_range(0.5f32..1.5)),
        PredictionKind::RelativeDisparity,
    );
    for method in [Method::Gssa, Method::Ssra(Default::default())] {
        let config = inverse_space(method.clone(), Normalisation::Minmax, 0);
        let cal = calibrate(&[CalibrationFrame::new(&noise, &gt)], &config).unwrap();
        let m = cal.error_model.unwrap();
        // heights not known at all: the cap, not a small σ that would trust them
        assert_eq!(m.height_sigma, 1.0, "{method:?}");
        m.validate().unwrap();
    }
    assert_eq!(moma_core::height::height_sigma(f64::INFINITY, 0.1), 1.0);
    assert_eq!(moma_core::height::height_sigma(f64::NAN, 0.1), 1.0);
    assert_eq!(moma_core::height::height_sigma(0.3, 0.4), 0.5);
}

/// GSSA in inverse space, no normalisation, 100 samples: the relative slope of 1/z on the
/// prediction, fitted on the samples where `keep` holds (least squares written out here).
fn slope(samples: &[moma_core::align::Sample], keep: impl Fn(usize, usize) -> bool) -> f64 {
    let pts: Vec<(f64, f64)> = samples
        .iter()
        .filter(|s| keep(s.u as usize, s.v as usize))
        .map(|s| (s.pred, 1.0 / s.target))
        .collect();
    let n = pts.len() as f64;
    let (mx, my) = (
        pts.iter().map(|p| p.0).sum::<f64>() / n,
        pts.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    sxy / sxx
}

/// The calibration's height σ for boxes `boxes` that the prediction flattens to `flatten` of
/// their height, and the GSSA samples it was fitted on.
fn calibrated(
    boxes: &[(usize, usize, usize, usize, f64)],
    flatten: f64,
) -> (f64, Vec<moma_core::align::Sample>) {
    let gt = MetricDepth::new(scene(boxes, 1.0));
    // a relative disparity: 2/z − 0.3 of the flattened scene
    let pred = Prediction::new(
        scene(boxes, flatten).mapv(|z| 2.0 / z - 0.3),
        PredictionKind::RelativeDisparity,
    );
    let config = inverse_space(Method::Gssa, Normalisation::None, 4);
    let cal = calibrate(&[CalibrationFrame::new(&pred, &gt)], &config).unwrap();
    let model = cal.error_model.expect("an error model");
    (model.height_sigma, cal.samples.samples)
}

#[test]
fn an_object_that_pulls_the_calibration_widens_the_heights_sigma() {
    // one box flattened to half its height: GSSA's slope is pulled by its samples
    let (one, samples) = calibrated(&[BOX_B], 0.5);
    let on_box = samples
        .iter()
        .filter(|s| inside(BOX_B, s.u as usize, s.v as usize))
        .count();
    assert!(on_box >= 3, "{on_box} samples on the box");
    let pull = slope(&samples, |_, _| true) / slope(&samples, |u, v| !inside(BOX_B, u, v)) - 1.0;
    assert!(pull.abs() > 0.02, "pull {pull}");
    // the height σ is that pull (the table alone fits exactly: no noise to take off), and the
    // folds' jackknife of the slope on top
    assert!(
        one >= pull.abs() * (1.0 - 1e-6) && one <= 1.25 * pull.abs(),
        "height σ {one} vs pull {pull}"
    );
    // not flattened: every fit is exact, nothing pulls
    let (exact, _) = calibrated(&[BOX_B], 1.0);
    assert!(exact < 1e-6, "{exact}");
    // two boxes flattened alike: each one left out, the other still pulls the same way, so
    // what one object does to the scale carries to the next
    let (two, _) = calibrated(&[BOX_A, BOX_B], 0.5);
    assert!(two < 0.8 * one, "two boxes {two}, one {one}");
}

/// Few-shot: each frame's samples are grouped by that frame's own objects; two frames with a
/// flattened box each pull the fit, the same frames with their boxes kept do not.
#[test]
fn a_few_shot_calibration_has_its_frames_objects_pull() {
    let frames = |flatten: f64| {
        [BOX_B, BOX_A].map(|b| {
            let gt = MetricDepth::new(scene(&[b], 1.0));
            let pred = Prediction::new(
                scene(&[b], flatten).mapv(|z| 2.0 / z - 0.3),
                PredictionKind::RelativeDisparity,
            );
            (pred, gt)
        })
    };
    let config = inverse_space(Method::Gssa, Normalisation::None, 4);
    let sigma = |flatten: f64| {
        let f = frames(flatten);
        let inputs: Vec<CalibrationFrame<'_>> =
            f.iter().map(|(p, g)| CalibrationFrame::new(p, g)).collect();
        calibrate(&inputs, &config)
            .unwrap()
            .error_model
            .unwrap()
            .height_sigma
    };
    let (flattened, kept) = (sigma(0.5), sigma(1.0));
    // the folds' spread of the slope alone is 0.031 here; with the two objects' pulls 0.071
    assert!(flattened > 0.05 && flattened <= 1.0, "{flattened}");
    assert!(kept < 1e-6, "{kept}");
}
