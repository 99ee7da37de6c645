//! Criterion benches of the hot paths (speed targets: docs/benchmarks.md).
//!
//! Everything runs on ONE thread (a 1-thread rayon pool) except `lwlr_exact_maps`, which runs on
//! two. Run: `cargo bench -p moma-core --bench core -- --warm-up-time 1 --measurement-time 3`.

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use moma_core::align::lwlr::{LwlrConfig, LwlrModel};
use moma_core::align::ssra::SsraConfig;
use moma_core::align::{AlignmentModel, Method, Sample, SampleSet};
use moma_core::metrics::DepthMetrics;
use moma_core::normalise::{Normalisation, NormalisationConfig, normalise};
use moma_core::{AlignOptions, CalibrationFrame, PredictionInput};
use moma_core::{ImageSize, Mask, MetricDepth, Prediction, PredictionKind};
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::hint::black_box;

fn samples(size: ImageSize, n: usize, seed: u64) -> SampleSet {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let samples = (0..n)
        .map(|_| {
            let u = rng.random_range(0..size.width) as f64;
            let v = rng.random_range(0..size.height) as f64;
            let pred = rng.random_range(0.3..1.5);
            let depth_m =
                pred * (0.9 + 2e-4 * u - 1e-4 * v) + 0.1 + rng.random_range(-0.003..0.003);
            Sample {
                u,
                v,
                pred,
                target: depth_m,
            }
        })
        .collect();
    SampleSet {
        space: moma_core::normalise::AlignSpace::Depth,
        image_size: size,
        samples,
    }
}

fn zhat(size: ImageSize) -> Array2<f32> {
    Array2::from_shape_fn(size.shape(), |(v, u)| {
        0.4 + ((u * 7 + v * 13) % 1000) as f32 * 1e-3
    })
}

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool")
}

fn bench_fits(c: &mut Criterion) {
    let p1 = pool(1);
    let size = ImageSize::new(640, 480);
    let mut g = c.benchmark_group("fit");
    for n in [100usize, 3000] {
        let set = samples(size, n, n as u64);
        g.throughput(Throughput::Elements(n as u64));
        let ssra = Method::Ssra(SsraConfig::default());
        g.bench_with_input(BenchmarkId::new("ssra", n), &set, |b, s| {
            p1.install(|| b.iter(|| ssra.fit(black_box(s)).unwrap()))
        });
        g.bench_with_input(BenchmarkId::new("gssa", n), &set, |b, s| {
            p1.install(|| b.iter(|| Method::Gssa.fit(black_box(s)).unwrap()))
        });
    }
    g.finish();
}

/// The error model's share of a calibration (target ≤ 5 ms on one core, docs/grasping.md): a whole SSRA
/// calibration on a 640×480 frame (normalise, sample, fit, error model), and the error-model
/// fit alone, side by side.
fn bench_error_model(c: &mut Criterion) {
    use moma_core::error_model::{DepthErrorModel, ResidualFrame};
    let p1 = pool(1);
    // a table at 0.8 m with 30 mm bumps; the prediction a compressed, tilted inverse depth
    let gt = Array2::from_shape_fn((480, 640), |(v, u)| {
        let (x, y) = ((u % 80) as f32 - 40.0, (v % 80) as f32 - 40.0);
        0.8 - 0.03 * (-(x * x + y * y) / 200.0).exp()
    });
    let pred = gt.mapv(|z| 1.0 / (0.9 * z + 0.02));
    // the aligned depth: the bumps at 80 % of their height (a relief factor to fit, and the
    // relief bands of fit step 1b to sum) and 3 mm too far
    let aligned = gt.mapv(|z| 0.8 - 0.8 * (0.8 - z) + 0.003);
    let gt_m = MetricDepth::new(gt.clone());
    let prediction = Prediction::new(pred, PredictionKind::RelativeDisparity);
    let config = moma_core::CalibrationConfig {
        method: Method::Ssra(SsraConfig::default()),
        normalisation: NormalisationConfig {
            method: Normalisation::Minmax,
            space: moma_core::AlignSpace::Inverse,
        },
        sampling: moma_core::sampling::SamplingConfig::default(),
        robust: None,
        workspace: None,
    };
    let mut g = c.benchmark_group("error_model");
    g.bench_function("calibrate_ssra_n100_640x480_1thread", |b| {
        p1.install(|| {
            b.iter(|| {
                moma_core::calibrate(
                    &[CalibrationFrame::new(black_box(&prediction), &gt_m)],
                    &config,
                )
                .unwrap()
            })
        })
    });
    // samples in the left half only: the calibration fits the distance part (fit step 5)
    let left = moma_core::Mask::from_vec(
        moma_core::ImageSize::new(640, 480),
        (0..480 * 640).map(|i| i % 640 < 320).collect(),
    )
    .unwrap();
    g.bench_function("calibrate_ssra_n100_640x480_left_half_1thread", |b| {
        p1.install(|| {
            b.iter(|| {
                moma_core::calibrate(
                    &[
                        CalibrationFrame::new(black_box(&prediction), &gt_m)
                            .sampled_in(Some(&left)),
                    ],
                    &config,
                )
                .unwrap()
            })
        })
    });
    g.bench_function("fit_640x480_1thread", |b| {
        let frame = ResidualFrame {
            aligned_m: aligned.view(),
            truth_m: gt.view(),
        };
        p1.install(|| b.iter(|| DepthErrorModel::fit(black_box(&[frame]), &[], 2.0).unwrap()))
    });
    // what every calibration adds to decide on the distance part, and what the part costs
    let cal = moma_core::calibrate(&[CalibrationFrame::new(&prediction, &gt_m)], &config).unwrap();
    g.bench_function("sample_reach_over_640x480_n100", |b| {
        b.iter(|| moma_core::sampling::sample_reach_over(black_box(&cal.samples), &[&gt_m]))
    });
    let uv = cal.samples.pixels_uv();
    g.bench_function("sample_distance_map_640x480_n100", |b| {
        b.iter(|| moma_core::sampling::sample_distance_map(480, 640, black_box(&uv)))
    });
    let distance = moma_core::sampling::sample_distance_map(480, 640, &uv);
    g.bench_function("fit_with_sample_distance_640x480_1thread", |b| {
        let frame = ResidualFrame {
            aligned_m: aligned.view(),
            truth_m: gt.view(),
        };
        p1.install(|| {
            b.iter(|| {
                DepthErrorModel::fit_with_sample_distance(
                    black_box(&[frame]),
                    &[],
                    2.0,
                    Some(distance.view()),
                )
                .unwrap()
            })
        })
    });
    // the height part a calibration adds (moma_core::height): the object pull on the bench's
    // table, whose 48 bumps stand 30 mm out of it (the samples on them are its objects), for
    // the global fit and the local one; and the heights of a frame's σ map and draws
    for (name, method) in [
        ("ssra", Method::Ssra(SsraConfig::default())),
        ("lwlr", Method::Lwlr(LwlrConfig::default())),
    ] {
        let config = moma_core::CalibrationConfig {
            method: method.clone(),
            ..config.clone()
        };
        let cal =
            moma_core::calibrate(&[CalibrationFrame::new(&prediction, &gt_m)], &config).unwrap();
        g.bench_function(format!("height_pull_{name}_n100_1thread"), |b| {
            b.iter(|| {
                moma_core::height::object_scale_pull(
                    &method,
                    &cal.model,
                    moma_core::AlignSpace::Inverse,
                    black_box(&cal.samples),
                    &[(0..cal.samples.samples.len(), &gt_m)],
                )
            })
        });
    }
    g.bench_function("height_above_plane_640x480", |b| {
        b.iter(|| moma_core::height::height_above_plane(black_box(aligned.view())).unwrap())
    });
    g.finish();
}

fn bench_apply(c: &mut Criterion) {
    let p1 = pool(1);
    let mut g = c.benchmark_group("apply");
    for (w, h) in [(640usize, 480usize), (1280, 720)] {
        let size = ImageSize::new(w, h);
        let set = samples(size, 100, 1);
        let z = zhat(size);
        let mut out = Array2::<f32>::zeros(size.shape());
        g.throughput(Throughput::Elements((w * h) as u64));
        let id = format!("{w}x{h}");
        let (ssra, _) = Method::Ssra(SsraConfig::default()).fit(&set).unwrap();
        g.bench_function(BenchmarkId::new("ssra", &id), |b| {
            p1.install(|| {
                b.iter(|| {
                    ssra.apply_into(black_box(z.view()), &mut out.view_mut())
                        .unwrap()
                })
            })
        });
        let (gssa, _) = Method::Gssa.fit(&set).unwrap();
        g.bench_function(BenchmarkId::new("gssa", &id), |b| {
            p1.install(|| {
                b.iter(|| {
                    gssa.apply_into(black_box(z.view()), &mut out.view_mut())
                        .unwrap()
                })
            })
        });
        let (lwlr, _) = Method::Lwlr(LwlrConfig::default()).fit(&set).unwrap();
        g.bench_function(BenchmarkId::new("lwlr_maps_cached", &id), |b| {
            p1.install(|| {
                b.iter(|| {
                    lwlr.apply_into(black_box(z.view()), &mut out.view_mut())
                        .unwrap()
                })
            })
        });
    }
    g.finish();
}

/// Samples on a planar scale field plus a Gaussian bump (σ = 60 px), so that the local
/// correction is kept (no fallback).
fn bumpy_samples(size: ImageSize, n: usize, seed: u64) -> SampleSet {
    let mut set = samples(size, n, seed);
    for s in &mut set.samples {
        let bump = 0.1 * (-((s.u - 400.0).powi(2) + (s.v - 240.0).powi(2)) / 7200.0).exp();
        s.target += s.pred * bump;
    }
    set
}

fn bench_local(c: &mut Criterion) {
    let p1 = pool(1);
    let size = ImageSize::new(640, 480);
    let set = bumpy_samples(size, 100, 11);
    let mut g = c.benchmark_group("local");
    for name in ["ssra-local", "gssa-local"] {
        let method: Method = name.parse().unwrap();
        g.bench_function(BenchmarkId::new("fit_incl_cv_n100", name), |b| {
            p1.install(|| b.iter(|| method.fit(black_box(&set)).unwrap()))
        });
    }
    let method: Method = "ssra-local".parse().unwrap();
    let (model, _) = method.fit(&set).unwrap();
    match &model {
        AlignmentModel::Local(m) => assert!(!m.fallback, "bench scene must keep the correction"),
        _ => unreachable!(),
    }
    let z = zhat(size);
    let mut out = Array2::<f32>::zeros(size.shape());
    g.throughput(Throughput::Elements(size.pixels() as u64));
    g.bench_function("apply_ssra_local_640x480_maps_cached", |b| {
        p1.install(|| {
            b.iter(|| {
                model
                    .apply_into(black_box(z.view()), &mut out.view_mut())
                    .unwrap()
            })
        })
    });
    g.bench_function("fit_and_first_apply_ssra_local_640x480_n100", |b| {
        p1.install(|| {
            b.iter(|| {
                let (m, _) = method.fit(black_box(&set)).unwrap();
                m.apply_into(z.view(), &mut out.view_mut()).unwrap()
            })
        })
    });
    g.sample_size(10);
    g.bench_function("fit_auto_n100", |b| {
        p1.install(|| {
            b.iter(|| {
                Method::Auto(Default::default())
                    .fit(black_box(&set))
                    .unwrap()
            })
        })
    });
    // the per-frame cross-validation (plain leave-one-out, relative error, finer
    // bandwidths and one more ridge), at 640×480 and 640×360; limit 10 ms on one core
    let per_frame = Method::Auto(moma_core::policy::local_config(
        moma_core::policy::Protocol::PerFrame,
    ));
    let set_360 = bumpy_samples(ImageSize::new(640, 360), 100, 11);
    for (name, s) in [("640x480", &set), ("640x360", &set_360)] {
        g.bench_function(BenchmarkId::new("fit_auto_per_frame_n100", name), |b| {
            p1.install(|| b.iter(|| per_frame.fit(black_box(s)).unwrap()))
        });
    }
    g.finish();
}

fn lwlr_model(cfg: LwlrConfig, size: ImageSize, n: usize) -> LwlrModel {
    match Method::Lwlr(cfg).fit(&samples(size, n, 7)).unwrap().0 {
        AlignmentModel::Lwlr(m) => m,
        _ => unreachable!(),
    }
}

fn bench_lwlr(c: &mut Criterion) {
    let size = ImageSize::new(640, 480);
    let mut g = c.benchmark_group("lwlr_maps");
    g.throughput(Throughput::Elements(size.pixels() as u64));
    g.sample_size(10);
    let exact = lwlr_model(LwlrConfig::exact(), size, 100);
    let p2 = pool(2);
    g.bench_function("exact_640x480_n100_2threads", |b| {
        p2.install(|| b.iter(|| black_box(exact.compute_maps())))
    });
    let p1 = pool(1);
    g.bench_function("exact_640x480_n100_1thread", |b| {
        p1.install(|| b.iter(|| black_box(exact.compute_maps())))
    });
    let grid = lwlr_model(LwlrConfig::faithful(), size, 100);
    g.bench_function("grid_640x480_n100_1thread", |b| {
        p1.install(|| b.iter(|| black_box(grid.compute_maps())))
    });
    g.finish();
}

fn bench_metrics(c: &mut Criterion) {
    let p1 = pool(1);
    let size = ImageSize::new(640, 480);
    let gt = MetricDepth::new(Array2::from_shape_fn(size.shape(), |(v, u)| {
        if (u + v) % 17 == 0 {
            0.0
        } else {
            0.5 + ((u * 3 + v) % 500) as f32 * 1e-3
        }
    }));
    let pred = MetricDepth::new(gt.depth_m.mapv(|z| z * 1.02 + 0.001));
    let mask = Mask::new(Array2::from_shape_fn(size.shape(), |(v, u)| {
        (u / 40 + v / 40) % 2 == 0
    }));
    let mut g = c.benchmark_group("metrics");
    g.throughput(Throughput::Elements(size.pixels() as u64));
    g.bench_function("640x480", |b| {
        p1.install(|| b.iter(|| DepthMetrics::compute(black_box(&pred), &gt, None).unwrap()))
    });
    g.bench_function("640x480_masked", |b| {
        p1.install(|| b.iter(|| DepthMetrics::compute(black_box(&pred), &gt, Some(&mask)).unwrap()))
    });
    g.finish();
}

fn bench_normalise(c: &mut Criterion) {
    let p1 = pool(1);
    let size = ImageSize::new(640, 480);
    let pred = Prediction::new(zhat(size), PredictionKind::RelativeDisparity);
    let mut g = c.benchmark_group("normalise");
    g.throughput(Throughput::Elements(size.pixels() as u64));
    for m in [
        Normalisation::Minmax,
        Normalisation::MinmaxUnit,
        Normalisation::Median,
    ] {
        let cfg = NormalisationConfig {
            method: m,
            space: moma_core::AlignSpace::Depth,
        };
        g.bench_function(format!("{m:?}_640x480"), |b| {
            p1.install(|| b.iter(|| normalise(black_box(&pred), &cfg, None).unwrap()))
        });
    }
    // the min-max forms' check for isolated extremes, one more pass per frame beside the
    // normalisation above (what `Calibration::align` adds to every frame's report)
    let cfg = NormalisationConfig {
        method: Normalisation::MinmaxUnit,
        space: moma_core::AlignSpace::Inverse,
    };
    g.bench_function("isolated_extremes_640x480", |b| {
        b.iter(|| {
            moma_core::normalise::isolated_extremes(
                black_box(pred.values.view()),
                pred.kind,
                &cfg,
                None,
            )
        })
    });
    g.finish();
}

/// The whole run-time step `Calibration::align` on 640×480 (normalisation + model + reciprocal
/// in inverse space): the fused path from a borrowed view (into a buffer, and `aligned`
/// allocating its output) against the unfused steps (`normalise`, then `align` of the normalised
/// map).
fn bench_align(c: &mut Criterion) {
    let p1 = pool(1);
    let size = ImageSize::new(640, 480);
    let gt = MetricDepth::new(Array2::from_shape_fn(size.shape(), |(v, u)| {
        0.5 + ((u * 3 + v) % 500) as f32 * 1e-3
    }));
    let kind = PredictionKind::RelativeDisparity;
    let pred = Prediction::new(gt.depth_m.mapv(|z| 2.0 / z - 0.5), kind);
    let mut out = Array2::<f32>::zeros(size.shape());
    let mut g = c.benchmark_group("align");
    g.throughput(Throughput::Elements(size.pixels() as u64));
    for (name, method) in [
        ("ssra", Method::Ssra(SsraConfig::default())),
        ("gssa", Method::Gssa),
    ] {
        for space in moma_core::AlignSpace::ALL {
            let config = moma_core::CalibrationConfig {
                method: method.clone(),
                normalisation: NormalisationConfig {
                    method: Normalisation::Minmax,
                    space,
                },
                sampling: moma_core::sampling::SamplingConfig::default(),
                robust: None,
                workspace: None,
            };
            let cal = moma_core::calibrate(&[CalibrationFrame::new(&pred, &gt)], &config).unwrap();
            let id = format!("{name}_{space}_640x480");
            g.bench_function(BenchmarkId::new("fused_into", &id), |b| {
                p1.install(|| {
                    b.iter(|| {
                        cal.align(
                            PredictionInput::view(black_box(pred.values.view()), kind),
                            &AlignOptions::default(),
                            &mut out.view_mut(),
                        )
                        .unwrap()
                    })
                })
            });
            g.bench_function(BenchmarkId::new("fused_alloc", &id), |b| {
                p1.install(|| {
                    b.iter(|| {
                        cal.aligned(
                            PredictionInput::view(black_box(pred.values.view()), kind),
                            &AlignOptions::default(),
                        )
                        .unwrap()
                        .depth
                    })
                })
            });
            g.bench_function(BenchmarkId::new("unfused_into", &id), |b| {
                p1.install(|| {
                    b.iter(|| {
                        let n = cal.normalise(black_box(&pred)).unwrap();
                        let n = PredictionInput::normalised(&n, kind);
                        cal.align(n, &AlignOptions::default(), &mut out.view_mut())
                            .unwrap()
                    })
                })
            });
        }
    }
    g.finish();
}

/// Drawing n = 100 calibration pixels at 640×480 and 1280×720 (the shared sets' sizes): MOMA's
/// protocol (any valid pixel) against the edge margin of 3 px, which adds the depth-edge map and
/// its dilation (one pass over the image each).
fn bench_sampling(c: &mut Criterion) {
    use moma_core::sampling::{SamplingConfig, sample_pixels};
    let p1 = pool(1);
    let mut g = c.benchmark_group("sampling");
    for size in [ImageSize::new(640, 480), ImageSize::new(1280, 720)] {
        // a table with a box 10 cm nearer and a few holes
        let (w, h) = (size.width, size.height);
        let gt = MetricDepth::new(Array2::from_shape_fn(size.shape(), |(v, u)| {
            if (u * 31 + v * 17) % 997 == 0 {
                0.0
            } else if (w / 4..w / 2).contains(&u) && (h / 3..2 * h / 3).contains(&v) {
                0.8
            } else {
                0.9 + 1e-4 * v as f32
            }
        }));
        g.throughput(Throughput::Elements(size.pixels() as u64));
        for margin in [0u32, 3] {
            let cfg = SamplingConfig {
                n: 100,
                edge_margin_px: margin,
                ..Default::default()
            };
            g.bench_function(format!("random_n100_margin{margin}_{w}x{h}"), |b| {
                p1.install(|| b.iter(|| sample_pixels(black_box(&gt), &cfg, None).unwrap()))
            });
        }
    }
    g.finish();
}

criterion_group!(
    benches,
    bench_error_model,
    bench_sampling,
    bench_align,
    bench_fits,
    bench_apply,
    bench_lwlr,
    bench_local,
    bench_metrics,
    bench_normalise
);
criterion_main!(benches);
