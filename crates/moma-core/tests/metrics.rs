//! Metrics against hand-computed values.

use moma_core::metrics::{DepthMetrics, MetricsAggregator};
use moma_core::{CoreError, ImageSize, Mask, MetricDepth};
use ndarray::{Array2, array};

fn md(a: Array2<f32>) -> MetricDepth {
    MetricDepth::new(a)
}

const TOL: f64 = 1e-6;

#[test]
fn hand_computed_values() {
    // (p, g): (1.04, 1) passes all δ; (1.9, 2): ratio 1.0526 fails 1.05 only; (5, 4): ratio 1.25
    // exactly fails all (strict <); (3, NaN) excluded.
    let gt = md(array![[1.0, 2.0], [4.0, f32::NAN]]);
    let pred = md(array![[1.04, 1.9], [5.0, 3.0]]);
    let m = DepthMetrics::compute(&pred, &gt, None).unwrap();
    assert_eq!(m.n, 3);
    assert!((m.d105 - 1.0 / 3.0).abs() < TOL);
    assert!((m.d110 - 2.0 / 3.0).abs() < TOL);
    assert!((m.d125 - 2.0 / 3.0).abs() < TOL);
    assert!(
        (m.rel - (0.04 + 0.05 + 0.25) / 3.0).abs() < TOL,
        "{}",
        m.rel
    );
    assert!((m.mae - (0.04 + 0.1 + 1.0) / 3.0).abs() < TOL);
    assert!((m.rmse - ((0.0016 + 0.01 + 1.0) / 3.0f64).sqrt()).abs() < TOL);
}

#[test]
fn mask_non_finite_and_nonpositive_predictions() {
    // pixel 0 masked out; pixel 1 p = NaN (excluded); pixel 2 p = −1 counted, fails δ;
    // pixel 3 g = 0 (invalid) excluded; pixel 4 p = inf excluded; pixel 5 exact
    let gt = md(array![[1.0, 1.0, 1.0], [0.0, 2.0, 3.0]]);
    let pred = md(array![[9.0, f32::NAN, -1.0], [1.0, f32::INFINITY, 3.0]]);
    let mask = Mask::new(array![[false, true, true], [true, true, true]]);
    let m = DepthMetrics::compute(&pred, &gt, Some(&mask)).unwrap();
    assert_eq!(m.n, 2);
    assert_eq!((m.d105, m.d110, m.d125), (0.5, 0.5, 0.5));
    assert!((m.mae - 1.0).abs() < TOL); // (2 + 0)/2
    assert!((m.rel - 1.0).abs() < TOL); // (2/1 + 0)/2
    assert!((m.rmse - 2.0f64.sqrt()).abs() < TOL); // sqrt(4/2)
}

#[test]
fn large_map_matches_straightforward_f64_loop() {
    let (h, w) = (123, 77);
    let gt = Array2::from_shape_fn((h, w), |(v, u)| {
        if (u + 2 * v) % 13 == 0 {
            0.0
        } else {
            0.5 + 0.01 * ((u * v) % 97) as f32
        }
    });
    let pred = Array2::from_shape_fn((h, w), |(v, u)| {
        gt[[v, u]] * (1.0 + 0.003 * ((u * 31 + v * 17) % 101) as f32 - 0.15) + 0.001
    });
    let mask = Array2::from_shape_fn((h, w), |(v, u)| (u / 7 + v / 5) % 3 != 0);
    let m = DepthMetrics::compute(
        &md(pred.clone()),
        &md(gt.clone()),
        Some(&Mask::new(mask.clone())),
    )
    .unwrap();
    let (mut n, mut c, mut rel, mut sq, mut ab) = (0.0, [0.0; 3], 0.0, 0.0, 0.0);
    for ((p, g), k) in pred.iter().zip(&gt).zip(&mask) {
        let (p, g) = (f64::from(*p), f64::from(*g));
        if !*k || g.is_nan() || g <= 0.0 || !p.is_finite() {
            continue;
        }
        n += 1.0;
        let r = (p / g).max(g / p);
        for (ci, t) in c.iter_mut().zip([1.05, 1.10, 1.25]) {
            if r < t {
                *ci += 1.0;
            }
        }
        rel += (p - g).abs() / g;
        sq += (p - g) * (p - g);
        ab += (p - g).abs();
    }
    assert_eq!(m.n as f64, n);
    assert!((m.d105 - c[0] / n).abs() < 1e-3, "{} {}", m.d105, c[0] / n); // f32 ratio ties may differ by a pixel
    assert!((m.d125 - c[2] / n).abs() < 1e-3);
    assert!((m.rel - rel / n).abs() < 1e-6);
    assert!((m.rmse - (sq / n).sqrt()).abs() < 1e-6);
    assert!((m.mae - ab / n).abs() < 1e-6);
}

#[test]
fn aggregation_mean_and_pooled() {
    let a = DepthMetrics {
        d105: 1.0,
        d110: 1.0,
        d125: 1.0,
        rel: 0.1,
        rmse: 3.0,
        mae: 0.2,
        n: 1,
    };
    let b = DepthMetrics {
        d105: 0.0,
        d110: 0.5,
        d125: 1.0,
        rel: 0.4,
        rmse: 1.0,
        mae: 0.5,
        n: 3,
    };
    let mut agg = MetricsAggregator::new();
    agg.push(a);
    agg.push(b);
    let mean = agg.mean().unwrap();
    assert_eq!(
        (mean.d105, mean.d110, mean.rel, mean.rmse, mean.mae, mean.n),
        (0.5, 0.75, 0.25, 2.0, 0.35, 4)
    );
    let pooled = agg.pooled().unwrap();
    assert!((pooled.d105 - 0.25).abs() < 1e-12);
    assert!((pooled.d110 - 0.625).abs() < 1e-12);
    assert!((pooled.rel - 1.3 / 4.0).abs() < 1e-12);
    assert!((pooled.rmse - ((9.0 + 3.0) / 4.0f64).sqrt()).abs() < 1e-12);
    assert!((pooled.mae - 1.7 / 4.0).abs() < 1e-12);
    // pooled over two computed images equals one computation over both images side by side
    let g1 = array![[1.0f32, 2.0, 3.0]];
    let p1 = array![[1.1f32, 2.0, 2.0]];
    let g2 = array![[0.5f32, f32::NAN, 1.0]];
    let p2 = array![[0.7f32, 1.0, 1.02]];
    let m1 = DepthMetrics::compute(&md(p1.clone()), &md(g1.clone()), None).unwrap();
    let m2 = DepthMetrics::compute(&md(p2.clone()), &md(g2.clone()), None).unwrap();
    let both = DepthMetrics::compute(
        &md(ndarray::concatenate![ndarray::Axis(1), p1, p2]),
        &md(ndarray::concatenate![ndarray::Axis(1), g1, g2]),
        None,
    )
    .unwrap();
    let pooled = DepthMetrics::pooled(&[m1, m2]).unwrap();
    assert_eq!(pooled.n, both.n);
    assert!((pooled.rmse - both.rmse).abs() < 1e-6 && (pooled.d105 - both.d105).abs() < 1e-9);
}

#[test]
fn metric_errors() {
    let gt = md(Array2::from_elem((2, 3), f32::NAN));
    let pred = md(Array2::from_elem((2, 3), 1.0));
    assert!(matches!(
        DepthMetrics::compute(&pred, &gt, None),
        Err(CoreError::NoValidPixels(_))
    ));
    let gt = md(Array2::from_elem((2, 3), 1.0));
    let empty = Mask::new(Array2::from_elem((2, 3), false));
    assert!(matches!(
        DepthMetrics::compute(&pred, &gt, Some(&empty)),
        Err(CoreError::NoValidPixels(_))
    ));
    let nan_pred = md(Array2::from_elem((2, 3), f32::NAN));
    assert!(matches!(
        DepthMetrics::compute(&nan_pred, &gt, None),
        Err(CoreError::NoValidPixels(_))
    ));
    let small = md(Array2::from_elem((3, 2), 1.0));
    assert!(matches!(
        DepthMetrics::compute(&small, &gt, None),
        Err(CoreError::SizeMismatch { .. })
    ));
    let wrong = Mask::full(ImageSize::new(2, 3));
    assert!(matches!(
        DepthMetrics::compute(&pred, &gt, Some(&wrong)),
        Err(CoreError::SizeMismatch { .. })
    ));
    assert!(DepthMetrics::mean(&[]).is_err());
    assert!(DepthMetrics::pooled(&[]).is_err());
}
