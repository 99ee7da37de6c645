//! Evaluation of re-alignment on static anchors on the procedural fixed-camera demo scene
//! (SIMULATED predictions).

use moma_core::ImageSize;
use moma_core::align::Method;
use moma_core::{Prediction, PredictionKind};
use moma_eval::demo::{DemoScene, build_demo};
use moma_eval::protocol::{EvalConfig, evaluate};
use moma_eval::realign::{RealignEval, brightness_response, realign_table, scale_brightness};
use moma_eval::scene::DemoSceneConfig;
use ndarray::{Array2, Array3};

#[test]
fn realign_rows_with_variants_and_stats() {
    let demo = DemoScene {
        scene: DemoSceneConfig {
            size: ImageSize::new(160, 120),
            focal_px: 150.0,
            frames: 3,
            ..Default::default()
        },
        ..Default::default()
    };
    let (set, preds) = build_demo(&demo, None).unwrap();
    let config = EvalConfig {
        methods: vec![Method::Gssa, Method::Ssra(Default::default())],
        seeds: 2,
        realign: Some(RealignEval {
            brightness: vec![1.0, 0.8],
            ..Default::default()
        }),
        ..Default::default()
    };
    let res = evaluate(&set, &preds, &config).unwrap();
    // 2 one-shot rows, then 2 methods × 2 brightness factors
    assert_eq!(res.len(), 6);
    let variants: Vec<&str> = res.iter().map(|r| r.variant.as_str()).collect();
    assert_eq!(
        variants,
        [
            "one-shot",
            "one-shot",
            "realign-anchors",
            "realign-anchors-b0.80",
            "realign-anchors",
            "realign-anchors-b0.80"
        ]
    );
    for r in &res[2..] {
        let s = r.realign.unwrap();
        assert_eq!(s.results, 2 * 2); // 2 evaluated frames × 2 seeds
        assert!(s.mean_anchors > 0.0);
        assert!(r.per_image.mae.mean.is_finite() && s.one_shot_mae_m.is_finite());
    }
    // at brightness 1 the baseline is the one-shot row of the same method
    assert!((res[2].realign.unwrap().one_shot_mae_m - res[0].per_image.mae.mean).abs() < 1e-12);
    assert!(res[0].realign.is_none());
    // the JSON contract carries the variant right after the method
    let json = moma_eval::report::contract_json(&res).unwrap();
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!(v[3]["variant"], "realign-anchors-b0.80");
    let text = realign_table(&res).to_text();
    assert!(text.contains("realign-anchors-b0.80") && text.contains("frames worse"));
}

#[test]
fn brightness_helpers() {
    let rgb = Array3::from_elem((2, 2, 3), 250u8);
    let b = scale_brightness(rgb.view(), 1.2);
    assert!(b.iter().all(|&x| x == 255)); // clipped
    let d = scale_brightness(rgb.view(), 0.8);
    assert!(d.iter().all(|&x| x == 200));
    // the response: q ← (1 + κ ln β)·q + κ ln β·min q; zeros (no depth) stay zero
    let p = Prediction::new(
        Array2::from_shape_vec((1, 3), vec![0.0, 1.0, 2.0]).unwrap(),
        PredictionKind::RelativeDisparity,
    );
    let r = brightness_response(&p, 0.8, 0.05);
    let e = 0.05 * 0.8f64.ln();
    assert_eq!(r.values[[0, 0]], 0.0);
    assert!((r.values[[0, 2]] as f64 - ((1.0 + e) * 2.0 + e)).abs() < 1e-6);
    assert_eq!(brightness_response(&p, 1.0, 0.05), p);
}
