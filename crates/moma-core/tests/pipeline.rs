//! End to end: calibrate on one frame, align another, score.

mod common;

use moma_core::align::lwlr::LwlrConfig;
use moma_core::align::ssra::SsraConfig;
use moma_core::align::{AlignmentModel, Method};
use moma_core::metrics::DepthMetrics;
use moma_core::normalise::{Normalisation, NormalisationConfig};
use moma_core::pipeline::{Calibration, CalibrationConfig, calibrate};
use moma_core::sampling::SamplingConfig;
use moma_core::{CoreError, ImageSize, Mask, MetricDepth, Prediction, PredictionKind};
use ndarray::Array2;

const SIZE: ImageSize = ImageSize::new(160, 120);

/// Ground truth and an inverse-depth prediction whose 1/d lies exactly in the SSRA family.
fn scene() -> (MetricDepth, Prediction) {
    let gt = common::tabletop_gt(SIZE);
    let inv = Array2::from_shape_fn(SIZE.shape(), |(v, u)| {
        let scale = 0.8 + 1e-3 * u as f64 - 5e-4 * v as f64;
        let pseudo = (f64::from(gt[[v, u]]) - 0.05) / scale;
        (1.0 / pseudo) as f32
    });
    (
        MetricDepth::new(gt),
        Prediction::new(inv, PredictionKind::InverseDepth),
    )
}

fn config(method: Method) -> CalibrationConfig {
    CalibrationConfig {
        method,
        normalisation: NormalisationConfig {
            method: Normalisation::None,
            inverse_space: false,
        },
        sampling: SamplingConfig {
            n: 100,
            seed: 3,
            ..Default::default()
        },
    }
}

#[test]
fn ssra_end_to_end_is_exact_on_its_own_family() {
    let (gt, pred) = scene();
    let cal = calibrate(
        &pred,
        &gt,
        &config(Method::Ssra(SsraConfig::default())),
        None,
        None,
    )
    .unwrap();
    assert_eq!(cal.report.n_used, 100);
    assert!(cal.report.rms_residual_m < 1e-5, "{:?}", cal.report);
    let out = cal.align(&pred, None).unwrap();
    let m = DepthMetrics::compute(&out, &gt, None).unwrap();
    assert!(m.mae < 1e-5 && m.d105 == 1.0, "{m:?}");
    // GSSA cannot represent the scale field and is clearly worse
    let g = calibrate(&pred, &gt, &config(Method::Gssa), None, None).unwrap();
    let mg = DepthMetrics::compute(&g.align(&pred, None).unwrap(), &gt, None).unwrap();
    assert!(mg.mae > 100.0 * m.mae.max(1e-6), "{mg:?}");
}

#[test]
fn every_method_runs_and_calibration_round_trips_through_json() {
    let (gt, pred) = scene();
    for method in [
        Method::Raw,
        Method::Gssa,
        Method::Ssra(SsraConfig::default()),
        Method::Lwlr(LwlrConfig::default()),
    ] {
        let cal = calibrate(&pred, &gt, &config(method.clone()), None, None).unwrap();
        assert_eq!(cal.report.method, method.name());
        let json = serde_json::to_string(&cal).unwrap();
        // serde_json parses f64 to within 1 ulp (exact only with its `float_roundtrip` feature)
        let back: Calibration = serde_json::from_str(&json).unwrap();
        assert_eq!(
            (back.prediction_kind, back.normalisation, back.samples.len()),
            (cal.prediction_kind, cal.normalisation, cal.samples.len())
        );
        let (x, y) = (
            back.align(&pred, None).unwrap().depth_m,
            cal.align(&pred, None).unwrap().depth_m,
        );
        assert!(
            x.iter().zip(&y).all(|(p, q)| (p - q).abs() < 1e-6),
            "{}",
            method.name()
        );
    }
}

#[test]
fn workspace_and_sample_region_are_used() {
    let (gt, pred) = scene();
    let region = Mask::new(Array2::from_shape_fn(SIZE.shape(), |(v, u)| {
        u < 80 && v >= 30
    }));
    let mut cfg = config(Method::Ssra(SsraConfig::default()));
    cfg.normalisation.method = Normalisation::Minmax;
    let cal = calibrate(&pred, &gt, &cfg, Some(&region), Some(&region)).unwrap();
    assert!(
        cal.samples
            .samples
            .iter()
            .all(|s| s.u < 80.0 && s.v >= 30.0)
    );
    // the same workspace at run time reproduces the calibration frame
    let out = cal.align(&pred, Some(&region)).unwrap();
    let m = DepthMetrics::compute(&out, &gt, Some(&region)).unwrap();
    assert!(m.mae < 0.02, "{m:?}");
}

#[test]
fn pipeline_errors() {
    let (gt, pred) = scene();
    let cal = calibrate(&pred, &gt, &config(Method::Gssa), None, None).unwrap();
    let as_depth = Prediction::new(pred.values.clone(), PredictionKind::Depth);
    assert_eq!(
        cal.align(&as_depth, None),
        Err(CoreError::KindMismatch {
            expected: PredictionKind::InverseDepth,
            got: PredictionKind::Depth
        })
    );
    let small = Prediction::new(
        Array2::from_elem((10, 10), 1.0),
        PredictionKind::InverseDepth,
    );
    assert!(matches!(
        cal.align(&small, None),
        Err(CoreError::SizeMismatch { .. })
    ));
    assert!(matches!(
        calibrate(&small, &gt, &config(Method::Gssa), None, None),
        Err(CoreError::SizeMismatch { .. })
    ));
    let invalid_gt = MetricDepth::new(Array2::from_elem(SIZE.shape(), 0.0));
    assert!(matches!(
        calibrate(&pred, &invalid_gt, &config(Method::Gssa), None, None),
        Err(CoreError::NoValidPixels(_))
    ));
    let mut nan_pred = pred.clone();
    nan_pred.values[[5, 6]] = f32::NAN;
    assert!(matches!(
        calibrate(&nan_pred, &gt, &config(Method::Gssa), None, None),
        Err(CoreError::NonFinitePrediction {
            count: 1,
            u: 6,
            v: 5
        })
    ));
    // only 3 valid ground-truth pixels: too few for SSRA
    let mut sparse = Array2::from_elem(SIZE.shape(), 0.0f32);
    for (k, (v, u)) in [(10, 10), (50, 90), (100, 20)].into_iter().enumerate() {
        sparse[[v, u]] = 1.0 + k as f32 * 0.1;
    }
    assert!(matches!(
        calibrate(
            &pred,
            &MetricDepth::new(sparse),
            &config(Method::Ssra(SsraConfig::default())),
            None,
            None
        ),
        Err(CoreError::TooFewSamples {
            need: 4,
            got: 3,
            ..
        })
    ));
    assert!(matches!(cal.model, AlignmentModel::Gssa(_)));
}
