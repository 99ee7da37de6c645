//! The CPU work around the network in `DepthModel::predict`, per 640×480 image: the
//! pre-processing (OpenCV INTER_CUBIC resize to 518×686, ImageNet normalisation) and the resize of
//! the network output back to 480×640 (bilinear, align_corners). On a GPU these run on the CPU
//! and add to every frame's latency.
//!
//! `cargo bench -p moma-depth --bench preprocess`

use criterion::{Criterion, criterion_group, criterion_main};
use moma_depth::preprocess::{preprocess, resize_bilinear_align_corners};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    // A seeded, textured 640×480 image (the arithmetic does not depend on the values).
    let mut state = 0x9e37_79b9_7f4a_7c15_u64;
    let rgb = image::RgbImage::from_fn(640, 480, |_, _| {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1);
        let v = (state >> 40) as u8;
        image::Rgb([v, v.wrapping_mul(3), v.wrapping_add(91)])
    });
    let net = ndarray::Array2::from_shape_fn((518, 686), |(y, x)| (y * 686 + x) as f32 * 1e-3);
    c.bench_function("preprocess 640x480 -> 3x518x686", |b| {
        b.iter(|| preprocess(black_box(&rgb), 518).unwrap())
    });
    c.bench_function("resize back 518x686 -> 480x640", |b| {
        b.iter(|| resize_bilinear_align_corners(&black_box(&net).view(), 480, 640))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
