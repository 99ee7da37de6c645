//! The error model's distance part (`DepthErrorModel::sample_distance_gain`, fit step 5): the
//! flat σ `√(σ0² + (gain·d)²)` at a distance d from the nearest calibration sample, fitted where
//! the samples reach only part of the image. Against closed forms (a rest that is that σ
//! exactly), the draws' spread, and a calibration whose left-half samples extrapolate a
//! distortion they do not see.

mod common;

use std::sync::Arc;

use moma_core::align::Method;
use moma_core::error_model::{Draws, HeldOutResidual, ResidualFrame, Roi};
use moma_core::normalise::{AlignSpace, Normalisation};
use moma_core::pipeline::{AlignOptions, CalibrationConfig, CalibrationFrame, calibrate};
use moma_core::sampling::sample_distance_map;
use moma_core::{DepthErrorModel, ImageSize, Mask, MetricDepth, Prediction, PredictionKind};
use ndarray::Array2;

const H: usize = 120;
const W: usize = 320;
/// The flat σ at the samples, metres, and its growth, metres per pixel.
const S0: f64 = 0.004;
const GAIN: f64 = 3e-5;

/// Samples every 10 px in the image's first 60 columns.
fn left_samples() -> Vec<(f64, f64)> {
    (0..60)
        .step_by(10)
        .flat_map(|u| (0..H).step_by(10).map(move |v| (u as f64, v as f64)))
        .collect()
}

fn sigma_at(d: f32) -> f64 {
    S0.hypot(GAIN * f64::from(d))
}

/// An aligned depth whose rest against a flat truth is `√(S0² + (GAIN·d)²)` at every pixel:
/// the fit's least squares of the rest's square on 1 and d² gives S0 and GAIN back.
#[test]
fn the_fit_gives_back_a_flat_error_that_grows_with_the_distance_to_the_samples() {
    let d = sample_distance_map(H, W, &left_samples());
    let truth = Array2::from_elem((H, W), 1.0f32);
    let aligned = d.mapv(|x| 1.0 + sigma_at(x) as f32);
    let frame = ResidualFrame {
        aligned_m: aligned.view(),
        truth_m: truth.view(),
    };
    let m = DepthErrorModel::fit_with_sample_distance(&[frame], &[], 0.0, Some(d.view())).unwrap();
    assert!(
        (m.sample_distance_gain / GAIN - 1.0).abs() < 0.05,
        "gain {} against {GAIN}",
        m.sample_distance_gain
    );
    assert!(
        (m.sigma_flat_m / S0 - 1.0).abs() < 0.05,
        "σ0 {} against {S0}",
        m.sigma_flat_m
    );
    assert_eq!(m.sample_distance_px.as_deref(), Some(&d));
    // without the map there is no such part: σ is the whole frame's level
    let plain = DepthErrorModel::fit(&[frame], &[], 0.0).unwrap();
    assert_eq!(plain.sample_distance_gain, 0.0);
    assert!(plain.sample_distance_px.is_none());
    assert!(plain.sigma_flat_m > 1.2 * S0, "{}", plain.sigma_flat_m);
    // the dense σ stays the whole frame's (what a re-aligned frame's background is held to),
    // with or without the part
    assert_eq!(m.sigma_dense_m, plain.sigma_dense_m);
    assert!(m.sigma_dense_m.unwrap() > 1.2 * S0, "{:?}", m.sigma_dense_m);
    // the fit's optimism applies to the level at the samples: 6 mm held out of a fit exact at
    // them (depth space, at 1 m; its held-out level bounds it) lift σ0 to 6 mm and leave the
    // gain as it was
    let cv =
        [(0.006, 1.0), (-0.006, 1.0), (0.006, 0.9), (-0.006, 1.1)].map(|(r, z)| HeldOutResidual {
            held_out_m: r,
            in_sample_m: 0.0,
            depth_m: z,
        });
    let lifted =
        DepthErrorModel::fit_with_sample_distance(&[frame], &cv, 0.0, Some(d.view())).unwrap();
    assert!(m.sigma_flat_m < 0.006, "{}", m.sigma_flat_m);
    assert!(
        (lifted.sigma_flat_m - 0.006).abs() < 1e-9,
        "{}",
        lifted.sigma_flat_m
    );
    assert_eq!(lifted.sample_distance_gain, m.sample_distance_gain);

    // a rest that does not grow: no part worth a thousandth of σ0 at the farthest pixel
    let level = Array2::from_elem((H, W), 1.0 + S0 as f32);
    let frame = ResidualFrame {
        aligned_m: level.view(),
        truth_m: truth.view(),
    };
    let m = DepthErrorModel::fit_with_sample_distance(&[frame], &[], 0.0, Some(d.view())).unwrap();
    let far = d.iter().fold(0.0f32, |a, &b| a.max(b));
    assert!(
        m.sample_distance_gain * f64::from(far) < 1e-3 * S0,
        "{}",
        m.sample_distance_gain
    );
    assert!(
        (m.sigma_flat_m / S0 - 1.0).abs() < 1e-3,
        "{}",
        m.sigma_flat_m
    );

    // a map without a finite distance (no sample): no part, the fit without a map
    let none = sample_distance_map(H, W, &[]);
    let growing = ResidualFrame {
        aligned_m: aligned.view(),
        truth_m: truth.view(),
    };
    let m =
        DepthErrorModel::fit_with_sample_distance(&[growing], &[], 0.0, Some(none.view())).unwrap();
    assert_eq!(m, plain);

    // a map of another size than any frame is an error naming both
    let small = Array2::<f32>::zeros((H, W / 2));
    let e = DepthErrorModel::fit_with_sample_distance(&[frame], &[], 0.0, Some(small.view()))
        .unwrap_err()
        .to_string();
    assert!(e.contains("160") && e.contains("320"), "{e}");
    let (t2, a2) = (
        Array2::from_elem((H, W / 2), 1.0f32),
        small.mapv(|_| 1.01f32),
    );
    let other = ResidualFrame {
        aligned_m: a2.view(),
        truth_m: t2.view(),
    };
    let e = DepthErrorModel::fit_with_sample_distance(&[frame, other], &[], 0.0, Some(d.view()))
        .unwrap_err()
        .to_string();
    assert!(e.contains("frame 1") && e.contains("160"), "{e}");
}

/// A uniform model with the part: its σ map is `√(σ0² + (gain·d)²)` at every pixel, and its
/// draws spread by that much (400 draws: within 12 % at the samples and 260 px from them).
/// Without the map, or with one of another size, the part is left out.
#[test]
fn the_sigma_map_and_the_draws_grow_with_the_distance() {
    let uv = left_samples();
    let d = sample_distance_map(H, W, &uv);
    let mut m = DepthErrorModel::uniform(S0).unwrap();
    m.sample_distance_gain = GAIN;
    m.validate().unwrap();
    let flat = MetricDepth::new(Array2::from_elem((H, W), 1.0f32));
    // without a map: the level alone
    assert!(
        m.sigma_map(&flat)
            .iter()
            .all(|&s| (f64::from(s) - S0).abs() < 1e-9)
    );
    m.sample_distance_px = Some(Arc::new(d.clone()));
    let sigma = m.sigma_map(&flat);
    for ((v, u), &s) in sigma.indexed_iter() {
        let want = sigma_at(d[[v, u]]);
        assert!(
            (f64::from(s) / want - 1.0).abs() < 1e-5,
            "({u}, {v}): {s} against {want}"
        );
    }
    let (near, far) = ((60, 0), (60, W - 1));
    assert_eq!(d[near], 0.0);
    assert!(d[far] > 255.0, "{}", d[far]);
    let draws: Vec<Array2<f32>> = (0..400).map(|k| m.draw(&flat, 3, k).depth_m).collect();
    for px in [near, far] {
        let x: Vec<f64> = draws.iter().map(|a| f64::from(a[px]) - 1.0).collect();
        let sd = (x.iter().map(|e| e * e).sum::<f64>() / x.len() as f64).sqrt();
        let want = sigma_at(d[px]);
        assert!(
            (sd / want - 1.0).abs() < 0.12,
            "{px:?}: {sd} against {want}"
        );
    }
    // a level of 0 at the samples (a fit that passes through them): the draws still carry
    // the part, `gain · d`, and leave the samples' pixels as they are
    let mut through = m.clone();
    through.sigma_flat_m = 0.0;
    let draws: Vec<Array2<f32>> = (0..400)
        .map(|k| through.draw(&flat, 3, k).depth_m)
        .collect();
    assert!(draws.iter().all(|a| a[near] == 1.0));
    let x: Vec<f64> = draws.iter().map(|a| f64::from(a[far]) - 1.0).collect();
    let sd = (x.iter().map(|e| e * e).sum::<f64>() / x.len() as f64).sqrt();
    let want = GAIN * f64::from(d[far]);
    assert!((sd / want - 1.0).abs() < 0.12, "{sd} against {want}");
    assert!((f64::from(through.sigma_map(&flat)[far]) / want - 1.0).abs() < 1e-5);

    // a map of another size (not this image's): left out, as without one
    m.sample_distance_px = Some(Arc::new(Array2::zeros((H / 2, W))));
    assert!(
        m.sigma_map(&flat)
            .iter()
            .all(|&s| (f64::from(s) - S0).abs() < 1e-9)
    );
    m.sample_distance_gain = -1e-5;
    assert!(m.validate().is_err());
}

/// GSSA in depth space, 100 samples of `seed`.
fn config(seed: u64) -> CalibrationConfig {
    common::calibration_config(
        Method::Gssa,
        Normalisation::None,
        AlignSpace::Depth,
        100,
        seed,
    )
}

/// The share of the pixels in columns `cols` whose true error is within ±1σ.
fn within_one_sigma(
    truth: &Array2<f32>,
    aligned: &Array2<f32>,
    sigma: &Array2<f32>,
    cols: std::ops::Range<usize>,
) -> f64 {
    let (mut n, mut k) = (0usize, 0usize);
    for ((v, u), &t) in truth.indexed_iter() {
        if cols.contains(&u) {
            n += 1;
            k += usize::from((t - aligned[[v, u]]).abs() <= sigma[[v, u]]);
        }
    }
    k as f64 / n as f64
}

/// A prediction bent by `0.06·(u/W)²` m plus a ripple of 3 mm, calibrated by GSSA on samples in
/// the left half: the fit extrapolates the bend, up to 4 cm wrong at the right border. The
/// calibration finds its samples partial, fits the part, and its σ then holds the right
/// quarter's errors (without the part the same model's σ holds under a quarter of them). The
/// calibration read back from its JSON rebuilds the same σ. Samples spread over the image get
/// no part at all.
#[test]
fn a_calibration_whose_samples_reach_half_the_image_widens_sigma_beyond_them() {
    let truth = Array2::from_shape_fn((H, W), |(v, u)| 0.8 + 0.001 * v as f32 + 0.0002 * u as f32);
    let bent = Array2::from_shape_fn((H, W), |(v, u)| {
        let x = u as f32 / W as f32;
        truth[[v, u]] + 0.06 * x * x + 0.003 * ((u as f32 / 7.0).sin() * (v as f32 / 5.0).cos())
    });
    let gt = MetricDepth::new(truth.clone());
    let pred = Prediction::new(bent.clone(), PredictionKind::RelativeDepth);
    let left = Mask::from_vec(
        ImageSize::new(W, H),
        (0..H * W).map(|i| i % W < W / 2).collect(),
    )
    .unwrap();
    let frame = CalibrationFrame::new(&pred, &gt).sampled_in(Some(&left));
    let cal = calibrate(&[frame], &config(1)).unwrap();
    let stored = cal.error_model.clone().expect("an error model");
    assert!(stored.sample_distance_gain > 0.0, "{stored:?}");
    // the calibration holds what its file holds: the gain, not the map
    assert!(stored.sample_distance_px.is_none());
    let aligned = cal.aligned(&pred, &AlignOptions::default()).unwrap();
    let model = aligned.error_model.clone().unwrap();
    assert!(model.sample_distance_px.is_some());
    let sigma = model.sigma_map(&aligned.depth);
    let right = 3 * W / 4..W;
    let with_part = within_one_sigma(&truth, &aligned.depth.depth_m, &sigma, right.clone());
    let without = DepthErrorModel {
        sample_distance_gain: 0.0,
        ..model.clone()
    }
    .sigma_map(&aligned.depth);
    let without = within_one_sigma(&truth, &aligned.depth.depth_m, &without, right);
    // in the target's band (55–80 %, docs/grasping.md): wider than the errors, not a σ so
    // large that it holds everything
    assert!(
        (0.55..=0.9).contains(&with_part),
        "{with_part} of the right quarter within ±1σ"
    );
    assert!(without < 0.25, "{without} without the part");

    // the file keeps the gain, not the map; read back, the calibration rebuilds it
    let json = serde_json::to_string(&cal).unwrap();
    assert!(json.contains("sample_distance_gain"));
    let back: moma_core::pipeline::Calibration = serde_json::from_str(&json).unwrap();
    assert_eq!(back, cal);
    let again = back.aligned(&pred, &AlignOptions::default()).unwrap();
    assert_eq!(again.error_model.unwrap().sigma_map(&again.depth), sigma);

    // spread samples: the same scene gets no distance part
    let spread = calibrate(&[CalibrationFrame::new(&pred, &gt)], &config(1)).unwrap();
    let m = spread.error_model.unwrap();
    assert_eq!(m.sample_distance_gain, 0.0);
    assert!(m.sample_distance_px.is_none());
}

/// Draws of a region (the path robust grasp quality takes) read the distance map at the region's
/// own pixels, and the depth law scales the part. With the offset alone every pixel of a draw
/// deviates by one normal number times `σ(d)·(z/z_ref)²`, so a region's draw equals the whole
/// map's draw at its pixels, and two pixels' deviations are in the ratio of their σ exactly.
/// `long_range` keeps the part in proportion to the variance it keeps.
#[test]
fn region_draws_read_the_distance_at_their_own_pixels_and_follow_the_depth_law() {
    let d = sample_distance_map(H, W, &left_samples());
    let mut m = DepthErrorModel::uniform(S0).unwrap();
    m.variance_shares = [1.0, 0.0, 0.0, 0.0];
    m.sample_distance_gain = GAIN;
    m.depth_ref_m = 1.0;
    m.depth_exponent = 2.0;
    m.sample_distance_px = Some(Arc::new(d.clone()));
    m.validate().unwrap();
    // 1 m on the left half, 2 m on the right: σ four times the level there
    let depth = Array2::from_shape_fn((H, W), |(_, u)| if u < W / 2 { 1.0f32 } else { 2.0 });
    let sigma_of = |v: usize, u: usize| sigma_at(d[[v, u]]) * f64::from(depth[[v, u]]).powi(2);
    let roi = Roi {
        u0: 140,
        v0: 30,
        width: 120,
        height: 60,
    };
    let region = Draws::new(&m, depth.view(), roi);
    let whole = MetricDepth::new(depth.clone());
    for k in 0..3 {
        let a = region.draw(11, k);
        let all = m.draw(&whole, 11, k).depth_m;
        // the normal number of this draw, from the region's first pixel
        let (v0, u0) = (roi.v0, roi.u0);
        let x = f64::from(a[[0, 0]] - depth[[v0, u0]]) / sigma_of(v0, u0);
        assert!(x.abs() > 1e-3, "draw {k}: {x}");
        for ((v, u), &z) in a.indexed_iter() {
            let (vv, uu) = (v + v0, u + u0);
            assert_eq!(z, all[[vv, uu]], "draw {k} at ({uu}, {vv})");
            let want = x * sigma_of(vv, uu);
            let got = f64::from(z - depth[[vv, uu]]);
            assert!(
                (got - want).abs() <= 1e-4 * want.abs().max(1e-4),
                "draw {k} at ({uu}, {vv}): {got} against {want}"
            );
        }
    }
    // long_range keeps √(offset + coarse) of the flat σ, at every distance
    let mut mixed = m.clone();
    mixed.variance_shares = [0.25, 0.5, 0.0, 0.25];
    let long = mixed.long_range();
    for dist in [0.0, 50.0, 270.0] {
        let want = 0.5f64.sqrt() * sigma_at(dist as f32);
        let got = long.flat_sigma_at_distance_m(dist);
        assert!(
            (got / want - 1.0).abs() < 1e-12,
            "{dist} px: {got} against {want}"
        );
    }
}
