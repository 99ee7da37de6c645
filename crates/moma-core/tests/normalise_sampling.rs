//! Normalisation formulas and sampling on tiny maps, with the bad-input paths.

use moma_core::normalise::{AlignSpace, Normalisation, NormalisationConfig, normalise};
use moma_core::sampling::{Pixel, SamplingConfig, SamplingStrategy, sample_pixels};
use moma_core::{CoreError, ImageSize, Mask, MetricDepth, Prediction, PredictionKind};
use ndarray::{Array2, array};
use proptest::prelude::*;

fn cfg(method: Normalisation) -> NormalisationConfig {
    NormalisationConfig {
        method,
        space: AlignSpace::Depth,
    }
}

/// A depth-like prediction whose values are any numbers (relative depth: no unit, no sign rule).
fn depth(a: Array2<f32>) -> Prediction {
    Prediction::new(a, PredictionKind::RelativeDepth)
}

fn close(a: &Array2<f32>, b: &Array2<f32>) -> bool {
    a.iter()
        .zip(b)
        .all(|(x, y)| (x.is_nan() && y.is_nan()) || (x - y).abs() < 1e-6)
}

#[test]
fn minmax_paper_formula() {
    // (z − 1)/(5 − 1) + 1
    let n = normalise(
        &depth(array![[1.0, 2.0], [3.0, 5.0]]),
        &cfg(Normalisation::Minmax),
        None,
    )
    .unwrap();
    assert!(
        close(&n.values, &array![[1.0, 1.25], [1.5, 2.0]]),
        "{:?}",
        n.values
    );
    assert_eq!((n.stats.min, n.stats.max, n.stats.n), (1.0, 5.0, 4));
    assert!(n.stats.median.is_nan());
}

#[test]
fn minmax_unit_formula() {
    let n = normalise(
        &depth(array![[1.0, 2.0], [3.0, 5.0]]),
        &cfg(Normalisation::MinmaxUnit),
        None,
    )
    .unwrap();
    assert!(close(&n.values, &array![[0.0, 0.25], [0.5, 1.0]]));
}

#[test]
fn median_formula_even_and_odd() {
    // values 1 2 3 5: m = 2.5, μ = (1.5 + .5 + .5 + 2.5)/4 = 1.25
    let n = normalise(
        &depth(array![[1.0, 2.0], [3.0, 5.0]]),
        &cfg(Normalisation::Median),
        None,
    )
    .unwrap();
    assert_eq!((n.stats.median, n.stats.mad), (2.5, 1.25));
    assert!(close(&n.values, &array![[-1.2, -0.4], [0.4, 2.0]]));
    // values 4 1 2: m = 2, μ = (2 + 1 + 0)/3 = 1
    let n = normalise(
        &depth(array![[4.0, 1.0, 2.0]]),
        &cfg(Normalisation::Median),
        None,
    )
    .unwrap();
    assert_eq!((n.stats.median, n.stats.mad), (2.0, 1.0));
    assert!(close(&n.values, &array![[2.0, -1.0, 0.0]]));
}

#[test]
fn none_is_identity() {
    let a = array![[1.0f32, -2.0], [3.5, 0.0]];
    let n = normalise(&depth(a.clone()), &cfg(Normalisation::None), None).unwrap();
    assert_eq!(n.values, a);
}

#[test]
fn a_metric_depth_at_or_behind_the_camera_is_no_prediction() {
    // 0 and negative metres: NaN (neither a sample nor an output pixel); relative depth keeps
    // every value
    let a = array![[1.0f32, -2.0], [3.5, 0.0]];
    let m = Prediction::new(a.clone(), PredictionKind::MetricDepth);
    let n = normalise(&m, &cfg(Normalisation::None), None).unwrap();
    assert_eq!((n.values[[0, 0]], n.values[[1, 0]]), (1.0, 3.5));
    assert!(
        n.values[[0, 1]].is_nan() && n.values[[1, 1]].is_nan(),
        "{}",
        n.values
    );
    // min-max over the positive values only: (z − 1)/(3.5 − 1)
    let u = normalise(&m, &cfg(Normalisation::MinmaxUnit), None).unwrap();
    assert_eq!((u.values[[0, 0]], u.values[[1, 0]]), (0.0, 1.0));
    assert_eq!(u.stats.min, 1.0);
    let r = normalise(&depth(a.clone()), &cfg(Normalisation::None), None).unwrap();
    assert_eq!(r.values, a);
    // no positive value: no valid pixel
    let none = Prediction::new(array![[0.0f32, -1.0]], PredictionKind::MetricDepth);
    assert!(matches!(
        normalise(&none, &cfg(Normalisation::Minmax), None),
        Err(CoreError::NoValidPixels(_))
    ));
}

#[test]
fn inverse_depth_is_inverted_and_nonpositive_is_nan() {
    // d = 1, 2, 4, 0 → z = 1, .5, .25, NaN; minmax-unit over valid: (z − .25)/.75
    let p = Prediction::new(
        array![[1.0, 2.0], [4.0, 0.0]],
        PredictionKind::RelativeDisparity,
    );
    let n = normalise(&p, &cfg(Normalisation::MinmaxUnit), None).unwrap();
    assert!(
        close(&n.values, &array![[1.0, 1.0 / 3.0], [0.0, f32::NAN]]),
        "{:?}",
        n.values
    );
    assert_eq!(n.stats.n, 3);
    // in inverse space the values are used as they are (0 included)
    let inv = NormalisationConfig {
        method: Normalisation::MinmaxUnit,
        space: AlignSpace::Inverse,
    };
    let n = normalise(&p, &inv, None).unwrap();
    assert!(close(&n.values, &array![[0.25, 0.5], [1.0, 0.0]]));
}

#[test]
fn statistics_over_region_applied_everywhere() {
    // region holds 2 and 3 only: minmax-unit (z − 2)/1
    let region = Mask::new(array![[false, true], [true, false]]);
    let n = normalise(
        &depth(array![[1.0, 2.0], [3.0, 5.0]]),
        &cfg(Normalisation::MinmaxUnit),
        Some(&region),
    )
    .unwrap();
    assert!(close(&n.values, &array![[-1.0, 0.0], [1.0, 3.0]]));
    assert_eq!(n.stats.n, 2);
}

#[test]
fn normalisation_errors() {
    let mut a = array![[1.0f32, 2.0, 3.0], [4.0, 5.0, 6.0]];
    a[[0, 2]] = f32::NAN;
    a[[1, 1]] = f32::INFINITY;
    let r = normalise(&depth(a.clone()), &cfg(Normalisation::Minmax), None);
    assert_eq!(
        r,
        Err(CoreError::NonFinitePrediction {
            count: 2,
            u: 2,
            v: 0,
            metric_depth: false,
        })
    );
    // the message's hint follows the kind: only a metric depth has a marker for "no value"
    let relative = r.unwrap_err().to_string();
    assert!(
        relative.contains("a relative prediction has a value at every pixel"),
        "{relative}"
    );
    let metric = Prediction::new(a, PredictionKind::MetricDepth);
    let r = normalise(&metric, &cfg(Normalisation::MinmaxUnit), None).unwrap_err();
    assert!(
        r.to_string()
            .contains("marks a pixel without a value by 0 or a negative number"),
        "{r}"
    );

    let constant = depth(Array2::from_elem((3, 4), 0.7));
    for m in [
        Normalisation::Minmax,
        Normalisation::MinmaxUnit,
        Normalisation::Median,
    ] {
        assert!(
            matches!(
                normalise(&constant, &cfg(m), None),
                Err(CoreError::Degenerate(_))
            ),
            "{m:?}"
        );
    }
    assert!(normalise(&constant, &cfg(Normalisation::None), None).is_ok());

    let p = depth(array![[1.0, 2.0], [3.0, 5.0]]);
    let empty = Mask::new(Array2::from_elem((2, 2), false));
    assert!(matches!(
        normalise(&p, &cfg(Normalisation::Minmax), Some(&empty)),
        Err(CoreError::NoValidPixels(_))
    ));
    let wrong = Mask::full(ImageSize::new(3, 2));
    assert!(matches!(
        normalise(&p, &cfg(Normalisation::Minmax), Some(&wrong)),
        Err(CoreError::SizeMismatch { .. })
    ));
    // inverse depth with no positive value
    let p = Prediction::new(array![[0.0, -1.0]], PredictionKind::RelativeDisparity);
    assert!(matches!(
        normalise(&p, &cfg(Normalisation::Minmax), None),
        Err(CoreError::NoValidPixels(_))
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn minmax_output_range_and_median_matches_sorting(vals in proptest::collection::vec(-50.0f32..50.0, 2..200)) {
        let n = vals.len();
        let a = Array2::from_shape_vec((1, n), vals.clone()).unwrap();
        let lo = vals.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = vals.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        prop_assume!(hi > lo);
        let u = normalise(&depth(a.clone()), &cfg(Normalisation::MinmaxUnit), None).unwrap();
        prop_assert!(u.values.iter().all(|&x| (-1e-6..=1.0 + 1e-6).contains(&x)));
        prop_assert!(u.values.iter().any(|&x| x.abs() < 1e-6) && u.values.iter().any(|&x| (x - 1.0).abs() < 1e-6));
        let m = normalise(&depth(a.clone()), &cfg(Normalisation::Minmax), None).unwrap();
        let lo64 = f64::from(lo);
        prop_assert!(m.values.iter().all(|&x| f64::from(x) >= lo64 - 1e-5 && f64::from(x) <= lo64 + 1.0 + 1e-5));
        // median by sorting
        let mut s: Vec<f64> = vals.iter().map(|&x| f64::from(x)).collect();
        s.sort_by(f64::total_cmp);
        let med = if n % 2 == 1 { s[n / 2] } else { 0.5 * (s[n / 2 - 1] + s[n / 2]) };
        let mad = s.iter().map(|x| (x - med).abs()).sum::<f64>() / n as f64;
        prop_assume!(mad > 0.0);
        let md = normalise(&depth(a), &cfg(Normalisation::Median), None).unwrap();
        prop_assert_eq!(md.stats.median, med);
        prop_assert!((md.stats.mad - mad).abs() <= 1e-9 * mad.max(1.0));
    }
}

// ---- sampling ----------------------------------------------------------------------------

fn gt_with_holes(w: usize, h: usize) -> MetricDepth {
    MetricDepth::new(Array2::from_shape_fn((h, w), |(v, u)| {
        if (u * 7 + v * 3) % 5 == 0 {
            0.0
        } else if (u + v) % 11 == 0 {
            f32::NAN
        } else {
            1.0 + u as f32 * 0.01
        }
    }))
}

#[test]
fn random_sampling_is_deterministic_valid_distinct() {
    let gt = gt_with_holes(64, 48);
    let c = SamplingConfig {
        strategy: SamplingStrategy::Random,
        n: 100,
        seed: 7,
        edge_margin_px: 0,
    };
    let a = sample_pixels(&gt, &c, None).unwrap();
    let b = sample_pixels(&gt, &c, None).unwrap();
    assert_eq!(a, b);
    assert_eq!(a.len(), 100);
    let other = sample_pixels(&gt, &SamplingConfig { seed: 8, ..c }, None).unwrap();
    assert_ne!(a, other);
    let mut set: Vec<Pixel> = a.clone();
    set.sort_by_key(|p| (p.v, p.u));
    set.dedup();
    assert_eq!(set.len(), 100, "duplicates");
    assert!(
        a.iter()
            .all(|p| moma_core::is_valid_depth(gt.depth_m[[p.v as usize, p.u as usize]]))
    );
}

#[test]
fn random_sampling_is_roughly_uniform() {
    // left half vs right half of a fully valid image: ~50 % each over many seeds
    let gt = MetricDepth::new(Array2::from_elem((40, 40), 1.0f32));
    let mut left = 0;
    for seed in 0..50 {
        let px = sample_pixels(
            &gt,
            &SamplingConfig {
                n: 100,
                seed,
                ..Default::default()
            },
            None,
        )
        .unwrap();
        left += px.iter().filter(|p| p.u < 20).count();
    }
    let frac = left as f64 / 5000.0;
    assert!((frac - 0.5).abs() < 0.03, "{frac}");
}

#[test]
fn random_sampling_restriction_and_count() {
    let gt = gt_with_holes(64, 48);
    let restrict = Mask::new(Array2::from_shape_fn((48, 64), |(v, u)| u < 10 && v < 8));
    let eligible = (0..8)
        .flat_map(|v| (0..10).map(move |u| (u, v)))
        .filter(|&(u, v)| moma_core::is_valid_depth(gt.depth_m[[v, u]]))
        .count();
    let px = sample_pixels(
        &gt,
        &SamplingConfig {
            n: 1000,
            ..Default::default()
        },
        Some(&restrict),
    )
    .unwrap();
    assert_eq!(
        px.len(),
        eligible,
        "returns all eligible pixels when n exceeds them"
    );
    assert!(px.iter().all(|p| p.u < 10 && p.v < 8));
    let px = sample_pixels(
        &gt,
        &SamplingConfig {
            n: 5,
            ..Default::default()
        },
        Some(&restrict),
    )
    .unwrap();
    assert_eq!(px.len(), 5);
    assert!(px.iter().all(|p| p.u < 10
        && p.v < 8
        && moma_core::is_valid_depth(gt.depth_m[[p.v as usize, p.u as usize]])));
}

#[test]
fn grid_sampling_places_nodes_evenly() {
    let gt = MetricDepth::new(Array2::from_elem((100, 100), 1.0f32));
    let px = sample_pixels(
        &gt,
        &SamplingConfig {
            strategy: SamplingStrategy::Grid,
            n: 100,
            seed: 0,
            edge_margin_px: 0,
        },
        None,
    )
    .unwrap();
    // nodes at (i + ½)·10 − ½ = 4.5 + 10 i; ties snap to the smaller coordinate → 4 + 10 i
    let want: Vec<Pixel> = (0..10)
        .flat_map(|j| {
            (0..10).map(move |i| Pixel {
                u: 4 + 10 * i,
                v: 4 + 10 * j,
            })
        })
        .collect();
    assert_eq!(px, want);
    // non-square n: ⌊√n⌋² nodes
    let px = sample_pixels(
        &gt,
        &SamplingConfig {
            strategy: SamplingStrategy::Grid,
            n: 50,
            seed: 0,
            edge_margin_px: 0,
        },
        None,
    )
    .unwrap();
    assert_eq!(px.len(), 49);
}

#[test]
fn grid_sampling_snaps_to_nearest_valid() {
    // valid only for u ≥ 6; 2×2 nodes at u, v ∈ {2, 7}
    let gt = MetricDepth::new(Array2::from_shape_fn((10, 10), |(_, u)| {
        if u >= 6 { 1.0 } else { 0.0 }
    }));
    let px = sample_pixels(
        &gt,
        &SamplingConfig {
            strategy: SamplingStrategy::Grid,
            n: 4,
            seed: 0,
            edge_margin_px: 0,
        },
        None,
    )
    .unwrap();
    assert_eq!(
        px,
        vec![
            Pixel { u: 6, v: 2 },
            Pixel { u: 7, v: 2 },
            Pixel { u: 6, v: 7 },
            Pixel { u: 7, v: 7 }
        ]
    );
    // a single valid pixel: every node snaps to it, kept once
    let mut one = Array2::from_elem((10, 10), 0.0f32);
    one[[9, 0]] = 2.0;
    let px = sample_pixels(
        &MetricDepth::new(one),
        &SamplingConfig {
            strategy: SamplingStrategy::Grid,
            n: 16,
            seed: 0,
            edge_margin_px: 0,
        },
        None,
    )
    .unwrap();
    assert_eq!(px, vec![Pixel { u: 0, v: 9 }]);
}

#[test]
fn sampling_errors() {
    let gt = gt_with_holes(8, 6);
    assert!(matches!(
        sample_pixels(
            &gt,
            &SamplingConfig {
                n: 0,
                ..Default::default()
            },
            None
        ),
        Err(CoreError::InvalidParameter(_))
    ));
    let invalid = MetricDepth::new(Array2::from_elem((6, 8), f32::NAN));
    for strategy in [SamplingStrategy::Random, SamplingStrategy::Grid] {
        let c = SamplingConfig {
            strategy,
            ..Default::default()
        };
        assert!(matches!(
            sample_pixels(&invalid, &c, None),
            Err(CoreError::NoValidPixels(_))
        ));
        let empty = Mask::new(Array2::from_elem((6, 8), false));
        assert!(matches!(
            sample_pixels(&gt, &c, Some(&empty)),
            Err(CoreError::NoValidPixels(_))
        ));
    }
    let wrong = Mask::full(ImageSize::new(6, 8));
    assert!(matches!(
        sample_pixels(&gt, &SamplingConfig::default(), Some(&wrong)),
        Err(CoreError::SizeMismatch { .. })
    ));
}

#[test]
fn huge_sample_counts_are_refused_not_overflowed() {
    use moma_core::sampling::MAX_SAMPLES;
    let gt = gt_with_holes(8, 6);
    for strategy in [SamplingStrategy::Random, SamplingStrategy::Grid] {
        // The limit itself is accepted (every valid pixel is returned, as for any n ≥ valid).
        let c = SamplingConfig {
            strategy,
            n: MAX_SAMPLES,
            seed: 0,
            edge_margin_px: 0,
        };
        assert!(!sample_pixels(&gt, &c, None).unwrap().is_empty());
        // Above it, and at usize::MAX (whose grid k·k would overflow), a clear error.
        for n in [MAX_SAMPLES + 1, usize::MAX] {
            let e = sample_pixels(&gt, &SamplingConfig { n, ..c }, None)
                .unwrap_err()
                .to_string();
            assert!(
                e.contains(&n.to_string()) && e.contains("exceeds the limit of 10000 ("),
                "{e}"
            );
        }
    }
}

/// A 40 × 30 scene for the edge margin: a table at 1 m rising steeply but continuously to the
/// right (adjacent pixels differ by 2 %, below the 3 % jump), a box 10 cm nearer, a one-pixel
/// hole and a 4 % step.
fn edge_scene() -> MetricDepth {
    let mut z = Array2::from_shape_fn((30, 40), |(_, u)| {
        if u < 30 {
            1.0f32
        } else {
            1.02f32.powi(u as i32 - 29)
        }
    });
    for v in 5..12 {
        for u in 6..14 {
            z[[v, u]] = 0.9;
        }
    }
    z[[20, 8]] = 0.0;
    for v in 15..30 {
        for u in 18..24 {
            z[[v, u]] = 0.96;
        }
    }
    MetricDepth::new(z)
}

/// The eligible set by brute force, independently of the library: valid pixels with no
/// "edge" pixel (invalid, or a 4-neighbour invalid or off by more than 3 % of the nearer depth)
/// within Chebyshev distance r.
fn interior_by_brute_force(gt: &MetricDepth, r: i64) -> Vec<Pixel> {
    let z = &gt.depth_m;
    let (h, w) = (z.nrows() as i64, z.ncols() as i64);
    let ok = |v: i64, u: i64| z[[v as usize, u as usize]] > 0.0;
    let edge = |v: i64, u: i64| {
        if !ok(v, u) {
            return true;
        }
        let a = z[[v as usize, u as usize]];
        [(0, 1), (1, 0), (0, -1), (-1, 0)].iter().any(|&(dv, du)| {
            let (vv, uu) = (v + dv, u + du);
            (0..h).contains(&vv)
                && (0..w).contains(&uu)
                && (!ok(vv, uu)
                    || (a - z[[vv as usize, uu as usize]]).abs()
                        > 0.03 * a.min(z[[vv as usize, uu as usize]]))
        })
    };
    let mut out = Vec::new();
    for v in 0..h {
        for u in 0..w {
            let near = (v - r..=v + r).any(|vv| {
                (u - r..=u + r)
                    .any(|uu| (0..h).contains(&vv) && (0..w).contains(&uu) && edge(vv, uu))
            });
            if ok(v, u) && !near {
                out.push(Pixel {
                    u: u as u32,
                    v: v as u32,
                });
            }
        }
    }
    out
}

#[test]
fn edge_margin_keeps_exactly_the_pixels_away_from_depth_discontinuities() {
    let gt = edge_scene();
    let all = |edge_margin_px| SamplingConfig {
        n: 10_000,
        edge_margin_px,
        ..Default::default()
    };
    // margin 0 is MOMA's protocol: every valid pixel, and the same draw for a seed
    assert_eq!(
        sample_pixels(&gt, &all(0), None).unwrap().len(),
        30 * 40 - 1
    );
    let c100 = SamplingConfig {
        n: 100,
        seed: 5,
        ..Default::default()
    };
    assert_eq!(
        sample_pixels(&gt, &c100, None).unwrap(),
        sample_pixels(
            &gt,
            &SamplingConfig {
                edge_margin_px: 0,
                ..c100
            },
            None
        )
        .unwrap()
    );
    // the edge map itself: invalid pixels, and both sides of every jump
    let edges = moma_core::sampling::depth_edges(&gt);
    // the pixels a map leaves unmarked, row-major
    let unmarked = |map: &Array2<bool>| -> Vec<Pixel> {
        map.indexed_iter()
            .filter(|(_, marked)| !**marked)
            .map(|((v, u), _)| Pixel {
                u: u as u32,
                v: v as u32,
            })
            .collect()
    };
    assert_eq!(unmarked(&edges), interior_by_brute_force(&gt, 0));
    assert!(edges[[20, 8]] && edges[[20, 9]] && edges[[5, 6]] && edges[[5, 5]]);
    for r in [1u32, 2, 3, 6] {
        let mut got = sample_pixels(&gt, &all(r), None).unwrap();
        got.sort_by_key(|p| (p.v, p.u));
        let want = interior_by_brute_force(&gt, i64::from(r));
        assert_eq!(got, want, "margin {r}");
        // the band near the edges is the rest of the valid pixels
        let near = moma_core::sampling::near_depth_edges(&gt, r);
        assert_eq!(unmarked(&near), want, "band {r}");
        // the continuous 2 %-per-pixel slope is no edge: its interior pixels stay eligible
        assert!(got.contains(&Pixel { u: 35, v: 3 }), "margin {r}");
        // the 4 % step (box at 0.96 m) is one
        assert!(!got.contains(&Pixel { u: 18, v: 25 }), "margin {r}");
    }
    // the draw stays seeded, and inside the margin, for both strategies
    let interior = interior_by_brute_force(&gt, 2);
    for strategy in [SamplingStrategy::Random, SamplingStrategy::Grid] {
        let c = SamplingConfig {
            strategy,
            n: 49,
            seed: 7,
            edge_margin_px: 2,
        };
        let px = sample_pixels(&gt, &c, None).unwrap();
        assert!(
            px.len() >= 40 && px.iter().all(|p| interior.contains(p)),
            "{strategy}"
        );
        assert_eq!(px, sample_pixels(&gt, &c, None).unwrap());
    }
    // with a mask: both restrictions apply
    let left = Mask::new(Array2::from_shape_fn((30, 40), |(_, u)| u < 20));
    let px = sample_pixels(&gt, &all(2), Some(&left)).unwrap();
    assert_eq!(px.len(), interior.iter().filter(|p| p.u < 20).count());
}

#[test]
fn an_edge_margin_that_leaves_no_pixel_is_an_error_naming_it() {
    let gt = edge_scene();
    for margin in [20u32, u32::MAX] {
        let e = sample_pixels(
            &gt,
            &SamplingConfig {
                edge_margin_px: margin,
                ..Default::default()
            },
            None,
        )
        .unwrap_err();
        assert!(matches!(e, CoreError::NoValidPixels(_)), "{e:?}");
        assert!(
            e.to_string()
                .contains(&format!("edge margin of {margin} px")),
            "{e}"
        );
    }
    // an all-invalid map keeps its own error
    let invalid = MetricDepth::new(Array2::from_elem((6, 8), f32::NAN));
    let e = sample_pixels(
        &invalid,
        &SamplingConfig {
            edge_margin_px: 2,
            ..Default::default()
        },
        None,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("no valid depth"), "{e}");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]

    /// Any small map (holes, NaN, steps), any margin (also wider than the image), both
    /// strategies: no panic; the pixels drawn lie in the brute-force interior; an error only
    /// when that interior is empty.
    #[test]
    fn edge_margin_draws_only_interior_pixels(
        (h, w, vals) in (1usize..12, 1usize..12).prop_flat_map(|(h, w)| {
            (Just(h), Just(w), proptest::collection::vec(
                prop_oneof![Just(0.0f32), Just(f32::NAN), 0.5f32..2.0, Just(1.0f32)], h * w))
        }),
        margin in 0u32..8,
        n in 1usize..60,
        grid in any::<bool>(),
    ) {
        let gt = MetricDepth::new(Array2::from_shape_vec((h, w), vals).unwrap());
        let strategy = if grid { SamplingStrategy::Grid } else { SamplingStrategy::Random };
        let c = SamplingConfig { strategy, n, seed: 1, edge_margin_px: margin };
        // margin 0 is off: every valid pixel
        let interior = if margin == 0 {
            gt.depth_m.indexed_iter().filter(|(_, z)| **z > 0.0).map(|((v, u), _)| Pixel { u: u as u32, v: v as u32 }).collect()
        } else {
            interior_by_brute_force(&gt, i64::from(margin))
        };
        match sample_pixels(&gt, &c, None) {
            Ok(px) => {
                prop_assert!(!px.is_empty());
                prop_assert!(px.iter().all(|p| interior.contains(p)));
            }
            Err(e) => {
                prop_assert!(interior.is_empty(), "{e}");
                prop_assert!(matches!(e, CoreError::NoValidPixels(_)), "{e:?}");
            }
        }
    }

    /// Piecewise-constant scenes (blocks of a few levels, some 1 % apart: no edge, some 10 %:
    /// an edge, an occasional hole) up to 40 × 40, so that interiors exist: with n above the
    /// pixel count the draw is exactly the brute-force interior, whatever the margin.
    #[test]
    fn edge_margin_keeps_exactly_the_interior_of_block_scenes(
        (h, w, bh, bw, levels) in (2usize..40, 2usize..40, 1usize..15, 1usize..15)
            .prop_flat_map(|(h, w, bh, bw)| {
                let blocks = h.div_ceil(bh) * w.div_ceil(bw);
                (Just(h), Just(w), Just(bh), Just(bw), proptest::collection::vec(
                    prop_oneof![4 => Just(1.0f32), 4 => Just(1.01f32), 2 => Just(1.1f32), 1 => Just(0.0f32)],
                    blocks))
            }),
        margin in 1u32..6,
    ) {
        let cols = w.div_ceil(bw);
        let gt = MetricDepth::new(Array2::from_shape_fn((h, w), |(v, u)| levels[(v / bh) * cols + u / bw]));
        let interior = interior_by_brute_force(&gt, i64::from(margin));
        let c = SamplingConfig { n: h * w + 1, edge_margin_px: margin, ..Default::default() };
        match sample_pixels(&gt, &c, None) {
            Ok(mut px) => {
                px.sort_by_key(|p| (p.v, p.u));
                prop_assert_eq!(px, interior);
            }
            Err(e) => {
                prop_assert!(interior.is_empty(), "{e}");
            }
        }
    }
}
