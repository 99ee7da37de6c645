//! The default normalisation by prediction kind (`moma_core::policy::default_normalisation`),
//! against closed forms: a calibration on one frame of an exact metric prediction, applied to a
//! later frame whose scale drifted or whose nearest surface changed.
//!
//! GSSA fits z = s·ẑ + t exactly on exact data, so the later frame's error is the closed form of
//! the normalisations alone. Frame A: a table at 1.0–1.3 m (metres, depth grows down the image)
//! and a far wall at 5.0 m in the top rows, so z_min = 1.0 m and the range R = 4.0 m.

mod common;

use moma_core::align::Method;
use moma_core::metrics::DepthMetrics;
use moma_core::normalise::{AlignSpace, Normalisation};
use moma_core::pipeline::calibrate;
use moma_core::policy::{default_normalisation, normalisation};
use moma_core::{AlignOptions, CalibrationFrame};
use moma_core::{ImageSize, Mask, MetricDepth, Prediction, PredictionKind};
use ndarray::Array2;

const SIZE: ImageSize = ImageSize::new(80, 60);
const WALL_ROWS: usize = 10;
const WALL_M: f64 = 5.0;

/// Frame A's depth in metres at (row v, column u).
fn table_m(v: usize, u: usize) -> f64 {
    if v < WALL_ROWS {
        WALL_M
    } else {
        1.0 + 0.006 * (v - WALL_ROWS) as f64 + 0.0005 * u as f64
    }
}

/// Frame B: frame A with a box whose top lies 0.8 m away (nearer than anything in A).
fn with_box(v: usize, u: usize) -> f64 {
    if (40..50).contains(&v) && (30..45).contains(&u) {
        0.8
    } else {
        table_m(v, u)
    }
}

fn map(f: impl Fn(usize, usize) -> f64) -> Array2<f32> {
    Array2::from_shape_fn(SIZE.shape(), |(v, u)| f(v, u) as f32)
}

/// Frame A's table pixels (neither the wall nor where frame B's box is): where the closed forms
/// are compared.
fn table_mask() -> Mask {
    Mask::new(Array2::from_shape_fn(SIZE.shape(), |(v, u)| {
        v >= WALL_ROWS && with_box(v, u) == table_m(v, u)
    }))
}

/// The MAE in metres over `region` of frame `later` (an exact metric prediction of `truth`
/// times `scale`) aligned by a GSSA calibration on frame A with normalisation `norm`.
fn later_frame_mae_m(norm: Normalisation, later: &Array2<f32>, scale: f64) -> f64 {
    let gt_a = MetricDepth::new(map(table_m));
    let pred_a = Prediction::new(map(table_m), PredictionKind::MetricDepth);
    let config = common::calibration_config(Method::Gssa, norm, AlignSpace::Depth, 100, 7);
    let cal = calibrate(&[CalibrationFrame::new(&pred_a, &gt_a)], &config).unwrap();
    assert!(
        cal.report.rms_residual_m < 1e-5,
        "{norm:?}: {:?}",
        cal.report
    );
    let pred = Prediction::new(
        later.mapv(|z| (f64::from(z) * scale) as f32),
        PredictionKind::MetricDepth,
    );
    let out = cal.aligned(&pred, &AlignOptions::default()).unwrap().depth;
    let m = DepthMetrics::compute(&out, &MetricDepth::new(later.clone()), Some(&table_mask()));
    m.unwrap().mae
}

/// Mean of `f(z)` over the table pixels of frame A.
fn table_mean(f: impl Fn(f64) -> f64) -> f64 {
    let (mut sum, mut n) = (0.0, 0.0);
    for v in WALL_ROWS..SIZE.height {
        for u in 0..SIZE.width {
            if with_box(v, u) == table_m(v, u) {
                sum += f(table_m(v, u));
                n += 1.0;
            }
        }
    }
    sum / n
}

#[test]
fn the_default_is_the_papers_for_disparity_and_the_authors_code_for_depth() {
    use PredictionKind::*;
    assert_eq!(
        default_normalisation(RelativeDisparity),
        Normalisation::Minmax
    );
    assert_eq!(
        default_normalisation(MetricDepth),
        Normalisation::MinmaxUnit
    );
    assert_eq!(
        default_normalisation(RelativeDepth),
        Normalisation::MinmaxUnit
    );
    for kind in PredictionKind::ALL {
        let n = normalisation(&Method::Gssa, None, None, kind);
        assert_eq!(n.method, default_normalisation(kind), "{kind:?}");
        assert_eq!(n.space, AlignSpace::native(kind), "{kind:?}");
        // RAW uses the prediction as metres: no normalisation unless one is asked for (which
        // its fit then refuses)
        let raw = normalisation(&Method::Raw, None, None, kind);
        assert_eq!(
            (raw.method, raw.space),
            (Normalisation::None, AlignSpace::Depth)
        );
        let asked = normalisation(&Method::Gssa, Some(Normalisation::Median), None, kind);
        assert_eq!(asked.method, Normalisation::Median);
    }
}

#[test]
fn a_metric_frames_scale_drift_is_absorbed_by_the_default_and_kept_by_none() {
    // frame C = frame A's content predicted 3 % too far
    let a = map(table_m);
    let drift = 1.03;
    let default = later_frame_mae_m(
        default_normalisation(PredictionKind::MetricDepth),
        &a,
        drift,
    );
    assert!(
        default < 1e-5,
        "minmax-unit is scale-invariant: {default} m"
    );
    // none keeps the 3 %: 0.03 · z
    let none = later_frame_mae_m(Normalisation::None, &a, drift);
    let expected = table_mean(|z| (drift - 1.0) * z);
    assert!((none - expected).abs() < 1e-4, "{none} vs {expected}");
    // the paper's minmax adds z_min back: 1.03 · 1.0 m instead of 1.0 m, times the range 4 m
    let paper = later_frame_mae_m(Normalisation::Minmax, &a, drift);
    let expected = (WALL_M - 1.0) * (drift - 1.0) * 1.0;
    assert!((paper - expected).abs() < 1e-4, "{paper} vs {expected}");
}

#[test]
fn a_nearer_object_moves_the_papers_minmax_by_the_range_times_its_nearness() {
    // frame B: frame A with a box 0.8 m away; z_min 1.0 → 0.8 m, the range 4.0 → 4.2 m
    let b = map(with_box);
    let (r_a, r_b, min_a, min_b) = (WALL_M - 1.0, WALL_M - 0.8, 1.0, 0.8);
    // minmax-unit: z' = R_a (z − min_b) / R_b + min_a
    let unit = later_frame_mae_m(Normalisation::MinmaxUnit, &b, 1.0);
    let expected_unit = table_mean(|z| (r_a * (z - min_b) / r_b + min_a - z).abs());
    assert!(
        (unit - expected_unit).abs() < 1e-4,
        "{unit} vs {expected_unit}"
    );
    // the paper's: the same plus R_a (min_b − min_a), opposite in sign here
    let paper = later_frame_mae_m(Normalisation::Minmax, &b, 1.0);
    let expected_paper =
        table_mean(|z| (r_a * ((z - min_b) / r_b + min_b - min_a) + min_a - z).abs());
    assert!(
        (paper - expected_paper).abs() < 1e-4,
        "{paper} vs {expected_paper}"
    );
    assert!(paper > 2.5 * unit, "{paper} vs {unit}");
    // none has no statistic to move: exact
    let none = later_frame_mae_m(Normalisation::None, &b, 1.0);
    assert!(none < 1e-5, "{none}");
}
