//! Few-shot calibration through the binary: `moma calibrate` with several --pred/--gt pairs and
//! `moma eval --calib-frames`, on the bundled procedural scene (no shared data needed).

use std::path::{Path, PathBuf};

mod common;
use common::{fails, moma, ok, s};

/// The demo scene (3 frames, SIMULATED inverse-depth predictions).
fn demo(dir: &Path) -> (PathBuf, PathBuf) {
    let out = dir.join("demo");
    ok(&["demo", "-o", s(&out), "--frames", "3", "--no-exports"]);
    (out.join("scene"), out.join("predictions"))
}

#[test]
fn calibrate_with_several_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let ps: Vec<PathBuf> = (0..3)
        .map(|k| pred.join(format!("frame_0{k}.npy")))
        .collect();
    let gs: Vec<PathBuf> = (0..3)
        .map(|k| scene.join(format!("frames/frame_0{k}/depth.png")))
        .collect();
    let p = |k: usize| ps[k].as_path();
    let g = |k: usize| gs[k].as_path();
    let (one, two) = (tmp.path().join("one.json"), tmp.path().join("two.json"));
    let base = [
        "--pred-kind",
        "inverse-depth",
        "--method",
        "gssa",
        "--seed",
        "4",
    ];

    // The one-frame form, unchanged.
    let mut args = vec!["calibrate", "--pred", s(p(0)), "--gt", s(g(0))];
    args.extend(base);
    args.extend(["-o", s(&one), "--json"]);
    let j1: serde_json::Value = serde_json::from_str(&ok(&args)).unwrap();
    assert_eq!(j1["frames"], 1);
    assert_eq!(j1["n_used"], 100);

    // Two frames as repeated pairs.
    let mut args = vec![
        "calibrate",
        "--pred",
        s(p(0)),
        "--gt",
        s(g(0)),
        "--pred",
        s(p(1)),
        "--gt",
        s(g(1)),
    ];
    args.extend(base);
    args.extend(["-o", s(&two), "--json"]);
    let j2: serde_json::Value = serde_json::from_str(&ok(&args)).unwrap();
    assert_eq!(j2["frames"], 2);
    assert_eq!(j2["n_used"], 200, "--samples per frame");
    assert_ne!(j1["model"], j2["model"]);

    // Frame 0's samples are the one-frame calibration's; the file records both frames.
    let c1 = moma_io::read_calibration(&one).unwrap();
    let c2 = moma_io::read_calibration(&two).unwrap();
    assert_eq!(
        c2.calibration.samples.samples[..100],
        c1.calibration.samples.samples[..]
    );
    assert_eq!(c2.calibration.samples.samples.len(), 200);
    let sources = &c2.created.sources;
    assert!(sources.contains_key("prediction") && sources.contains_key("ground_truth (frame 1)"));

    // Text report says how many frames; the calibration aligns later frames.
    let mut args = vec![
        "calibrate",
        "--pred",
        s(p(0)),
        s(p(1)),
        "--gt",
        s(g(0)),
        s(g(1)),
    ];
    args.extend(base);
    args.extend(["-o", s(&two)]);
    let text = ok(&args);
    assert!(text.contains("on 200 samples from 2 frames"), "{text}");
    let aligned = tmp.path().join("aligned");
    ok(&[
        "align",
        "--calib",
        s(&two),
        "--pred",
        s(p(2)),
        "-o",
        s(&aligned),
    ]);
    assert!(aligned.join("frame_02.depth.png").is_file());
}

#[test]
fn calibrate_bad_frame_lists_fail_clearly() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let out = tmp.path().join("c.json");
    let p0 = pred.join("frame_00.npy");
    let p1 = pred.join("frame_01.npy");
    let g0 = scene.join("frames/frame_00/depth.png");
    let mask = scene.join("frames/frame_00/mask.png");

    // Two predictions, one ground truth.
    let err = fails(&[
        "calibrate",
        "--pred",
        s(&p0),
        s(&p1),
        "--gt",
        s(&g0),
        "-o",
        s(&out),
    ]);
    assert!(
        err.contains("one --gt per --pred") && err.contains("2 prediction input(s) and 1"),
        "{err}"
    );

    // Two masks for three frames.
    let g1 = scene.join("frames/frame_01/depth.png");
    let g2 = scene.join("frames/frame_02/depth.png");
    let p2 = pred.join("frame_02.npy");
    let err = fails(&[
        "calibrate",
        "--pred",
        s(&p0),
        s(&p1),
        s(&p2),
        "--gt",
        s(&g0),
        s(&g1),
        s(&g2),
        "--mask",
        s(&mask),
        s(&mask),
        "-o",
        s(&out),
    ]);
    assert!(err.contains("2 masks for 3 frames"), "{err}");

    // A frame of another size, named.
    let small = tmp.path().join("small.npy");
    moma_io::write_npy_f32(&small, ndarray::Array2::<f32>::ones((10, 12)).view()).unwrap();
    let err = fails(&[
        "calibrate",
        "--pred",
        s(&p0),
        s(&small),
        "--pred-kind",
        "inverse-depth",
        "--gt",
        s(&g0),
        s(&g1),
        "-o",
        s(&out),
    ]);
    assert!(
        err.contains("same size") && err.contains("small.npy"),
        "{err}"
    );
    assert!(!out.exists());
}

#[test]
fn eval_calib_frames_variants_and_too_few_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let out = tmp.path().join("eval");
    let rows: serde_json::Value = serde_json::from_str(&ok(&[
        "eval",
        "--set",
        s(&scene),
        "--pred",
        s(&pred),
        "--methods",
        "gssa,ssra",
        "--seeds",
        "2",
        "--calib-frames",
        "1,2",
        "-o",
        s(&out),
        "--json",
    ]))
    .unwrap();
    let rows = rows.as_array().unwrap();
    let got: Vec<(&str, &str, &str)> = rows
        .iter()
        .map(|r| {
            (
                r["method"].as_str().unwrap(),
                r["variant"].as_str().unwrap(),
                r["calib_frame"].as_str().unwrap(),
            )
        })
        .collect();
    assert_eq!(
        got,
        [
            ("gssa", "one-shot", "frame_00"),
            ("ssra", "one-shot", "frame_00"),
            ("gssa", "few-shot-2", "frame_00+frame_01"),
            ("ssra", "few-shot-2", "frame_00+frame_01"),
        ]
    );
    let md = std::fs::read_to_string(out.join("results.md")).unwrap();
    assert!(
        md.contains("| variant |") && md.contains("few-shot-2"),
        "{md}"
    );

    // Without the flag: one-shot rows, all other frames scored.
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
        "-o",
        s(&out),
        "--json",
    ]))
    .unwrap();
    assert_eq!(rows[0]["variant"], "one-shot");

    // Too few frames: a row says so, the command succeeds.
    let o = moma(&[
        "eval",
        "--set",
        s(&scene),
        "--pred",
        s(&pred),
        "--methods",
        "gssa",
        "--seeds",
        "1",
        "--calib-frames",
        "1,3",
        "-o",
        s(&out),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("too few frames: 3, needs at least 4"),
        "{stdout}"
    );

    // With --calib-frame: refused.
    let err = fails(&[
        "eval",
        "--set",
        s(&scene),
        "--pred",
        s(&pred),
        "--calib-frame",
        "frame_01",
        "--calib-frames",
        "2",
        "-o",
        s(&out),
    ]);
    assert!(err.contains("--calib-frame"), "{err}");
    let err = fails(&[
        "eval",
        "--set",
        s(&scene),
        "--pred",
        s(&pred),
        "--calib-frames",
        "0",
        "-o",
        s(&out),
    ]);
    assert!(err.contains("at least 1"), "{err}");
}
