//! Criterion benches of the robust fits (docs/method.md §2) at n = 100 samples, 640×480, 20 %
//! gross outliers, on ONE thread, next to the plain least-squares fit of the same method; each
//! kind with the default `auto` threshold and with the former fixed 0.01 m (`<kind>-fixed`).
//! Run: `cargo bench -p moma-core --bench robust -- --warm-up-time 1 --measurement-time 3`.

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use moma_core::ImageSize;
use moma_core::align::robust::{DEFAULT_THRESHOLD_M, Robust, RobustKind};
use moma_core::align::{Method, Sample, SampleSet};
use moma_core::normalise::AlignSpace;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::hint::black_box;

/// `n` samples of an SSRA-family scene with ±3 mm noise; every 5th sample's depth is off by
/// ±0.1–0.5 m.
fn samples(n: usize, seed: u64) -> SampleSet {
    let size = ImageSize::new(640, 480);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let samples = (0..n)
        .map(|k| {
            let u = rng.random_range(0..size.width) as f64;
            let v = rng.random_range(0..size.height) as f64;
            let pred = rng.random_range(0.3..1.5);
            let mut depth_m =
                pred * (0.9 + 2e-4 * u - 1e-4 * v) + 0.1 + rng.random_range(-0.003..0.003);
            if k.is_multiple_of(5) {
                let sign = if rng.random::<bool>() { 1.0 } else { -1.0 };
                depth_m += sign * rng.random_range(0.1..0.5);
            }
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

fn bench_robust(c: &mut Criterion) {
    let p1 = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("thread pool");
    let set = samples(100, 3);
    let mut g = c.benchmark_group("robust_fit_n100");
    for name in ["gssa", "ssra", "gssa-local", "ssra-local"] {
        let method: Method = name.parse().expect("method name");
        g.bench_with_input(BenchmarkId::new(name, "plain"), &set, |b, s| {
            p1.install(|| b.iter(|| method.fit(black_box(s)).expect("fit")))
        });
        // the default `auto` threshold, and the former fixed 0.01 m for comparison
        let runs = [RobustKind::Huber, RobustKind::Tukey, RobustKind::Ransac]
            .into_iter()
            .flat_map(|k| {
                [
                    (k.name().to_string(), Robust::new(k)),
                    (
                        format!("{}-fixed", k.name()),
                        Robust::new(k).with_threshold_m(DEFAULT_THRESHOLD_M),
                    ),
                ]
            });
        for (label, r) in runs {
            g.bench_with_input(BenchmarkId::new(name, label), &set, |b, s| {
                p1.install(|| {
                    b.iter(|| {
                        r.fit(&method, black_box(s), AlignSpace::Depth)
                            .expect("robust fit")
                    })
                })
            });
        }
    }
    g.finish();
}

criterion_group!(benches, bench_robust);
criterion_main!(benches);
