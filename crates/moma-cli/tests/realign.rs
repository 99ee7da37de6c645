//! `moma calibrate --anchors`, `moma align --realign anchors` and `moma eval --realign anchors`
//! end to end on the bundled demo scene (SIMULATED predictions; no ../shared, no network).

use std::path::Path;

mod common;
use common::{
    align_args, calibrate_args, demo, demo_frame, eval_args, eval_rows, fails, method_variants, ok,
    s,
};

/// `moma calibrate`'s arguments for an SSRA calibration with anchors from `rgb`, into `out`.
fn anchor_calibration<'a>(
    pred: &'a Path,
    gt: &'a Path,
    rgb: &'a Path,
    out: &'a Path,
) -> Vec<&'a str> {
    calibrate_args(
        &[pred],
        &[gt],
        &[
            "--pred-kind",
            "relative-disparity",
            "--method",
            "ssra",
            "--anchors",
            "--anchors-rgb",
            s(rgb),
            "-o",
            s(out),
        ],
    )
}

#[test]
fn calibrate_align_and_eval_with_realignment() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let frames = scene.join("frames");
    let calib = tmp.path().join("calib.json");
    let (pred0, gt0) = demo_frame(&scene, &pred, 0);
    let rgb0 = frames.join("frame_00/rgb.png");
    ok(&anchor_calibration(&pred0, &gt0, &rgb0, &calib));
    let text = std::fs::read_to_string(&calib).unwrap();
    assert!(
        text.contains("\"grey_b64\"") && text.contains("\"normalised_b64\""),
        "the anchor store and the normalised calibration prediction are in the file"
    );
    let out = tmp.path().join("aligned");
    let (pred1, _) = demo_frame(&scene, &pred, 1);
    let rgb1 = frames.join("frame_01/rgb.png");
    let align = |extra: &[&str], rgb: &Path| -> Vec<String> {
        let mut a = vec![
            "--pred-kind",
            "relative-disparity",
            "--realign",
            "anchors",
            "--realign-rgb",
            s(rgb),
        ];
        a.extend_from_slice(extra);
        align_args(&calib, &pred1, &out, &a)
            .iter()
            .map(|a| a.to_string())
            .collect()
    };
    let run = |args: Vec<String>| -> serde_json::Value {
        let a: Vec<&str> = args.iter().map(|x| x.as_str()).collect();
        let v: serde_json::Value = serde_json::from_str(&ok(&a)).unwrap();
        v.as_array().unwrap()[0]["realign"].clone()
    };
    // each frame names the calibration's method and normalisation (the default: minmax-unit)
    let frame: serde_json::Value = serde_json::from_str(&ok(&align(&["--json"], &rgb1)
        .iter()
        .map(|x| x.as_str())
        .collect::<Vec<_>>()))
    .unwrap();
    assert_eq!(frame[0]["method"], "ssra", "{frame}");
    assert_eq!(frame[0]["normalisation"], "minmax-unit", "{frame}");
    // every form gives a per-frame report with accepted / reason
    for form in ["scale-shift", "planar", "prediction-affine"] {
        let r = run(align(&["--realign-form", form, "--json"], &rgb1));
        assert!(r["accepted"].is_boolean(), "{form}: {r}");
        assert!(r["reason"].as_str().unwrap().len() > 10, "{r}");
        assert!(r["anchors"].as_u64().unwrap() > 0, "{form}: {r}");
        assert_eq!(r["correction"], form, "{r}");
    }
    // the flags reach the library: ridge, max anchors, target
    let r = run(align(
        &[
            "--realign-ridge",
            "0",
            "--realign-max-anchors",
            "60",
            "--realign-target",
            "ground-truth",
            "--json",
        ],
        &rgb1,
    ));
    assert!(r["anchors_used"].as_u64().unwrap() <= 60, "{r}");
    // a covered background (a frame whose RGB is all different) falls back with the reason
    let img = image::RgbImage::from_fn(
        image::image_dimensions(&rgb1).unwrap().0,
        image::image_dimensions(&rgb1).unwrap().1,
        |x, y| {
            image::Rgb([
                (x * 7 % 256) as u8,
                (y * 13 % 256) as u8,
                ((x + y) % 256) as u8,
            ])
        },
    );
    let covered = tmp.path().join("covered.png");
    img.save(&covered).unwrap();
    for form in ["scale-shift", "prediction-affine"] {
        let r = run(align(&["--realign-form", form, "--json"], &covered));
        assert_eq!(r["accepted"], false, "{r}");
        assert!(
            r["reason"].as_str().unwrap().contains("anchor"),
            "{form}: {r}"
        );
        assert!(r["held_out_rmse_before_m"].is_null(), "{r}");
    }
    // the text output warns
    let a = align(&[], &covered);
    let text = ok(&a.iter().map(|x| x.as_str()).collect::<Vec<_>>());
    assert!(text.contains("WARNING"), "{text}");

    // bad flag values error clearly
    let bad = |extra: &[&str]| {
        let a = align(extra, &rgb1);
        fails(&a.iter().map(|x| x.as_str()).collect::<Vec<_>>())
    };
    let e = bad(&["--realign-form", "affine"]);
    assert!(
        e.contains("--realign-form") && e.contains("prediction-affine"),
        "{e}"
    );
    let e = bad(&["--realign-ridge=-1"]);
    assert!(e.contains("ridge") && e.contains(">= 0"), "{e}");
    assert!(bad(&["--realign-max-anchors", "5"]).contains("max_anchors"));
    let e = bad(&["--realign-target", "truth"]);
    assert!(
        e.contains("--realign-target") && e.contains("ground-truth"),
        "{e}"
    );
    let e = bad(&[
        "--realign-form",
        "prediction-affine",
        "--realign-target",
        "ground-truth",
    ]);
    assert!(e.contains("scale-shift"), "{e}");
    // the flags need --realign
    let e = fails(&align_args(
        &calib,
        &pred1,
        &out,
        &["--pred-kind", "relative-disparity", "--realign-ridge", "3"],
    ));
    assert!(e.contains("--realign"), "{e}");

    // eval: one-shot rows and one block of re-alignment rows per brightness factor
    let rows = eval_rows(
        &scene,
        &pred,
        &tmp.path().join("eval"),
        &[
            "--methods",
            "gssa",
            "--seeds",
            "2",
            "--realign",
            "anchors",
            "--brightness",
            "1,0.8",
            "--realign-form",
            "prediction-affine",
        ],
    );
    let variants: Vec<String> = method_variants(&rows).into_iter().map(|(_, v)| v).collect();
    assert_eq!(
        variants,
        ["one-shot", "realign-anchors", "realign-anchors-b0.80"],
        "{rows:?}"
    );
    // the full results (written to -o) carry the re-alignment statistics
    let full: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(tmp.path().join("eval/results.json")).unwrap(),
    )
    .unwrap();
    let full: Vec<&serde_json::Value> = full
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| r["variant"].as_str().unwrap().starts_with("realign"))
        .collect();
    assert_eq!(full.len(), 2);
    for r in full {
        assert_eq!(r["method"], "gssa");
        let st = &r["realign"];
        assert_eq!(st["results"], 4, "2 seeds × 2 evaluated frames: {st}");
        assert!(st["worse_fraction"].as_f64().unwrap() <= 1.0);
    }
    assert!(
        fails(&eval_args(
            &scene,
            &pred,
            &tmp.path().join("eval2"),
            &["--realign", "anchors", "--realign-ridge", "nan"],
        ))
        .contains("ridge")
    );
}

/// `calibrate --anchors` on an over-exposed calibration RGB (a blown-out table: a review's
/// scene) warns that the saturated part can hold no anchor; the demo's own RGB does not.
#[test]
fn calibrate_warns_of_a_saturated_calibration_rgb() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let (pred0, gt0) = demo_frame(&scene, &pred, 0);
    let rgb0 = scene.join("frames/frame_00/rgb.png");
    let mut blown = moma_io::read_rgb(&rgb0).unwrap();
    let h = blown.height();
    for (_, y, p) in blown.enumerate_pixels_mut() {
        if y < h * 9 / 10 {
            *p = image::Rgb([255, 255, 255]);
        }
    }
    let blown_path = tmp.path().join("blown.png");
    moma_io::write_rgb(&blown_path, &blown).unwrap();
    let run = |rgb: &Path| {
        let calib = tmp.path().join("c.json");
        let a = anchor_calibration(&pred0, &gt0, rgb, &calib);
        let out = common::moma(&a);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    assert!(!run(&rgb0).contains("saturated"));
    let err = run(&blown_path);
    assert!(
        err.contains("90 % of the calibration frame's RGB is saturated")
            && err.contains("exposure"),
        "{err}"
    );
}
