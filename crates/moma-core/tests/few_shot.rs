//! Few-shot calibration (`calibrate` with several frames): one frame reproduces the one-shot steps exactly,
//! several frames average out per-frame noise, bad input is refused naming the frame.

mod common;

use moma_core::AlignOptions;
use moma_core::align::ssra::SsraConfig;
use moma_core::align::{Method, SampleSet};
use moma_core::normalise::{AlignSpace, Normalisation, normalise};
use moma_core::pipeline::{CalibrationConfig, CalibrationFrame, calibrate, frame_seed};
use moma_core::sampling::{SamplingConfig, sample_pixels};
use moma_core::{CoreError, ImageSize, Mask, MetricDepth, Prediction, PredictionKind};
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const SIZE: ImageSize = ImageSize::new(96, 72);

fn gt() -> MetricDepth {
    MetricDepth::new(common::tabletop_gt(SIZE))
}

/// A disparity-like prediction of `gt` with per-frame scale `a` and shift `b` and independent
/// per-pixel noise of relative size `noise` (seeded).
fn frame_pred(gt: &MetricDepth, a: f64, b: f64, noise: f64, seed: u64) -> Prediction {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let values = gt.depth_m.mapv(|z| {
        let e: f64 = (0..12).map(|_| rng.random::<f64>()).sum::<f64>() - 6.0;
        (a / f64::from(z) * (1.0 + noise * e) + b) as f32
    });
    Prediction::new(values, PredictionKind::RelativeDisparity)
}

fn config(method: Method, space: AlignSpace, norm: Normalisation, seed: u64) -> CalibrationConfig {
    common::calibration_config(method, norm, space, 60, seed)
}

/// One frame gives bit-identical results to `calibrate` and to the one-shot steps written out
/// by hand (sample with the seed, gather, fit), in both spaces and with a sample region.
#[test]
fn one_frame_is_the_one_shot_calibration() {
    let gt = gt();
    let pred = frame_pred(&gt, 2.0, -0.4, 0.01, 1);
    let region = Mask::new(Array2::from_shape_fn(SIZE.shape(), |(v, _)| v > 10));
    for (space, method) in [
        (AlignSpace::Depth, Method::Gssa),
        (AlignSpace::Inverse, Method::Gssa),
        (AlignSpace::Depth, Method::Ssra(SsraConfig::default())),
        (AlignSpace::Depth, Method::Lwlr(Default::default())),
    ] {
        let cfg = config(method.clone(), space, Normalisation::Minmax, 5);
        let few = calibrate(
            &[CalibrationFrame {
                pred: (&pred).into(),
                gt: &gt,
                sample_region: Some(&region),
            }],
            &cfg,
        )
        .unwrap();
        let one = calibrate(
            &[CalibrationFrame::new(&pred, &gt).sampled_in(Some(&region))],
            &cfg,
        )
        .unwrap();
        assert_eq!(few.model, one.model, "{method} in {space}");
        assert_eq!(few.samples, one.samples);
        assert_eq!(few.report.rms_residual_m, one.report.rms_residual_m);

        // The one-shot steps by hand.
        let map = normalise(&pred, &cfg.normalisation, None).unwrap();
        let pixels = sample_pixels(&gt, &cfg.sampling, Some(&region)).unwrap();
        let samples = SampleSet::gather(&map, &gt, &pixels).unwrap();
        assert_eq!(few.samples, samples);
        let fit_on = if space == AlignSpace::Inverse {
            let mut t = samples.clone();
            for s in &mut t.samples {
                s.target = 1.0 / s.target;
            }
            t
        } else {
            samples
        };
        let (model, _) = method.fit(&fit_on).unwrap();
        assert_eq!(few.model, model, "{method} in {space}");
    }
}

/// Frame i draws n samples with seed `frame_seed(seed, i)` inside its own region; the samples
/// are kept frame after frame.
#[test]
fn samples_are_drawn_per_frame_and_kept() {
    let gt = gt();
    let preds: Vec<Prediction> = (0..3)
        .map(|k| frame_pred(&gt, 2.0, -0.4, 0.01, 10 + k))
        .collect();
    let left = Mask::new(Array2::from_shape_fn(SIZE.shape(), |(_, u)| u < 40));
    let frames: Vec<CalibrationFrame<'_>> = preds
        .iter()
        .enumerate()
        .map(|(k, p)| CalibrationFrame {
            pred: p.into(),
            gt: &gt,
            sample_region: (k == 1).then_some(&left),
        })
        .collect();
    let cfg = config(Method::Gssa, AlignSpace::Inverse, Normalisation::Minmax, 9);
    let cal = calibrate(&frames, &cfg).unwrap();
    assert_eq!(cal.samples.samples.len(), 3 * 60);
    assert_eq!(cal.report.n_used, 3 * 60);
    assert_eq!(frame_seed(9, 0), 9);
    for (k, chunk) in cal.samples.samples.chunks(60).enumerate() {
        let sampling = SamplingConfig {
            seed: frame_seed(9, k),
            ..cfg.sampling
        };
        let pixels = sample_pixels(&gt, &sampling, frames[k].sample_region).unwrap();
        let map = normalise(&preds[k], &cfg.normalisation, None).unwrap();
        let expected = SampleSet::gather(&map, &gt, &pixels).unwrap();
        assert_eq!(chunk, expected.samples.as_slice(), "frame {k}");
        if k == 1 {
            assert!(chunk.iter().all(|s| s.u < 40.0));
        }
    }
    // Different frames draw different pixels.
    let pos = |k: usize| -> Vec<(f64, f64)> {
        cal.samples.samples[k * 60..(k + 1) * 60]
            .iter()
            .map(|s| (s.u, s.v))
            .collect()
    };
    assert_ne!(pos(0), pos(2));
    // Deterministic.
    assert_eq!(calibrate(&frames, &cfg).unwrap().model, cal.model);
}

/// Each frame's depth-model output has its own scale/shift error (independent across frames,
/// relative sd 5 %) and pixel noise; the truth is the mean model. Calibrating on 3 frames
/// averages the per-frame errors: on held-out truth its MAE over 24 trials is clearly below
/// 1-frame calibration's (expected ratio about 1/√3 for the scale part).
#[test]
fn three_frames_beat_one_on_held_out_truth() {
    let gt = gt();
    let truth = frame_pred(&gt, 2.0, 0.0, 0.0, 0);
    let mut rng = ChaCha8Rng::seed_from_u64(77);
    let (mut mae1, mut mae3) = (0.0, 0.0);
    let trials = 24;
    for t in 0..trials {
        let preds: Vec<Prediction> = (0..3)
            .map(|k| {
                let g: f64 = (0..12).map(|_| rng.random::<f64>()).sum::<f64>() - 6.0;
                frame_pred(&gt, 2.0 * (1.0 + 0.05 * g), 0.0, 0.005, 1000 * t + k)
            })
            .collect();
        let frames: Vec<CalibrationFrame<'_>> = preds
            .iter()
            .map(|p| CalibrationFrame {
                pred: p.into(),
                gt: &gt,
                sample_region: None,
            })
            .collect();
        let cfg = config(Method::Gssa, AlignSpace::Inverse, Normalisation::None, t);
        let mae = |n: usize| {
            let cal = calibrate(&frames[..n], &cfg).unwrap();
            let out = cal.aligned(&truth, &AlignOptions::default()).unwrap().depth;
            let err: f64 = out
                .depth_m
                .iter()
                .zip(&gt.depth_m)
                .map(|(a, b)| f64::from((a - b).abs()))
                .sum();
            err / SIZE.pixels() as f64
        };
        mae1 += mae(1) / trials as f64;
        mae3 += mae(3) / trials as f64;
    }
    assert!(
        mae3 < 0.75 * mae1,
        "3 frames: MAE {:.2} mm, 1 frame: {:.2} mm",
        mae3 * 1e3,
        mae1 * 1e3
    );
}

fn message(e: CoreError) -> String {
    e.to_string()
}

fn frame<'a>(pred: &'a Prediction, gt: &'a MetricDepth) -> CalibrationFrame<'a> {
    CalibrationFrame {
        pred: pred.into(),
        gt,
        sample_region: None,
    }
}

#[test]
fn bad_frames_are_refused_naming_the_frame() {
    let gt = gt();
    let pred = frame_pred(&gt, 2.0, -0.4, 0.01, 1);
    let cfg = config(Method::Gssa, AlignSpace::Inverse, Normalisation::Minmax, 0);
    let (pred, gt) = (&pred, &gt);

    // No frame.
    let e = message(calibrate(&[], &cfg).unwrap_err());
    assert!(e.contains("at least one frame"), "{e}");

    // A frame of another size.
    let small_gt = &MetricDepth::new(common::tabletop_gt(ImageSize::new(48, 36)));
    let small = &frame_pred(small_gt, 2.0, -0.4, 0.01, 2);
    let e = message(
        calibrate(
            &[frame(pred, gt), frame(pred, gt), frame(small, small_gt)],
            &cfg,
        )
        .unwrap_err(),
    );
    assert!(
        e.contains("frame 2") && e.contains("48x36") && e.contains("96x72"),
        "{e}"
    );

    // Ground truth of another size than its prediction (frame 1).
    let e = message(calibrate(&[frame(pred, gt), frame(pred, small_gt)], &cfg).unwrap_err());
    assert!(e.contains("frame 1") && e.contains("ground truth"), "{e}");

    // Kinds that differ.
    let depth = &Prediction::new(gt.depth_m.clone(), PredictionKind::MetricDepth);
    let e = message(calibrate(&[frame(pred, gt), frame(depth, gt)], &cfg).unwrap_err());
    assert!(
        e.contains("frame 1") && e.contains("'metric-depth'") && e.contains("'relative-disparity'"),
        "{e}"
    );

    // A frame without valid ground truth inside its region is named.
    let empty = &Mask::new(Array2::from_elem(SIZE.shape(), false));
    let e = message(
        calibrate(
            &[
                frame(pred, gt),
                CalibrationFrame {
                    pred: pred.into(),
                    gt,
                    sample_region: Some(empty),
                },
            ],
            &cfg,
        )
        .unwrap_err(),
    );
    assert!(e.contains("frame 1"), "{e}");

    // The sample limit holds for the frames' samples together (they are cross-validated
    // together): 3 × 4000 and 2 × 5001 are refused before any sampling.
    let many = |n: usize| CalibrationConfig {
        sampling: SamplingConfig { n, ..cfg.sampling },
        ..cfg.clone()
    };
    let three = [frame(pred, gt), frame(pred, gt), frame(pred, gt)];
    let e = message(calibrate(&three, &many(4000)).unwrap_err());
    assert!(
        e.contains("3 frames × 4000 samples = 12000") && e.contains("limit of 10000"),
        "{e}"
    );
    let e = message(calibrate(&three[..2], &many(5001)).unwrap_err());
    assert!(e.contains("2 frames × 5001 samples = 10002"), "{e}");
}
