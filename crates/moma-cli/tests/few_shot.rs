//! Few-shot calibration through the binary: `moma calibrate` with several --pred/--gt pairs and
//! `moma eval --calib-frames`, on the bundled procedural scene (no shared data needed).

use std::path::{Path, PathBuf};

mod common;
use common::{
    align_args, calibrate_args, demo, demo_frame, eval_args, eval_rows, fails, moma, ok, s,
};

#[test]
fn calibrate_with_several_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let (ps, gs): (Vec<PathBuf>, Vec<PathBuf>) =
        (0..3).map(|k| demo_frame(&scene, &pred, k)).unzip();
    let p = |k: usize| ps[k].as_path();
    let g = |k: usize| gs[k].as_path();
    let (one, two) = (tmp.path().join("one.json"), tmp.path().join("two.json"));
    let base = [
        "--pred-kind",
        "relative-disparity",
        "--method",
        "gssa",
        "--seed",
        "4",
    ];
    let run = |preds: &[&Path], gts: &[&Path], out: &Path, json: bool| -> String {
        let mut extra: Vec<&str> = base.to_vec();
        extra.extend(["-o", s(out)]);
        if json {
            extra.push("--json");
        }
        ok(&calibrate_args(preds, gts, &extra))
    };

    // The one-frame form, unchanged.
    let j1: serde_json::Value = serde_json::from_str(&run(&[p(0)], &[g(0)], &one, true)).unwrap();
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

    // Text report says how many frames (one flag, several values); the calibration aligns
    // later frames.
    let text = run(&[p(0), p(1)], &[g(0), g(1)], &two, false);
    assert!(text.contains("on 200 samples from 2 frames"), "{text}");
    let aligned = tmp.path().join("aligned");
    ok(&align_args(&two, p(2), &aligned, &[]));
    assert!(aligned.join("frame_02.depth.png").is_file());
}

#[test]
fn calibrate_bad_frame_lists_fail_clearly() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let out = tmp.path().join("c.json");
    let (p0, g0) = demo_frame(&scene, &pred, 0);
    let (p1, g1) = demo_frame(&scene, &pred, 1);
    let (p2, g2) = demo_frame(&scene, &pred, 2);
    let mask = scene.join("frames/frame_00/mask.png");
    let to_out = ["-o", s(&out)];

    // Two predictions, one ground truth.
    let err = fails(&calibrate_args(&[&p0, &p1], &[&g0], &to_out));
    assert!(
        err.contains("one --gt per --pred") && err.contains("2 prediction input(s) and 1"),
        "{err}"
    );

    // Two masks for three frames.
    let err = fails(&calibrate_args(
        &[&p0, &p1, &p2],
        &[&g0, &g1, &g2],
        &["--mask", s(&mask), s(&mask), "-o", s(&out)],
    ));
    assert!(err.contains("2 masks for 3 frames"), "{err}");

    // A frame of another size, named.
    let small = tmp.path().join("small.npy");
    moma_io::write_npy_f32(&small, ndarray::Array2::<f32>::ones((10, 12)).view()).unwrap();
    let err = fails(&calibrate_args(
        &[&p0, &small],
        &[&g0, &g1],
        &["--pred-kind", "relative-disparity", "-o", s(&out)],
    ));
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
    let rows = eval_rows(
        &scene,
        &pred,
        &out,
        &[
            "--methods",
            "gssa,ssra",
            "--seeds",
            "2",
            "--calib-frames",
            "1,2",
        ],
    );
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
    let rows = eval_rows(&scene, &pred, &out, &["--methods", "gssa", "--seeds", "2"]);
    assert_eq!(rows[0]["variant"], "one-shot");

    // Too few frames for every set: nothing is evaluated, the command fails with the reason and
    // writes nothing (it printed an empty `--json` array and succeeded).
    let fresh = out.with_file_name("too-few");
    let mut args = eval_args(
        &scene,
        &pred,
        &fresh,
        &["--methods", "gssa", "--seeds", "1", "--calib-frames", "1,3"],
    );
    args.push("--json");
    let o = moma(&args);
    assert!(!o.status.success());
    assert!(o.stdout.is_empty(), "no JSON array on stdout");
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains("no set could be evaluated")
            && e.contains("too few frames: 3, needs at least 4"),
        "{e}"
    );
    assert!(!fresh.exists());

    // With --calib-frame: refused.
    let err = fails(&eval_args(
        &scene,
        &pred,
        &out,
        &["--calib-frame", "frame_01", "--calib-frames", "2"],
    ));
    assert!(err.contains("--calib-frame"), "{err}");
    let err = fails(&eval_args(&scene, &pred, &out, &["--calib-frames", "0"]));
    assert!(err.contains("at least 1"), "{err}");
}
