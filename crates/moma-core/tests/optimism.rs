//! The error model's flat σ and the fit's optimism at its calibration samples
//! (`moma_core::error_model`, "Where the numbers come from"): the pipeline keeps each sample's
//! residual out of a cross-validation fold and in the calibration's own fit, and the flat σ
//! grows by their ratio (at most to the held-out level).

mod common;

use moma_core::align::Method;
use moma_core::normalise::{AlignSpace, Normalisation};
use moma_core::pipeline::{CalibrationFrame, calibrate};
use moma_core::{MetricDepth, Prediction, PredictionKind};
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A slanted table 0.8–1.2 m away and a "depth model" exact but for independent noise of ±5.2 mm (uniform,
/// σ 3 mm, seeded) at every pixel, calibrated by GSSA (2 parameters) on 6 samples: least
/// squares fits its own samples better than the others (each held-out residual is its
/// in-sample one over 1 − leverage, large with 6 samples), so the samples' residuals out of
/// the folds exceed those in the fit and the frame's dense level, and the flat σ stands above
/// that level, by at most the held-out one. Were the in-sample residuals taken from the folds'
/// refits (a ratio of 1), the two would be equal.
#[test]
fn the_flat_sigma_stands_above_the_dense_level_by_the_fits_optimism() {
    let (h, w) = (120usize, 160usize);
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    // a table seen at a slant: 0.8 m at the top row, 1.2 m at the bottom
    let truth = Array2::from_shape_fn((h, w), |(v, _)| 0.8 + 0.4 * v as f32 / (h - 1) as f32);
    let noisy = truth.mapv(|z| z + rng.random_range(-0.0052f32..0.0052));
    let gt = MetricDepth::new(truth);
    let pred = Prediction::new(noisy, PredictionKind::MetricDepth);
    let config =
        common::calibration_config(Method::Gssa, Normalisation::None, AlignSpace::Depth, 6, 3);
    let cal = calibrate(&[CalibrationFrame::new(&pred, &gt)], &config).unwrap();
    let m = cal.error_model.expect("an error model");
    let dense = m.sigma_dense_m.expect("the dense level");
    assert!((dense - 0.003).abs() < 0.0003, "dense σ {dense}");
    assert!(
        m.sigma_flat_m > 1.02 * dense && m.sigma_flat_m < 1.5 * dense,
        "flat σ {} against the dense {dense}",
        m.sigma_flat_m
    );
}
