//! `evaluate_few_shot` (`moma eval --calib-frames K,...`) against the library calibration written
//! out by hand, the `variant` column, and sets with too few frames.

mod common;

use common::*;
use moma_core::AlignOptions;
use moma_core::metrics::DepthMetrics;
use moma_core::normalise::{AlignSpace, Normalisation, NormalisationConfig};
use moma_core::pipeline::{CalibrationConfig, CalibrationFrame, calibrate};
use moma_core::sampling::SamplingConfig;
use moma_eval::EvalError;
use moma_eval::protocol::{EvalConfig, EvalNote, JsonRow, evaluate, evaluate_few_shot};
use moma_eval::report::{contract_json, eval_csv, eval_table, eval_table_with_notes};

fn config(methods: &[&str], seeds: usize) -> EvalConfig {
    EvalConfig {
        methods: methods.iter().map(|s| s.parse().unwrap()).collect(),
        norms: vec![Normalisation::Minmax],
        samples: 30,
        seeds,
        ..Default::default()
    }
}

/// Every K scores the same frames (after the largest K); each row's MAE is that of
/// `calibrate` on the first K frames, applied and scored by hand.
#[test]
fn every_k_scores_the_same_frames_with_the_library_calibration() {
    let set = set(6);
    let preds = preds(6);
    let cfg = config(&["gssa", "lwlr"], 3);
    let rows = evaluate_few_shot(&set, &preds, &cfg, &[1, 2, 3]).unwrap();
    assert_eq!(rows.len(), 6);
    let variants: Vec<&str> = rows.iter().map(|r| r.variant.as_str()).collect();
    assert_eq!(
        variants,
        [
            "one-shot",
            "one-shot",
            "few-shot-2",
            "few-shot-2",
            "few-shot-3",
            "few-shot-3"
        ]
    );
    for r in &rows {
        assert_eq!(r.eval_frames, 3);
        let ids: Vec<&str> = r.frames.iter().map(|f| f.frame.as_str()).collect();
        assert_eq!(ids, ["f3", "f4", "f5"], "{} {}", r.method, r.variant);
    }
    assert_eq!(rows[0].calib_frame, "f0");
    assert_eq!(rows[4].calib_frame, "f0+f1+f2");

    for r in &rows {
        let k = match r.variant.as_str() {
            "one-shot" => 1,
            v => v.trim_start_matches("few-shot-").parse().unwrap(),
        };
        let method: moma_core::align::Method = r.method.parse().unwrap();
        let method = method.with_intrinsics(Some(intrinsics()));
        let maes: Vec<f64> = (0..3u64)
            .map(|seed| {
                let frames: Vec<CalibrationFrame<'_>> = (0..k)
                    .map(|i| CalibrationFrame {
                        pred: (&preds.maps[i]).into(),
                        gt: &set.frames[i].gt,
                        sample_region: None,
                    })
                    .collect();
                let cal = calibrate(
                    &frames,
                    &CalibrationConfig {
                        method: method.clone(),
                        normalisation: NormalisationConfig {
                            method: Normalisation::Minmax,
                            space: AlignSpace::Depth,
                        },
                        sampling: SamplingConfig {
                            n: 30,
                            seed,
                            ..Default::default()
                        },
                        robust: None,
                        workspace: None,
                    },
                )
                .unwrap();
                let per_frame: Vec<f64> = (3..6)
                    .map(|i| {
                        let out = cal
                            .aligned(&preds.maps[i], &AlignOptions::default())
                            .unwrap()
                            .depth;
                        let region = mask(i).data() & &set.frames[i].gt.depth_m.mapv(|z| z > 0.0);
                        DepthMetrics::compute(
                            &out,
                            &set.frames[i].gt,
                            Some(&moma_core::Mask::new(region)),
                        )
                        .unwrap()
                        .mae
                    })
                    .collect();
                per_frame.iter().sum::<f64>() / 3.0
            })
            .collect();
        let mean = maes.iter().sum::<f64>() / 3.0;
        assert!(
            (r.per_image.mae.mean - mean).abs() < 1e-9,
            "{} {}: eval {} vs by hand {}",
            r.method,
            r.variant,
            r.per_image.mae.mean,
            mean
        );
    }
    // More frames, more samples, less per-frame distortion: not worse here.
    assert!(rows[4].per_image.mae.mean <= rows[0].per_image.mae.mean * 1.05);
}

/// Without --calib-frames the rows are the one-shot protocol, labelled `one-shot`; the JSON
/// contract has `variant` right after `method`, the tables a variant column.
#[test]
fn one_shot_rows_carry_the_variant_everywhere() {
    let set = set(4);
    let preds = preds(4);
    let rows = evaluate(&set, &preds, &config(&["gssa"], 2)).unwrap();
    assert_eq!(rows[0].variant, "one-shot");
    assert_eq!(rows[0].eval_frames, 3);
    let json = contract_json(&rows).unwrap();
    let (m, v, n) = (
        json.find("\"method\"").unwrap(),
        json.find("\"variant\"").unwrap(),
        json.find("\"norm\"").unwrap(),
    );
    assert!(m < v && v < n, "{json}");
    let parsed: Vec<JsonRow> = serde_json::from_str(&json).unwrap();
    assert_eq!(parsed[0].variant, "one-shot");
    let table = eval_table(&rows, false);
    assert_eq!(&table.headers[..4], ["set", "method", "variant", "norm"]);
    assert_eq!(table.rows[0][2], "one-shot");
    let csv = eval_csv(&rows);
    assert!(
        csv.lines().next().unwrap().contains("method,variant,norm"),
        "{csv}"
    );
}

/// A set without a frame to score after the largest K says so (an error another set's
/// evaluation survives, and a row of the table); bad K lists are refused.
#[test]
fn too_few_frames_and_bad_counts() {
    let set = set(3);
    let preds = preds(3);
    let cfg = config(&["gssa"], 1);
    let e = evaluate_few_shot(&set, &preds, &cfg, &[1, 3]).unwrap_err();
    assert!(
        matches!(
            e,
            EvalError::TooFewFrames {
                frames: 3,
                needed: 4,
                ..
            }
        ),
        "{e}"
    );
    let note = EvalNote::from_error(&e, "few-shot").unwrap();
    assert!(note.note.contains("too few frames: 3"), "{}", note.note);
    let ok = evaluate_few_shot(&set, &preds, &cfg, &[1, 2]).unwrap();
    assert_eq!(ok[0].eval_frames, 1);
    let table = eval_table_with_notes(&ok, std::slice::from_ref(&note), false);
    assert_eq!(table.rows.len(), 3);
    assert!(table.rows[2][4].contains("too few frames"));
    assert_eq!(table.rows[2].len(), table.headers.len());
    assert!(table.to_markdown().contains("needs at least 4"));

    // Not a note: other errors.
    assert!(EvalNote::from_error(&EvalError::InvalidParameter("x".into()), "v").is_none());
    for (ks, what) in [
        (&[][..], "at least one"),
        (&[0][..], "at least 1"),
        (&[2, 2][..], "twice"),
    ] {
        let e = evaluate_few_shot(&set, &preds, &cfg, ks)
            .unwrap_err()
            .to_string();
        assert!(e.contains(what), "{ks:?}: {e}");
    }
    let mut c = cfg.clone();
    c.calib_frame = Some("f1".into());
    let e = evaluate_few_shot(&set, &preds, &c, &[1])
        .unwrap_err()
        .to_string();
    assert!(e.contains("cannot both"), "{e}");

    // Robust and re-alignment variants are one-shot only: refused, not silently dropped.
    let mut c = cfg.clone();
    c.robust = vec![moma_core::align::robust::Robust::new(
        moma_core::align::robust::RobustKind::Huber,
    )];
    let e = evaluate_few_shot(&set, &preds, &c, &[1])
        .unwrap_err()
        .to_string();
    assert!(e.contains("does not combine"), "{e}");
    let mut c = cfg.clone();
    c.realign = Some(moma_eval::realign::RealignEval::default());
    let e = evaluate_few_shot(&set, &preds, &c, &[1])
        .unwrap_err()
        .to_string();
    assert!(e.contains("does not combine"), "{e}");
}
