//! `moma calibrate --anchors`, `moma align --realign anchors` and `moma eval --realign anchors`
//! end to end on the bundled demo scene (SIMULATED predictions; no ../shared, no network).

use std::path::{Path, PathBuf};

mod common;
use common::{fails, ok, s};

fn demo(dir: &Path) -> (PathBuf, PathBuf) {
    let out = dir.join("demo");
    ok(&["demo", "-o", s(&out), "--frames", "3", "--no-exports"]);
    (out.join("scene"), out.join("predictions"))
}

#[test]
fn calibrate_align_and_eval_with_realignment() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let frames = scene.join("frames");
    let calib = tmp.path().join("calib.json");
    ok(&[
        "calibrate",
        "--pred",
        s(&pred.join("frame_00.npy")),
        "--pred-kind",
        "inverse-depth",
        "--gt",
        s(&frames.join("frame_00/depth.png")),
        "--method",
        "ssra",
        "--anchors",
        "--anchors-rgb",
        s(&frames.join("frame_00/rgb.png")),
        "-o",
        s(&calib),
    ]);
    let text = std::fs::read_to_string(&calib).unwrap();
    assert!(
        text.contains("\"grey_b64\"") && text.contains("\"normalised_b64\""),
        "the anchor store and the normalised calibration prediction are in the file"
    );
    let out = tmp.path().join("aligned");
    let pred1 = pred.join("frame_01.npy");
    let rgb1 = frames.join("frame_01/rgb.png");
    let align = |extra: &[&str], rgb: &Path| -> Vec<String> {
        [
            "align",
            "--calib",
            s(&calib),
            "--pred",
            s(&pred1),
            "--pred-kind",
            "inverse-depth",
            "-o",
            s(&out),
            "--realign",
            "anchors",
            "--realign-rgb",
            s(rgb),
        ]
        .iter()
        .map(|a| a.to_string())
        .chain(extra.iter().map(|a| a.to_string()))
        .collect()
    };
    let run = |args: Vec<String>| -> serde_json::Value {
        let a: Vec<&str> = args.iter().map(|x| x.as_str()).collect();
        let v: serde_json::Value = serde_json::from_str(&ok(&a)).unwrap();
        v.as_array().unwrap()[0]["realign"].clone()
    };
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
    let e = fails(&[
        "align",
        "--calib",
        s(&calib),
        "--pred",
        s(&pred1),
        "--pred-kind",
        "inverse-depth",
        "-o",
        s(&out),
        "--realign-ridge",
        "3",
    ]);
    assert!(e.contains("--realign"), "{e}");

    // eval: one-shot rows and one block of re-alignment rows per brightness factor
    let rows: serde_json::Value = serde_json::from_str(&ok(&[
        "eval",
        "--set",
        s(&scene),
        "--pred",
        s(&pred),
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
        "-o",
        s(&tmp.path().join("eval")),
        "--json",
    ]))
    .unwrap();
    let rows = rows.as_array().unwrap();
    let variants: Vec<&str> = rows
        .iter()
        .map(|r| r["variant"].as_str().unwrap())
        .collect();
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
        fails(&[
            "eval",
            "--set",
            s(&scene),
            "--pred",
            s(&pred),
            "--realign",
            "anchors",
            "--realign-ridge",
            "nan",
            "-o",
            s(&tmp.path().join("eval2")),
        ])
        .contains("ridge")
    );
}
