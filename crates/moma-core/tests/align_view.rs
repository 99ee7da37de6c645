//! The view-taking, fused run-time path (`Calibration::align` / `aligned` of a raw view) against
//! the unfused one (`Calibration::normalise`, then `aligned` of the normalised map): identical bit for bit
//! (NaN where the other is NaN) for every covered combination, the fallback for the others, any
//! strides of input and output, workspace masks, and the same errors.

mod common;

use moma_core::align::lwlr::LwlrConfig;
use moma_core::align::ssra::SsraConfig;
use moma_core::align::{AlignmentModel, Method};
use moma_core::normalise::{AlignSpace, Normalisation, NormalisationConfig};
use moma_core::pipeline::{Calibration, CalibrationConfig, calibrate};
use moma_core::sampling::SamplingConfig;
use moma_core::{AlignOptions, CalibrationFrame, PredictionInput};
use moma_core::{CoreError, ImageSize, Mask, MetricDepth, Prediction, PredictionKind};
use ndarray::{Array2, ArrayView2, ShapeBuilder, s};

/// Width not a multiple of the 8 lanes, so that row tails are exercised.
const SIZE: ImageSize = ImageSize::new(45, 23);

/// Ground truth 0.5–0.9 m with a tilt, and a prediction of `kind` related to it by an unknown
/// scale/shift plus a ripple; a few pixels ≤ 0 (no depth after a conversion of space).
fn scene(kind: PredictionKind) -> (MetricDepth, Array2<f32>) {
    let gt = Array2::from_shape_fn(SIZE.shape(), |(v, u)| {
        0.5 + 0.006 * u as f32 + 0.004 * v as f32 + 0.01 * ((u * v) as f32 * 0.1).sin()
    });
    let pred = Array2::from_shape_fn(SIZE.shape(), |(v, u)| {
        let z = gt[[v, u]];
        let p = if kind.is_disparity() {
            2.0 / z - 0.7
        } else {
            1.3 * z + 0.2
        } + 0.003 * ((u + 3 * v) as f32).cos();
        if (u * 7 + v * 11) % 97 == 0 {
            -0.25
        } else if (u + v) % 131 == 5 {
            0.0
        } else {
            p
        }
    });
    (MetricDepth::new(gt), pred)
}

fn calibration(
    kind: PredictionKind,
    method: Method,
    norm: Normalisation,
    space: AlignSpace,
    workspace: Option<&Mask>,
) -> Option<Calibration> {
    let (gt, pred) = scene(kind);
    let config = common::calibration_config(method, norm, space, 60, 5);
    // Some combinations are refused by design (raw needs depth / none); skip those.
    calibrate(
        &[CalibrationFrame::new(&Prediction::new(pred, kind), &gt)],
        &config.clone().with_workspace(workspace).unwrap(),
    )
    .ok()
}

/// The reference: normalise, then apply the model (the unfused path).
fn unfused(cal: &Calibration, pred: &Array2<f32>, kind: PredictionKind) -> Array2<f32> {
    let p = Prediction::new(pred.clone(), kind);
    let n = cal.normalise(&p).unwrap();
    cal.aligned(
        PredictionInput::normalised(&n, kind),
        &AlignOptions::default(),
    )
    .unwrap()
    .depth
    .depth_m
}

/// [`Calibration::aligned`] of a borrowed view (no options): metres.
fn aligned_view(cal: &Calibration, pred: ArrayView2<'_, f32>, kind: PredictionKind) -> Array2<f32> {
    cal.aligned(PredictionInput::view(pred, kind), &AlignOptions::default())
        .unwrap()
        .depth
        .depth_m
}

fn assert_same(what: &str, got: ArrayView2<'_, f32>, want: ArrayView2<'_, f32>) {
    assert_eq!(got.dim(), want.dim(), "{what}");
    let mut nan = 0;
    for ((i, &g), &w) in got.indexed_iter().zip(want.iter()) {
        if w.is_nan() {
            assert!(g.is_nan(), "{what} at {i:?}: got {g}, want NaN");
            nan += 1;
        } else {
            assert_eq!(
                g.to_bits(),
                w.to_bits(),
                "{what} at {i:?}: got {g}, want {w}"
            );
        }
    }
    assert!(nan < got.len(), "{what}: all NaN");
}

fn workspace() -> Mask {
    Mask::new(Array2::from_shape_fn(SIZE.shape(), |(v, u)| {
        (5..35).contains(&u) && (3..20).contains(&v)
    }))
}

#[test]
fn fused_path_equals_unfused_bit_for_bit() {
    let methods = [
        Method::Gssa,
        Method::Ssra(SsraConfig::default()),
        Method::Lwlr(LwlrConfig::default()),
        Method::Raw,
    ];
    let ws = workspace();
    let mut checked = 0;
    let mut fused_models = 0;
    for kind in [
        PredictionKind::RelativeDisparity,
        PredictionKind::MetricDepth,
    ] {
        let (_, pred) = scene(kind);
        for method in &methods {
            for norm in Normalisation::ALL {
                for space in AlignSpace::ALL {
                    for region in [None, Some(&ws)] {
                        let Some(cal) = calibration(kind, method.clone(), norm, space, region)
                        else {
                            continue;
                        };
                        let what =
                            format!("{kind} {method} {norm} {space} ws={}", region.is_some());
                        let want = unfused(&cal, &pred, kind);
                        // no output pixel is at or behind the camera; a metric depth ≤ 0 is
                        // no prediction, so no depth
                        assert!(
                            want.iter().all(|&z| z > 0.0 || z.is_nan()),
                            "{what}: a depth ≤ 0 m"
                        );
                        if kind == PredictionKind::MetricDepth {
                            for (w, &p) in want.iter().zip(&pred) {
                                assert!(p > 0.0 || w.is_nan(), "{what}: {p} gave {w} m");
                            }
                        }
                        let got = aligned_view(&cal, pred.view(), kind);
                        assert_same(&what, got.view(), want.view());
                        let mut out = Array2::from_elem(SIZE.shape(), 7.0f32);
                        cal.align(
                            PredictionInput::view(pred.view(), kind),
                            &AlignOptions::default(),
                            &mut out.view_mut(),
                        )
                        .unwrap();
                        assert_same(&what, out.view(), want.view());
                        // The owned API is the same path.
                        let owned = cal
                            .aligned(
                                &Prediction::new(pred.clone(), kind),
                                &AlignOptions::default(),
                            )
                            .unwrap()
                            .depth;
                        assert_same(&what, owned.depth_m.view(), want.view());
                        checked += 1;
                        if matches!(cal.model, AlignmentModel::Gssa(_) | AlignmentModel::Ssra(_))
                            && norm != Normalisation::Median
                        {
                            fused_models += 1;
                        }
                    }
                }
            }
        }
    }
    // 2 kinds × (gssa, ssra, lwlr: 4 norms × 2 spaces × 2 regions) + raw (depth, none, depth
    // space, 2 regions).
    assert_eq!(checked, 2 * 3 * 4 * 2 * 2 + 2);
    assert_eq!(fused_models, 2 * 2 * 3 * 2 * 2);
}

#[test]
fn strided_input_and_output_give_the_same_result() {
    let kind = PredictionKind::RelativeDisparity;
    let (_, pred) = scene(kind);
    for method in [Method::Gssa, Method::Ssra(SsraConfig::default())] {
        for space in AlignSpace::ALL {
            let cal =
                calibration(kind, method.clone(), Normalisation::Minmax, space, None).unwrap();
            let want = unfused(&cal, &pred, kind);
            // Column-major copy (Fortran order): the view is not row-contiguous.
            let mut fortran = Array2::<f32>::zeros(SIZE.shape().f());
            fortran.assign(&pred);
            assert!(fortran.view().as_slice().is_none());
            let got = aligned_view(&cal, fortran.view(), kind);
            assert_same("fortran input", got.view(), want.view());
            // Every other column of a wider array.
            let mut wide = Array2::<f32>::zeros((SIZE.height, 2 * SIZE.width));
            wide.slice_mut(s![.., ..;2]).assign(&pred);
            let got = aligned_view(&cal, wide.slice(s![.., ..;2]), kind);
            assert_same("strided input", got.view(), want.view());
            // A strided output.
            let mut out_wide = Array2::<f32>::zeros((SIZE.height, 2 * SIZE.width));
            cal.align(
                PredictionInput::view(pred.view(), kind),
                &AlignOptions::default(),
                &mut out_wide.slice_mut(s![.., ..;2]),
            )
            .unwrap();
            assert_same("strided output", out_wide.slice(s![.., ..;2]), want.view());
            assert!(out_wide.slice(s![.., 1..;2]).iter().all(|&x| x == 0.0));
        }
    }
}

#[test]
fn fused_path_reports_the_unfused_errors() {
    let kind = PredictionKind::RelativeDisparity;
    let (_, pred) = scene(kind);
    let cal = calibration(
        kind,
        Method::Ssra(SsraConfig::default()),
        Normalisation::Minmax,
        AlignSpace::Inverse,
        None,
    )
    .unwrap();
    let err_of = |p: &Array2<f32>| {
        let fused = cal
            .aligned(
                PredictionInput::view(p.view(), kind),
                &AlignOptions::default(),
            )
            .map(|a| a.depth)
            .unwrap_err()
            .to_string();
        let unfused = cal
            .normalise(&Prediction::new(p.clone(), kind))
            .unwrap_err()
            .to_string();
        assert_eq!(fused, unfused);
        fused
    };
    let mut bad = pred.clone();
    bad[[4, 9]] = f32::NAN;
    bad[[10, 2]] = f32::INFINITY;
    err_of(&bad);
    assert!(matches!(
        cal.aligned(
            PredictionInput::view(bad.view(), kind),
            &AlignOptions::default()
        )
        .map(|a| a.depth),
        Err(CoreError::NonFinitePrediction {
            count: 2,
            u: 9,
            v: 4,
            ..
        })
    ));
    let constant = Array2::from_elem(SIZE.shape(), 0.5f32);
    assert!(matches!(
        cal.aligned(
            PredictionInput::view(constant.view(), kind),
            &AlignOptions::default()
        )
        .map(|a| a.depth),
        Err(CoreError::Degenerate(_))
    ));
    err_of(&constant);
    // Kind, prediction size and output size.
    assert!(matches!(
        cal.aligned(
            PredictionInput::view(pred.view(), PredictionKind::MetricDepth),
            &AlignOptions::default()
        )
        .map(|a| a.depth),
        Err(CoreError::KindMismatch { .. })
    ));
    assert!(matches!(
        cal.aligned(
            PredictionInput::view(pred.slice(s![1.., ..]), kind),
            &AlignOptions::default()
        )
        .map(|a| a.depth),
        Err(CoreError::SizeMismatch { .. })
    ));
    let mut small = Array2::<f32>::zeros((SIZE.height, SIZE.width - 1));
    assert!(matches!(
        cal.align(
            PredictionInput::view(pred.view(), kind),
            &AlignOptions::default(),
            &mut small.view_mut()
        ),
        Err(CoreError::SizeMismatch { .. })
    ));
}

#[test]
fn fused_inverse_space_shifted_disparity_is_recovered() {
    // Independent expectation: d = 2/z − 0.7 exactly (no ripple, no invalid pixel) is affine in
    // 1/z, so GSSA in inverse space recovers z to float precision.
    let gt = Array2::from_shape_fn(SIZE.shape(), |(v, u)| {
        0.5 + 0.006 * u as f32 + 0.004 * v as f32
    });
    let pred = gt.mapv(|z| 2.0 / z - 0.7);
    let config = CalibrationConfig {
        method: Method::Gssa,
        normalisation: NormalisationConfig::native(
            Normalisation::Minmax,
            PredictionKind::RelativeDisparity,
        ),
        sampling: SamplingConfig {
            n: 50,
            seed: 1,
            ..Default::default()
        },
        robust: None,
        workspace: None,
    };
    let cal = calibrate(
        &[CalibrationFrame::new(
            &Prediction::new(pred.clone(), PredictionKind::RelativeDisparity),
            &MetricDepth::new(gt.clone()),
        )],
        &config,
    )
    .unwrap();
    let out = cal
        .aligned(
            PredictionInput::view(pred.view(), PredictionKind::RelativeDisparity),
            &AlignOptions::default(),
        )
        .unwrap()
        .depth
        .depth_m;
    for (&o, &z) in out.iter().zip(gt.iter()) {
        assert!((o - z).abs() < 2e-5 * z, "{o} vs {z}");
    }
}

/// A metric-depth map with every value positive takes the fused depth-space kernel (the scene
/// above has values ≤ 0, so its metric cases fall back): fused equals unfused. A relative-depth
/// calibration given a metric-depth prediction (it accepts one) makes its values ≤ 0 no depth
/// on both paths: the rule follows the input's kind.
#[test]
fn metric_depth_fused_and_its_non_positive_values_follow_the_inputs_kind() {
    let (_, pred) = scene(PredictionKind::MetricDepth);
    let positive = pred.mapv(|p| if p > 0.0 { p } else { 0.9 });
    let mut checked = 0;
    for method in [Method::Gssa, Method::Ssra(SsraConfig::default())] {
        for norm in [
            Normalisation::None,
            Normalisation::Minmax,
            Normalisation::MinmaxUnit,
        ] {
            let Some(cal) = calibration(
                PredictionKind::MetricDepth,
                method.clone(),
                norm,
                AlignSpace::Depth,
                None,
            ) else {
                continue;
            };
            let what = format!("metric {method} {norm}");
            let want = unfused(&cal, &positive, PredictionKind::MetricDepth);
            let got = aligned_view(&cal, positive.view(), PredictionKind::MetricDepth);
            assert_same(&what, got.view(), want.view());
            checked += 1;
        }
    }
    assert_eq!(checked, 6);
    let cal = calibration(
        PredictionKind::RelativeDepth,
        Method::Gssa,
        Normalisation::None,
        AlignSpace::Depth,
        None,
    )
    .expect("a relative-depth calibration");
    let want = unfused(&cal, &pred, PredictionKind::MetricDepth);
    let got = aligned_view(&cal, pred.view(), PredictionKind::MetricDepth);
    assert_same(
        "relative-depth calibration, metric input",
        got.view(),
        want.view(),
    );
    for (w, &p) in want.iter().zip(&pred) {
        assert!(p > 0.0 || w.is_nan(), "{p} gave {w} m");
    }
}
