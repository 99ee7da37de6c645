//! Shared helpers of the integration tests: a small synthetic set.
#![allow(dead_code)]

use moma_core::{Intrinsics, Mask, MetricDepth, Prediction, PredictionKind};
use moma_eval::data::{LoadedFrame, LoadedSet};
use moma_eval::protocol::PredictionSet;
use ndarray::Array2;

pub const W: usize = 48;
pub const H: usize = 36;

pub fn intrinsics() -> Intrinsics {
    Intrinsics {
        width: W,
        height: H,
        fx: 50.0,
        fy: 50.0,
        cx: 23.5,
        cy: 17.5,
    }
}

/// Ground truth of frame `k`: a tilted plane with a box-shaped bump, a hole in the corner.
pub fn gt(k: usize) -> MetricDepth {
    MetricDepth::new(Array2::from_shape_fn((H, W), |(v, u)| {
        if u < 3 && v < 3 {
            return 0.0;
        }
        let plane = 0.7 + 0.002 * u as f32 - 0.001 * v as f32;
        let (cu, cv) = (10 + 8 * k, 12 + 3 * k);
        if u.abs_diff(cu) < 5 && v.abs_diff(cv) < 4 {
            plane - 0.05 - 0.003 * k as f32
        } else {
            plane
        }
    }))
}

pub fn mask(k: usize) -> Mask {
    let (cu, cv) = (10 + 8 * k, 12 + 3 * k);
    Mask::new(Array2::from_shape_fn((H, W), |(v, u)| {
        u.abs_diff(cu) < 7 && v.abs_diff(cv) < 6
    }))
}

/// A depth prediction: a smooth, non-affine distortion of the ground truth (no holes).
pub fn pred(k: usize) -> Prediction {
    let g = gt(k);
    let v = Array2::from_shape_fn((H, W), |(v, u)| {
        let z = g.depth_m[[v, u]];
        let z = if z > 0.0 { z } else { 0.7 };
        1.3 * z * (1.0 + 0.03 * ((u as f32) / 10.0).sin())
            + 0.02 * (v as f32 / 36.0)
            + 0.01 * k as f32
    });
    Prediction::new(v, PredictionKind::MetricDepth)
}

pub fn set(frames: usize) -> LoadedSet {
    LoadedSet {
        name: "synthetic".into(),
        dir: "synthetic".into(),
        intrinsics: intrinsics(),
        frames: (0..frames)
            .map(|k| LoadedFrame {
                id: format!("f{k}"),
                rgb: None,
                gt: gt(k),
                mask: Some(mask(k)),
                raw_depth: None,
            })
            .collect(),
    }
}

pub fn preds(frames: usize) -> PredictionSet {
    PredictionSet {
        label: "synthetic".into(),
        simulated: false,
        maps: (0..frames).map(pred).collect(),
    }
}

/// Independent, straightforward docs/method.md §3 metrics: [d105, d110, d125, rel, rmse, mae].
pub fn reference_metrics(p: &Array2<f32>, g: &Array2<f32>, m: &Array2<bool>) -> [f64; 6] {
    let mut n = 0.0;
    let mut acc = [0.0f64; 6];
    for ((&pp, &gg), &inside) in p.iter().zip(g.iter()).zip(m.iter()) {
        if !(inside && gg.is_finite() && gg > 0.0 && pp.is_finite()) {
            continue;
        }
        let (pp, gg) = (pp as f64, gg as f64);
        let ratio = (pp / gg).max(gg / pp);
        n += 1.0;
        acc[0] += (ratio < 1.05) as u8 as f64;
        acc[1] += (ratio < 1.10) as u8 as f64;
        acc[2] += (ratio < 1.25) as u8 as f64;
        acc[3] += (pp - gg).abs() / gg;
        acc[4] += (pp - gg).powi(2);
        acc[5] += (pp - gg).abs();
    }
    [
        acc[0] / n,
        acc[1] / n,
        acc[2] / n,
        acc[3] / n,
        (acc[4] / n).sqrt(),
        acc[5] / n,
    ]
}

/// A set of the shared data (`$MOMA_SHARED_DIR/data/<name>`, default `../shared` beside the
/// repository); panics naming the path when it is absent (the tests calling it are `#[ignore]`d).
pub fn shared_set(name: &str) -> LoadedSet {
    let base = std::env::var_os("MOMA_SHARED_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| {
            std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared")
        });
    let dir = base.join("data").join(name);
    assert!(
        dir.is_dir(),
        "this test needs the shared data, not found at {} (set MOMA_SHARED_DIR)",
        dir.display()
    );
    LoadedSet::open(&dir).expect("the shared set loads")
}

/// SIMULATED inverse-depth predictions of `set` (default simulator, seed `sim_seed`).
pub fn simulated_inverse_depth(set: &LoadedSet, sim_seed: u64) -> PredictionSet {
    use moma_eval::simulate::{SimulatorConfig, TransparencySource, simulated_predictions};
    simulated_predictions(
        set,
        SimulatorConfig::default(),
        sim_seed,
        PredictionKind::RelativeDisparity,
        TransparencySource::Auto,
    )
    .unwrap()
}
