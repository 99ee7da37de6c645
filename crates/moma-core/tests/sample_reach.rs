//! `sample_reach` and `sample_distance_map`: how far calibration samples reach over an image,
//! against closed forms and brute force.

use moma_core::MetricDepth;
use moma_core::align::SampleSet;
use moma_core::sampling::{
    PARTIAL_REACH_RATIO, sample_distance_map, sample_reach, sample_reach_over,
};
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// One sample at the centre of a disc of radius R: the share of the disc within r is r²/R², so
/// the 90th percentile is R·√0.9; as many samples spread uniformly (one, over πR²) reach 90 %
/// within R·√(ln 10).
#[test]
fn one_sample_at_a_discs_centre_reaches_its_closed_form() {
    let r = 150.0;
    let valid = Array2::from_shape_fn((400, 400), |(v, u)| {
        (u as f64 - 200.0).hypot(v as f64 - 200.0) <= r
    });
    let reach = sample_reach(&[(200.0, 200.0)], &valid).unwrap();
    assert!((reach.p90_px - r * 0.9f64.sqrt()).abs() < 2.0, "{reach:?}");
    let uniform = r * std::f64::consts::LN_10.sqrt();
    assert!(
        (reach.uniform_p90_px / uniform - 1.0).abs() < 0.005,
        "{reach:?}"
    );
    assert_eq!(reach.samples, 1);
    assert!(!reach.is_partial());
}

fn samples(n: usize, u_max: f64, seed: u64) -> Vec<(f64, f64)> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            (
                rng.random_range(0.0..u_max).floor(),
                rng.random_range(0.0..480.0f64).floor(),
            )
        })
        .collect()
}

/// Samples spread over the image reach as a uniform spread does; the same number drawn in its
/// left half leave the right half beyond reach.
#[test]
fn samples_in_half_the_image_are_partial_and_spread_ones_are_not() {
    let valid = Array2::from_elem((480, 640), true);
    for seed in 0..3 {
        let spread = sample_reach(&samples(100, 640.0, seed), &valid).unwrap();
        let ratio = spread.p90_px / spread.uniform_p90_px;
        assert!((0.8..1.3).contains(&ratio), "seed {seed}: {spread:?}");
        assert!(!spread.is_partial());

        let half = sample_reach(&samples(100, 320.0, seed), &valid).unwrap();
        // the right half's pixels are up to 320 px from the samples' edge, the 90th percentile
        // of all pixels about 0.8 of that
        assert!(half.p90_px > 200.0, "seed {seed}: {half:?}");
        assert!(
            half.p90_px > 2.0 * PARTIAL_REACH_RATIO * half.uniform_p90_px,
            "seed {seed}: {half:?}"
        );
        assert!(half.is_partial());
        assert_eq!(spread.warning("--mask", None), None);
        let w = half.warning("--mask", None).unwrap();
        assert!(
            w.contains("100 calibration samples") && w.contains("(--mask)"),
            "{w}"
        );
        assert!(!w.contains("grows"), "{w}");
        // with a model's distance part: σ at the samples and p90 away, in millimetres
        let mut model = moma_core::DepthErrorModel::uniform(0.004).unwrap();
        model.sample_distance_gain = 3e-5;
        let w = half.warning("--mask", Some(&model)).unwrap();
        let far = 1e3 * 0.004f64.hypot(3e-5 * half.p90_px);
        assert!(
            w.contains("grows from 4.0 mm at the samples")
                && w.contains(&format!("to {far:.1} mm {:.0} px away", half.p90_px)),
            "{w}"
        );
    }
}

#[test]
fn no_sample_or_no_valid_pixel_has_no_reach_and_an_off_grid_pixel_is_measured() {
    let valid = Array2::from_elem((48, 64), true);
    assert_eq!(sample_reach(&[], &valid), None);
    assert_eq!(
        sample_reach(&[(1.0, 1.0)], &Array2::from_elem((48, 64), false)),
        None
    );
    // the only pixel with depth lies between the 8-pixel grid's nodes: 3-4-5 from the sample
    let mut one = Array2::from_elem((48, 64), false);
    one[[3, 3]] = true;
    let reach = sample_reach(&[(6.0, 7.0)], &one).unwrap();
    assert_eq!(reach.p90_px, 5.0);
}

/// A calibration's reach counts the pixels where any of its frames has depth: two frames with
/// depth in one half each measure as one frame with depth everywhere.
#[test]
fn a_calibrations_reach_is_over_the_union_of_its_frames_depth() {
    let half = |left: bool| {
        MetricDepth::new(Array2::from_shape_fn((48, 64), |(_, u)| {
            if (u < 32) == left { 1.0 } else { f32::NAN }
        }))
    };
    let (left, right, full) = (
        half(true),
        half(false),
        MetricDepth::new(Array2::ones((48, 64))),
    );
    let samples: SampleSet = serde_json::from_value(serde_json::json!({
        "image_size": {"width": 64, "height": 48},
        "samples": [
            {"u": 10.0, "v": 10.0, "pred": 0.5, "depth_m": 1.0},
            {"u": 50.0, "v": 30.0, "pred": 0.5, "depth_m": 1.0},
        ],
    }))
    .unwrap();
    let both = sample_reach_over(&samples, &[&left, &right]).unwrap();
    assert_eq!(Some(both), sample_reach_over(&samples, &[&full]));
    let one = sample_reach_over(&samples, &[&left]).unwrap();
    assert!((one.uniform_p90_px / both.uniform_p90_px - 0.5f64.sqrt()).abs() < 1e-12);
    assert_eq!(sample_reach_over(&samples, &[]), None);
}

/// The distance transform against the brute-force distance to every sample: random samples
/// over images of several shapes (one row and one column included), samples on the border and
/// repeated; exact to f32 rounding.
#[test]
fn the_distance_map_is_the_exact_distance_to_the_nearest_sample() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for (h, w, n) in [
        (48, 64, 5),
        (37, 91, 40),
        (1, 50, 3),
        (50, 1, 3),
        (64, 48, 1),
    ] {
        for _ in 0..3 {
            let mut uv: Vec<(f64, f64)> = (0..n)
                .map(|_| (rng.random_range(0..w) as f64, rng.random_range(0..h) as f64))
                .collect();
            uv.push(uv[0]);
            uv.push((0.0, (h - 1) as f64));
            let map = sample_distance_map(h, w, &uv);
            assert_eq!(map.dim(), (h, w));
            for ((v, u), &d) in map.indexed_iter() {
                let brute = uv
                    .iter()
                    .map(|&(su, sv)| (u as f64 - su).hypot(v as f64 - sv))
                    .fold(f64::INFINITY, f64::min);
                assert!(
                    (f64::from(d) - brute).abs() <= 1e-4 * brute.max(1.0),
                    "{h}×{w}, pixel ({u}, {v}): {d} against {brute}"
                );
            }
        }
    }
}

/// Samples off the pixel grid count at their pixel, those outside the image at its border,
/// non-finite ones not at all; without a sample every distance is infinite.
#[test]
fn the_distance_map_rounds_clamps_and_skips_samples() {
    let map = sample_distance_map(10, 20, &[(3.4, 2.6)]);
    assert_eq!(map[[3, 3]], 0.0);
    assert_eq!(map[[3, 7]], 4.0);
    let outside = sample_distance_map(10, 20, &[(-50.0, 100.0), (f64::NAN, 1.0)]);
    assert_eq!(outside[[9, 0]], 0.0);
    assert_eq!(outside[[0, 0]], 9.0);
    assert!(
        sample_distance_map(10, 20, &[])
            .iter()
            .all(|d| d.is_infinite())
    );
    assert!(
        sample_distance_map(10, 20, &[(f64::NAN, 0.0)])
            .iter()
            .all(|d| d.is_infinite())
    );
    assert_eq!(sample_distance_map(0, 20, &[(1.0, 1.0)]).dim(), (0, 20));
}

/// The threshold itself: partial above twice the uniform spread's reach, not at or below it.
#[test]
fn the_partial_reach_threshold_is_twice_the_uniform_reach() {
    assert_eq!(PARTIAL_REACH_RATIO, 2.0);
    let reach = |p90_px: f64| moma_core::sampling::SampleReach {
        p90_px,
        uniform_p90_px: 12.0,
        samples: 100,
    };
    assert!(!reach(23.9).is_partial());
    assert!(!reach(24.0).is_partial());
    assert!(reach(24.1).is_partial());
    assert_eq!(reach(23.9).warning("--mask", None), None);
    assert!(reach(24.1).warning("--mask", None).is_some());
}

/// A sparse ground truth (150 measured points scattered over the image, or every 4th row of a
/// LiDAR) covers the image although few pixels have depth: samples among those points reach it
/// as a uniform spread over the image would, not "part of the image". Samples confined to the
/// left half of the same points still do not.
#[test]
fn samples_among_a_sparse_ground_truth_reach_the_image_it_covers() {
    let (h, w) = (480, 640);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let mut points = Array2::from_elem((h, w), false);
    let mut all = Vec::new();
    while all.len() < 150 {
        let (u, v) = (rng.random_range(0..w), rng.random_range(0..h));
        if !points[[v, u]] {
            points[[v, u]] = true;
            all.push((u as f64, v as f64));
        }
    }
    let spread = sample_reach(&all[..100], &points).unwrap();
    assert!(!spread.is_partial(), "{spread:?}");
    // the reference is about the image's: as many samples over 640 × 480 (the points' box)
    let image = (std::f64::consts::LN_10 / std::f64::consts::PI * (h * w) as f64 / 100.0).sqrt();
    assert!(
        (spread.uniform_p90_px / image - 1.0).abs() < 0.05,
        "{spread:?} vs {image}"
    );
    assert!(spread.p90_px > 0.5 * image, "{spread:?}");
    let left: Vec<(f64, f64)> = all.iter().copied().filter(|p| p.0 < 320.0).collect();
    assert!(sample_reach(&left, &points).unwrap().is_partial());

    let rows = Array2::from_shape_fn((h, w), |(v, _)| v % 4 == 0);
    let on_rows = samples(100, 640.0, 2)
        .into_iter()
        .map(|(u, v)| (u, (v / 4.0).floor() * 4.0))
        .collect::<Vec<_>>();
    assert!(!sample_reach(&on_rows, &rows).unwrap().is_partial());
}
