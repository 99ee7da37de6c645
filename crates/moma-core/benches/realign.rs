//! Criterion bench of per-frame re-alignment on static anchors at 640×480 (target: anchor
//! selection + re-alignment ≤ 3 ms per frame, one core).
//! Run: `cargo bench -p moma-core --bench realign -- --warm-up-time 1 --measurement-time 3`.

use criterion::{Criterion, criterion_group, criterion_main};
use moma_core::MetricDepth;
use moma_core::normalise::AlignSpace;
use moma_core::realign::{AnchorStore, RealignConfig, find_anchors, realign_in_place};
use moma_core::{AlignOptions, CalibrationFrame, PredictionInput};
use ndarray::{Array2, Array3};
use std::hint::black_box;

const W: usize = 640;
const H: usize = 480;

fn grey(u: usize, v: usize) -> f32 {
    let (x, y) = (u as f32, v as f32);
    110.0 + 35.0 * (x / 12.0).sin() * (y / 18.0).cos() + 25.0 * ((x + 2.0 * y) / 26.0).sin()
}

fn in_object(u: usize, v: usize) -> bool {
    (200..400).contains(&u) && (160..320).contains(&v)
}

fn bench(c: &mut Criterion) {
    let gt = MetricDepth::new(Array2::from_shape_fn((H, W), |(v, _)| {
        0.8 + 2.5e-4 * v as f32
    }));
    let calib_rgb = Array3::from_shape_fn((H, W, 3), |(v, u, _)| grey(u, v) as u8);
    // the test frame: brightness ×0.9 and an object covering a sixth of the image
    let frame_rgb = Array3::from_shape_fn((H, W, 3), |(v, u, _)| {
        if in_object(u, v) {
            200
        } else {
            (0.9 * grey(u, v)) as u8
        }
    });
    let calib_grey = moma_io::grey_half(calib_rgb.view()).unwrap();
    let store = AnchorStore::new(&calib_grey, &gt)
        .unwrap()
        .with_one_shot(&gt)
        .unwrap();
    // one-shot result off by a global scale
    let one_shot = gt.depth_m.mapv(|z| 1.05 * z);
    let config = RealignConfig::default();
    // re-alignment is single-threaded code (no rayon inside): one core; every frame's time
    // includes its RGB → grey conversion (moma_io::grey_half)
    {
        c.bench_function("find_anchors_640x480", |b| {
            b.iter(|| {
                let grey = moma_io::grey_half(black_box(frame_rgb.view())).unwrap();
                find_anchors(&store, &grey, &config.thresholds).unwrap()
            })
        });
        let mut depth = one_shot.clone();
        c.bench_function("realign_640x480", |b| {
            b.iter(|| {
                depth.assign(&one_shot);
                let grey = moma_io::grey_half(black_box(frame_rgb.view())).unwrap();
                let r = realign_in_place(
                    &store,
                    &grey,
                    AlignSpace::Inverse,
                    &config,
                    &mut depth.view_mut(),
                )
                .unwrap();
                assert!(r.accepted);
            })
        });
        // prediction-affine: selection, fit, held-out test through the model, and the model
        // applied to the corrected normalised map (GSSA, inverse space, min-max)
        let pred = moma_core::Prediction::new(
            gt.depth_m.mapv(|z| 2.0 / z),
            moma_core::PredictionKind::RelativeDisparity,
        );
        let cal = moma_core::calibrate(
            &[CalibrationFrame::new(&pred, &gt)],
            &moma_core::CalibrationConfig {
                method: moma_core::align::Method::Gssa,
                normalisation: moma_core::normalise::NormalisationConfig {
                    method: moma_core::normalise::Normalisation::Minmax,
                    space: AlignSpace::Inverse,
                },
                sampling: Default::default(),
                robust: None,
                workspace: None,
            },
        )
        .unwrap()
        .with_anchors(&calib_grey, &gt, &pred)
        .unwrap();
        // the frame: the background's prediction ×1.1 and shifted, an object nearer
        let frame_pred = moma_core::Prediction::new(
            Array2::from_shape_fn((H, W), |(v, u)| {
                let z = if in_object(u, v) {
                    0.6
                } else {
                    gt.depth_m[[v, u]]
                };
                2.2 / z + 0.1
            }),
            moma_core::PredictionKind::RelativeDisparity,
        );
        let normalised = cal.normalise(&frame_pred).unwrap();
        let pa = RealignConfig {
            model: moma_core::realign::CorrectionModel::PredictionAffine,
            ..config
        };
        let mut depth = cal
            .aligned(&frame_pred, &AlignOptions::default())
            .unwrap()
            .depth
            .depth_m;
        c.bench_function("realign_prediction_affine_640x480", |b| {
            b.iter(|| {
                let grey = moma_io::grey_half(black_box(frame_rgb.view())).unwrap();
                let r = cal
                    .align(
                        PredictionInput::normalised(&normalised, frame_pred.kind),
                        &AlignOptions::realigned(&grey, &pa),
                        &mut depth.view_mut(),
                    )
                    .unwrap();
                assert!(r.realign.as_ref().is_some_and(|r| r.accepted), "{r:?}");
            })
        });
        c.bench_function("one_shot_align_normalised_640x480", |b| {
            b.iter(|| {
                let n = PredictionInput::normalised(black_box(&normalised), frame_pred.kind);
                cal.align(n, &AlignOptions::default(), &mut depth.view_mut())
                    .unwrap()
            })
        });
        let mut depth = one_shot.clone();
        c.bench_function("copy_only_640x480", |b| {
            b.iter(|| depth.assign(black_box(&one_shot)))
        });
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
