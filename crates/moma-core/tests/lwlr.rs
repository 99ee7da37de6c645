//! LWLR: limits, naive references, grid vs exact, serialisation, bad input.

mod common;

use moma_core::align::gssa;
use moma_core::align::lwlr::{LwlrConfig, LwlrModel, LwlrSolve};
use moma_core::align::{AlignmentModel, Method, SampleSet};
use moma_core::sampling::{SamplingConfig, sample_pixels};
use moma_core::{CoreError, ImageSize, MetricDepth};
use nalgebra::{Matrix2, Vector2};
use ndarray::Array2;

fn fit_lwlr(set: &SampleSet, cfg: LwlrConfig) -> LwlrModel {
    match Method::Lwlr(cfg).fit(set).unwrap().0 {
        AlignmentModel::Lwlr(m) => m,
        other => panic!("{other:?}"),
    }
}

fn nonlinear_truth(u: f64, v: f64, p: f64) -> f64 {
    p * (0.9 + 2e-3 * u - 1e-3 * v + 0.05 * (u / 9.0).sin()) + 0.1 + 0.02 * (v / 7.0).cos()
}

/// Dense per-point reference: w_k = exp(−d²/2b²), x = prefit(ẑ), 2×2 ridge solve, folded onto ẑ.
fn reference_scale_shift(m: &LwlrModel, u: f64, v: f64) -> (f64, f64) {
    let (ps, pt) = if m.config.global_prefit {
        (m.global.scale, m.global.shift)
    } else {
        (1.0, 0.0)
    };
    let b = m.bandwidth_px;
    let mut a = Matrix2::zeros();
    let mut r = Vector2::zeros();
    for s in &m.samples {
        let w = (-((u - s.u).powi(2) + (v - s.v).powi(2)) / (2.0 * b * b)).exp();
        let x = Vector2::new(ps * s.pred + pt, 1.0);
        a += w * x * x.transpose();
        r += w * x * s.target;
    }
    a[(1, 1)] += m.config.ridge_shift;
    let sol = a.lu().solve(&r).expect("reference system singular");
    (sol[0] * ps, sol[0] * pt + sol[1])
}

#[test]
fn huge_bandwidth_without_ridge_equals_gssa() {
    let size = ImageSize::new(48, 36);
    let set = common::samples(size, 30, 1, 0.0, nonlinear_truth);
    let g = gssa::fit(&set.samples).unwrap();
    for prefit in [false, true] {
        for solve in [LwlrSolve::Exact, LwlrSolve::Grid] {
            let cfg = LwlrConfig {
                solve,
                bandwidth_px: Some(1e7),
                ridge_shift: 0.0,
                global_prefit: prefit,
                grid_step_px: 8,
                grid_offset_px: 4,
            };
            let m = fit_lwlr(&set, cfg);
            let maps = m.maps();
            assert_eq!(maps.singular_fits, 0);
            for (&s, &t) in maps.scale.iter().zip(&maps.shift) {
                assert!(
                    (f64::from(s) - g.scale).abs() < 1e-5,
                    "{prefit} {solve:?}: {s} vs {}",
                    g.scale
                );
                assert!((f64::from(t) - g.shift).abs() < 1e-5, "{t} vs {}", g.shift);
            }
        }
    }
}

#[test]
fn exact_matches_naive_reference() {
    let size = ImageSize::new(40, 30);
    let set = common::samples(size, 25, 2, 0.002, nonlinear_truth);
    for cfg in [
        LwlrConfig {
            bandwidth_px: Some(6.0),
            ..LwlrConfig::exact()
        },
        LwlrConfig {
            bandwidth_px: Some(9.0),
            ..LwlrConfig::bare_exact()
        },
    ] {
        let m = fit_lwlr(&set, cfg);
        let maps = m.maps();
        assert_eq!(maps.singular_fits, 0);
        let points = [(3.0, 7.0), (39.0, 29.0), (17.5, 11.0)];
        for (&(u, v), got) in points.iter().zip(m.scales_at(&points)) {
            let (want, _) = reference_scale_shift(&m, u, v);
            assert!(
                (got - want).abs() < 1e-9 * (1.0 + want.abs()),
                "({u},{v}) {got} vs {want}"
            );
        }
        for v in 0..30 {
            for u in 0..40 {
                let (s, t) = reference_scale_shift(&m, u as f64, v as f64);
                let (gs, gt) = (f64::from(maps.scale[[v, u]]), f64::from(maps.shift[[v, u]]));
                assert!(
                    (gs - s).abs() < 1e-5 * (1.0 + s.abs()),
                    "({u},{v}) scale {gs} vs {s} {cfg:?}"
                );
                assert!(
                    (gt - t).abs() < 1e-5 * (1.0 + t.abs()),
                    "({u},{v}) shift {gt} vs {t}"
                );
                // f64 single-point path
                let p = 0.8;
                assert!((m.predict(u as f64, v as f64, p) - (s * p + t)).abs() < 1e-9);
            }
        }
    }
}

/// BoostingDepth-style grid reference: nodes `np.arange(off, W, step)`, dense solve per node,
/// then an OpenCV INTER_LINEAR resize (half-pixel centres, clamped borders), written out per pixel.
fn reference_grid(m: &LwlrModel) -> (Array2<f64>, Array2<f64>) {
    let (w, h) = (m.image_size.width, m.image_size.height);
    let (step, off) = (m.config.grid_step_px, m.config.grid_offset_px);
    let xs: Vec<usize> = (off..w).step_by(step).collect();
    let ys: Vec<usize> = (off..h).step_by(step).collect();
    let node = |i: usize, j: usize| reference_scale_shift(m, xs[i] as f64, ys[j] as f64);
    let coord = |x: usize, n: usize, len: usize| {
        let mut f = (x as f64 + 0.5) * n as f64 / len as f64 - 0.5;
        let mut s = f.floor() as i64;
        f -= s as f64;
        if s < 0 {
            f = 0.0;
            s = 0;
        }
        if s >= n as i64 - 1 {
            f = 0.0;
            s = n as i64 - 1;
        }
        let s = s as usize;
        (s, (s + 1).min(n - 1), f)
    };
    let mut sm = Array2::zeros((h, w));
    let mut tm = Array2::zeros((h, w));
    for y in 0..h {
        let (y0, y1, fy) = coord(y, ys.len(), h);
        for x in 0..w {
            let (x0, x1, fx) = coord(x, xs.len(), w);
            let c = [node(x0, y0), node(x1, y0), node(x0, y1), node(x1, y1)];
            let wts = [
                (1.0 - fx) * (1.0 - fy),
                fx * (1.0 - fy),
                (1.0 - fx) * fy,
                fx * fy,
            ];
            sm[[y, x]] = (0..4).map(|k| wts[k] * c[k].0).sum();
            tm[[y, x]] = (0..4).map(|k| wts[k] * c[k].1).sum();
        }
    }
    (sm, tm)
}

#[test]
fn grid_matches_boostingdepth_style_reference() {
    let size = ImageSize::new(70, 45); // not multiples of the step: partial last cells
    let set = common::samples(size, 30, 3, 0.001, nonlinear_truth);
    let cfg = LwlrConfig {
        bandwidth_px: Some(12.0),
        grid_step_px: 8,
        grid_offset_px: 4,
        ..LwlrConfig::faithful()
    };
    let m = fit_lwlr(&set, cfg);
    let (sm, tm) = reference_grid(&m);
    let maps = m.maps();
    for ((a, b), (c, d)) in maps.scale.iter().zip(&sm).zip(maps.shift.iter().zip(&tm)) {
        assert!(
            (f64::from(*a) - b).abs() < 1e-5 * (1.0 + b.abs()),
            "scale {a} vs {b}"
        );
        assert!(
            (f64::from(*c) - d).abs() < 1e-5 * (1.0 + d.abs()),
            "shift {c} vs {d}"
        );
    }
    // the f64 single-point path interpolates the same way
    assert!((m.predict(13.0, 40.0, 1.1) - (sm[[40, 13]] * 1.1 + tm[[40, 13]])).abs() < 1e-9);
    // and so do the local scales at scattered points, from the nodes around them only
    let points = [
        (13.0, 40.0),
        (0.0, 0.0),
        (69.0, 44.0),
        (35.0, 3.0),
        (36.0, 3.0),
    ];
    for (&(u, v), got) in points.iter().zip(m.scales_at(&points)) {
        let want = sm[[v as usize, u as usize]];
        assert!(
            (got - want).abs() < 1e-9 * (1.0 + want.abs()),
            "({u},{v}) {got} vs {want}"
        );
    }
}

#[test]
fn faithful_defaults() {
    let c = LwlrConfig::default();
    assert_eq!(
        (
            c.solve,
            c.ridge_shift,
            c.global_prefit,
            c.grid_step_px,
            c.grid_offset_px
        ),
        (LwlrSolve::Grid, 1.0, true, 32, 16)
    );
    assert_eq!(c.bandwidth_for(ImageSize::new(640, 480)), 50.0);
    assert_eq!(c.bandwidth_for(ImageSize::new(1280, 720)), 100.0);
    let set = common::samples(ImageSize::new(640, 480), 10, 4, 0.0, nonlinear_truth);
    let m = fit_lwlr(&set, c);
    let (xs, ys) = m.grid_nodes();
    assert_eq!(
        (xs.len(), ys.len(), xs[0], xs[19], ys[14]),
        (20, 15, 16.0, 624.0, 464.0)
    );
}

#[test]
fn singular_local_systems_fall_back_to_global_fit() {
    let size = ImageSize::new(60, 40);
    let set = common::samples(size, 12, 5, 0.0, nonlinear_truth);
    let g = gssa::fit(&set.samples).unwrap();
    let cfg = LwlrConfig {
        bandwidth_px: Some(0.3),
        ..LwlrConfig::bare_exact()
    };
    let m = fit_lwlr(&set, cfg);
    let maps = m.maps();
    assert!(maps.singular_fits > 1000, "{}", maps.singular_fits);
    assert!(maps.scale.iter().chain(&maps.shift).all(|x| x.is_finite()));
    // a pixel far from every sample uses the global fit
    let far = (0..40)
        .flat_map(|v| (0..60).map(move |u| (u, v)))
        .max_by_key(|&(u, v)| {
            set.samples
                .iter()
                .map(|s| ((s.u - u as f64).powi(2) + (s.v - v as f64).powi(2)) as i64)
                .min()
                .unwrap()
        })
        .unwrap();
    assert!((f64::from(maps.scale[[far.1, far.0]]) - g.scale).abs() < 1e-6);
    assert!((f64::from(maps.shift[[far.1, far.0]]) - g.shift).abs() < 1e-6);
}

#[test]
fn serialises_compactly_and_recomputes_maps() {
    let size = ImageSize::new(64, 48);
    let set = common::samples(size, 20, 6, 0.001, nonlinear_truth);
    let (model, _) = Method::Lwlr(LwlrConfig {
        bandwidth_px: Some(10.0),
        ..Default::default()
    })
    .fit(&set)
    .unwrap();
    let json = serde_json::to_string(&model).unwrap();
    assert!(json.len() < 4000, "{} bytes", json.len());
    assert!(!json.contains("maps"), "{json}");
    // serde_json parses f64 to within 1 ulp (exact only with its `float_roundtrip` feature)
    let back: AlignmentModel = serde_json::from_str(&json).unwrap();
    let (AlignmentModel::Lwlr(a), AlignmentModel::Lwlr(b)) = (&back, &model) else {
        unreachable!()
    };
    assert_eq!(
        (a.config, a.image_size, a.samples.len()),
        (b.config, b.image_size, b.samples.len())
    );
    let z = Array2::from_shape_fn((48, 64), |(v, u)| 0.5 + 0.01 * ((u + v) % 50) as f32);
    let (x, y) = (
        back.apply(z.view()).unwrap().depth_m,
        model.apply(z.view()).unwrap().depth_m,
    );
    assert!(x.iter().zip(&y).all(|(p, q)| (p - q).abs() < 1e-6));
}

#[test]
fn apply_keeps_nan_and_checks_size() {
    let size = ImageSize::new(32, 24);
    let set = common::samples(size, 20, 7, 0.0, nonlinear_truth);
    let (model, report) = Method::Lwlr(LwlrConfig {
        bandwidth_px: Some(6.0),
        ..LwlrConfig::exact()
    })
    .fit(&set)
    .unwrap();
    assert_eq!((report.method.as_str(), report.n_used), ("lwlr-exact", 20));
    assert!(report.rms_residual_m.is_finite());
    let mut z = Array2::from_elem((24, 32), 0.9f32);
    z[[3, 4]] = f32::NAN;
    let out = model.apply(z.view()).unwrap().depth_m;
    assert!(out[[3, 4]].is_nan());
    let AlignmentModel::Lwlr(m) = &model else {
        unreachable!()
    };
    assert!((f64::from(out[[5, 6]]) - m.predict(6.0, 5.0, 0.9)).abs() < 1e-5);
    assert!(matches!(
        model.apply(Array2::<f32>::ones((24, 31)).view()),
        Err(CoreError::SizeMismatch { .. })
    ));
}

#[test]
fn invalid_settings_are_errors() {
    let set = common::samples(ImageSize::new(32, 24), 10, 8, 0.0, nonlinear_truth);
    for cfg in [
        LwlrConfig {
            bandwidth_px: Some(0.0),
            ..Default::default()
        },
        LwlrConfig {
            bandwidth_px: Some(f64::NAN),
            ..Default::default()
        },
        LwlrConfig {
            ridge_shift: -1.0,
            ..Default::default()
        },
        LwlrConfig {
            grid_step_px: 0,
            ..Default::default()
        },
    ] {
        assert!(
            matches!(
                Method::Lwlr(cfg).fit(&set),
                Err(CoreError::InvalidParameter(_))
            ),
            "{cfg:?}"
        );
    }
}

/// Grid (BoostingDepth) vs exact per-pixel solve on a realistic 640×480 tabletop, default settings.
/// Run with `cargo test -p moma-core --release --test lwlr -- --nocapture grid_vs_exact`.
#[test]
fn grid_vs_exact_difference() {
    let size = ImageSize::new(640, 480);
    let gt = common::tabletop_gt(size);
    let pred = common::distorted_prediction(&gt);
    let normalised = moma_core::normalise::NormalisedMap {
        values: pred.clone(),
        stats: moma_core::normalise::NormStats {
            min: 0.0,
            max: 0.0,
            median: f64::NAN,
            mad: f64::NAN,
            n: 0,
        },
    };
    let gtm = MetricDepth::new(gt.clone());
    let px = sample_pixels(
        &gtm,
        &SamplingConfig {
            n: 100,
            seed: 0,
            ..Default::default()
        },
        None,
    )
    .unwrap();
    let set = SampleSet::gather(&normalised, &gtm, &px).unwrap();
    let (grid, _) = Method::Lwlr(LwlrConfig::faithful()).fit(&set).unwrap();
    let (exact, _) = Method::Lwlr(LwlrConfig::exact()).fit(&set).unwrap();
    let (bare, _) = Method::Lwlr(LwlrConfig::bare_exact()).fit(&set).unwrap();
    let a = grid.apply(pred.view()).unwrap().depth_m;
    let b = exact.apply(pred.view()).unwrap().depth_m;
    let c = bare.apply(pred.view()).unwrap().depth_m;
    let diffs: Vec<f64> = a
        .iter()
        .zip(&b)
        .map(|(x, y)| f64::from((x - y).abs()))
        .collect();
    let mean = diffs.iter().sum::<f64>() / diffs.len() as f64;
    let max = diffs.iter().copied().fold(0.0, f64::max);
    let err = |m: &Array2<f32>| {
        m.iter()
            .zip(&gt)
            .map(|(x, y)| f64::from((x - y).abs()))
            .sum::<f64>()
            / gt.len() as f64
    };
    println!(
        "LWLR grid vs exact (640x480, n=100, b=50 px, ridge 1, pre-fit): mean |Δ| = {:.3} mm, max |Δ| = {:.3} mm; \
         MAE vs GT: grid {:.3} mm, exact {:.3} mm, bare exact (no pre-fit, no ridge) {:.3} mm",
        mean * 1e3,
        max * 1e3,
        err(&a) * 1e3,
        err(&b) * 1e3,
        err(&c) * 1e3
    );
    assert!(
        mean < 2e-3 && max < 2e-2,
        "grid and exact too far apart: mean {mean} max {max}"
    );
    assert!(mean > 0.0);
}

/// A lattice large enough for the thread pool (300 nodes × 100 samples: the maps and the
/// single-point path) and the few nodes of `scales_at`, solved on the calling thread: both
/// against the grid reference.
#[test]
fn pooled_and_calling_thread_lattices_agree_with_the_reference() {
    let size = ImageSize::new(640, 480);
    let set = common::samples(size, 100, 5, 0.001, nonlinear_truth);
    let m = fit_lwlr(&set, LwlrConfig::default());
    let (xs, ys) = m.grid_nodes();
    assert!(
        xs.len() * ys.len() * 100 >= 1 << 14,
        "the full lattice goes to the pool"
    );
    let (sm, tm) = reference_grid(&m);
    let maps = m.maps();
    let points = [(16.0, 16.0), (331.0, 207.0), (639.0, 479.0), (0.0, 300.0)];
    for (&(u, v), got) in points.iter().zip(m.scales_at(&points)) {
        let (us, vs) = (u as usize, v as usize);
        let (s, t) = (sm[[vs, us]], tm[[vs, us]]);
        assert!(
            (got - s).abs() < 1e-9 * (1.0 + s.abs()),
            "({u},{v}) {got} vs {s}"
        );
        let (ms, mt) = (maps.scale[[vs, us]], maps.shift[[vs, us]]);
        assert!(
            (f64::from(ms) - s).abs() < 1e-5 * (1.0 + s.abs()),
            "scale {ms} vs {s}"
        );
        assert!(
            (f64::from(mt) - t).abs() < 1e-5 * (1.0 + t.abs()),
            "shift {mt} vs {t}"
        );
        let slope = m.predict(u, v, 1.0) - m.predict(u, v, 0.0);
        assert!(
            (slope - s).abs() < 1e-9 * (1.0 + s.abs()),
            "({u},{v}) {slope} vs {s}"
        );
    }
}
