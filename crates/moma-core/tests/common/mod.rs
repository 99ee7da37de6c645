//! Shared synthetic data for the integration tests (seeded, independent of the code under test).
#![allow(dead_code)]

use moma_core::ImageSize;
use moma_core::align::{Sample, SampleSet};
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// `n` samples at random integer pixels of `size` with ẑ ~ U(0.3, 1.5) and depth `f(u, v, ẑ)`
/// plus Gaussian-ish noise of standard deviation `noise_m` (sum of uniforms).
pub fn samples(
    size: ImageSize,
    n: usize,
    seed: u64,
    noise_m: f64,
    f: impl Fn(f64, f64, f64) -> f64,
) -> SampleSet {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let samples = (0..n)
        .map(|_| {
            let u = rng.random_range(0..size.width) as f64;
            let v = rng.random_range(0..size.height) as f64;
            let pred = rng.random_range(0.3..1.5);
            // Irwin–Hall(12) − 6 has unit variance
            let e: f64 = (0..12).map(|_| rng.random::<f64>()).sum::<f64>() - 6.0;
            Sample {
                u,
                v,
                pred,
                target: f(u, v, pred) + noise_m * e,
            }
        })
        .collect();
    SampleSet {
        space: moma_core::normalise::AlignSpace::Depth,
        image_size: size,
        samples,
    }
}

/// A synthetic tabletop seen by a 640×480-like camera scaled to `size`: a tilted table plane at
/// ~0.8–1.2 m with three objects (box, cylinder, sphere) standing on it. Metres.
pub fn tabletop_gt(size: ImageSize) -> Array2<f32> {
    let (w, h) = (size.width as f64, size.height as f64);
    Array2::from_shape_fn(size.shape(), |(v, u)| {
        let (x, y) = (u as f64 / w, v as f64 / h);
        let table = 1.2 - 0.4 * y + 0.03 * x;
        let mut z = table;
        // box
        if (0.15..0.35).contains(&x) && (0.4..0.65).contains(&y) {
            z = table - 0.08;
        }
        // cylinder (disc from above)
        let d2 = (x - 0.6).powi(2) + ((y - 0.55) * h / w).powi(2);
        if d2 < 0.07f64.powi(2) {
            z = table - 0.12;
        }
        // sphere
        let r = 0.06;
        let d2 = (x - 0.8).powi(2) + ((y - 0.3) * h / w).powi(2);
        if d2 < r * r {
            z = z.min(table - 0.05 - (r * r - d2).sqrt());
        }
        z as f32
    })
}

/// A prediction-like map from a ground truth: a planar scale field, smooth bumps (2 %) and a
/// global affine change; unitless.
pub fn distorted_prediction(gt: &Array2<f32>) -> Array2<f32> {
    let (h, w) = gt.dim();
    Array2::from_shape_fn((h, w), |(v, u)| {
        let (x, y) = (u as f64 / w as f64, v as f64 / h as f64);
        let plane = 1.0 + 0.08 * (x - 0.5) - 0.05 * (y - 0.5);
        let bumps = 1.0 + 0.02 * (-((x - 0.3).powi(2) + (y - 0.7).powi(2)) / 0.05).exp()
            - 0.015 * (-((x - 0.75).powi(2) + (y - 0.25).powi(2)) / 0.03).exp();
        let z = gt[[v, u]] as f64;
        (1.7 * z * plane * bumps - 0.4) as f32
    })
}

/// A calibration of `method` with normalisation `norm` in `space`, `n` random samples drawn
/// with `seed`, no robust fit and no workspace: the configuration most tests calibrate with.
pub fn calibration_config(
    method: moma_core::align::Method,
    norm: moma_core::Normalisation,
    space: moma_core::AlignSpace,
    n: usize,
    seed: u64,
) -> moma_core::CalibrationConfig {
    moma_core::CalibrationConfig {
        method,
        normalisation: moma_core::NormalisationConfig {
            method: norm,
            space,
        },
        sampling: moma_core::sampling::SamplingConfig {
            n,
            seed,
            ..Default::default()
        },
        robust: None,
        workspace: None,
    }
}
