//! One path to grasps and grasping under the depth's error (`moma grasp --realign`,
//! `--sigma-m`, `--grasp-quality`, `--min-success-prob`; `moma align --sigma-map`;
//! `moma grasp-eval` with `moma eval`'s variants, Brier scores and reliability tables) end to
//! end on the bundled demo scene (SIMULATED predictions; no ../shared, no network).

use std::path::Path;

mod common;
use common::{align_args, calibrate_args, demo, demo_frame, fails, ok, s};

fn json(text: &str) -> Vec<serde_json::Value> {
    serde_json::from_str::<serde_json::Value>(text)
        .expect("JSON on stdout")
        .as_array()
        .expect("an array")
        .clone()
}

#[test]
fn grasps_from_a_realigned_calibration_carry_success_probabilities() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let frames = scene.join("frames");
    let camera = scene.join("camera.json");
    let (pred0, gt0) = demo_frame(&scene, &pred, 0);
    let (pred1, gt1) = demo_frame(&scene, &pred, 1);
    let (rgb0, rgb1) = (
        frames.join("frame_00/rgb.png"),
        frames.join("frame_01/rgb.png"),
    );
    let calib = tmp.path().join("calib.json");
    let plain = tmp.path().join("plain.json");
    for (out, anchors) in [(&calib, true), (&plain, false)] {
        let mut extra = vec!["--camera", s(&camera), "-o", s(out)];
        if anchors {
            extra.extend(["--anchors", "--anchors-rgb", s(&rgb0)]);
        }
        ok(&calibrate_args(&[&pred0], &[&gt0], &extra));
    }
    let file: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&calib).unwrap()).unwrap();
    assert_eq!(file["version"], moma_io::CALIBRATION_VERSION);
    let model = &file["calibration"]["error_model"];
    assert!(model["sigma_flat_m"].as_f64().unwrap() > 0.0, "{model}");

    // `moma grasp` of frame 1 with suction, from the calibration or from an aligned depth map
    let on_calib = |gripper: &'static str| {
        [
            "grasp",
            "--calib",
            s(&calib),
            "--pred",
            s(&pred1),
            "--gripper",
            gripper,
        ]
    };
    let grasp_with = |gripper: &'static str, extra: &[&str]| -> Vec<serde_json::Value> {
        json(&ok(&[
            &on_calib(gripper)[..],
            &["--top", "3", "--json"],
            extra,
        ]
        .concat()))
    };
    let grasp = |extra: &[&str]| grasp_with("suction", extra);
    let realign = ["--realign", "anchors", "--realign-rgb", s(&rgb1)];
    let nominal = grasp(&[&realign[..], &["--grasp-quality", "nominal"]].concat());
    let aligned_dir = tmp.path().join("aligned");
    ok(&align_args(
        &calib,
        &pred1,
        &aligned_dir,
        &[&realign[..], &["--sigma-map"]].concat(),
    ));
    let aligned = aligned_dir.join("frame_01.depth.npy");
    let depth_args = |gripper: &'static str| {
        [
            "grasp",
            "--depth",
            s(&aligned),
            "--camera",
            s(&camera),
            "--gripper",
            gripper,
        ]
    };
    let on_depth = json(&ok(&[
        &depth_args("suction")[..],
        &["--top", "3", "--json"],
    ]
    .concat()));
    assert!(!nominal.is_empty());
    // `moma grasp` takes its depth as `moma align --realign` does: the frame's depth it writes
    // with -o equals align's output bit for bit (the planner then works on the error model's
    // expected truth of it, so its grasps differ from a plan on the bare map on purpose)
    let out = tmp.path().join("grasp-out");
    ok(&[
        &on_calib("parallel")[..],
        &realign[..],
        &["--grasp-quality", "nominal", "-o", s(&out)],
    ]
    .concat());
    assert_eq!(
        std::fs::read(out.join("depth.npy")).unwrap(),
        std::fs::read(&aligned).unwrap(),
        "the depth moma grasp planned from is not moma align's"
    );
    // the overlay is drawn on the frame's RGB that --realign-rgb gave (it was drawn on the
    // colour-mapped depth): away from the drawn grasps its pixels are the image's
    let (overlay, frame) = (
        moma_io::read_rgb(out.join("overlay.png")).unwrap(),
        moma_io::read_rgb(&rgb1).unwrap(),
    );
    let same = overlay
        .pixels()
        .zip(frame.pixels())
        .filter(|(a, b)| a == b)
        .count();
    let n = (frame.width() * frame.height()) as usize;
    assert!(
        same * 10 > n * 9,
        "{same} of {n} overlay pixels are the frame's RGB"
    );
    // with a calibration: a probability on every grasp; on a bare depth map: null, unless a σ
    for g in &nominal {
        let p = g["success_prob"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&p), "{g}");
    }
    assert!(on_depth.iter().all(|g| g["success_prob"].is_null()));
    let with_sigma = json(&ok(&[
        &depth_args("suction")[..],
        &["--sigma-m", "0.004", "--json"],
    ]
    .concat()));
    assert!(with_sigma.iter().all(|g| g["success_prob"].is_number()));
    // robust (the default): best probability first, up to the suction tie tolerance
    let robust = grasp(&realign);
    let probs: Vec<f64> = robust
        .iter()
        .map(|g| g["success_prob"].as_f64().unwrap())
        .collect();
    let best = probs.iter().copied().fold(0.0, f64::max);
    assert!(
        probs[0] >= best - f64::from(moma_grasp::DEFAULT_SUCTION_TIE_TOLERANCE) - 1e-9,
        "{probs:?}"
    );
    // the same seed: the same probabilities; a minimum above every grasp: empty, with the reason
    assert_eq!(grasp(&realign), robust);
    let out = common::moma(
        &[
            &on_calib("suction")[..],
            &["--json", "--min-success-prob", "1.0", "--sigma-m", "0.05"],
            &realign[..],
        ]
        .concat(),
    );
    assert!(out.status.success());
    assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), "[]");
    assert!(String::from_utf8_lossy(&out.stderr).contains("below the minimum"));
    // a σ meant in millimetres plans, with a note saying so
    let out = common::moma(&[&on_calib("suction")[..], &["--json", "--sigma-m", "10"]].concat());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success() && err.contains("millimetres?"),
        "{err}"
    );

    // the σ map: metres, beside the depth, finite where the depth is
    // (a σ of millimetres is no depth map: `read_depth` refuses a median that near)
    let sigma = moma_io::read_npy_f32(aligned_dir.join("frame_01.sigma.npy")).unwrap();
    let depth = moma_io::read_depth(&aligned).unwrap();
    assert_eq!(moma_core::ImageSize::of(&sigma.view()), depth.size());
    for (z, sg) in depth.depth_m.iter().zip(sigma.iter()) {
        assert_eq!(z.is_finite(), sg.is_finite());
    }
    assert!(aligned_dir.join("frame_01.sigma.png").is_file());
    let _ = gt1;

    // bad input
    let e = fails(&[
        "grasp",
        "--calib",
        s(&plain),
        "--pred",
        s(&pred1),
        "--gripper",
        "suction",
        "--realign",
        "anchors",
        "--realign-rgb",
        s(&rgb1),
    ]);
    assert!(e.contains("plain.json") && e.contains("anchor"), "{e}");
    let e = fails(&[&depth_args("suction")[..], &realign[..]].concat());
    assert!(e.contains("--realign") && e.contains("calibration"), "{e}");
    for (flag, value, says) in [
        ("--grasp-draws", "0", "--grasp-draws must be at least 1"),
        ("--grasp-draws", "-1", "--grasp-draws"),
        (
            "--min-success-prob",
            "1.5",
            "--min-success-prob 1.5 is outside [0, 1]",
        ),
        (
            "--min-success-prob",
            "-0.1",
            "--min-success-prob -0.1 is outside [0, 1]",
        ),
        (
            "--grasp-tie-tolerance",
            "2",
            "--grasp-tie-tolerance 2 is outside [0, 1]",
        ),
        ("--sigma-m", "-1", "sigma"),
    ] {
        // `--flag=value` and `--flag value` alike: a negative value is a value, not a flag
        let arg = format!("{flag}={value}");
        let e = fails(&[&on_calib("suction")[..], &[arg.as_str()]].concat());
        assert!(e.contains(says), "{flag} {value}: {e}");
        let e = fails(&[&on_calib("suction")[..], &[flag, value]].concat());
        assert!(e.contains(says), "{flag} {value}: {e}");
    }
    let e = fails(&[&depth_args("suction")[..], &["--grasp-quality", "robust"]].concat());
    assert!(e.contains("error model"), "{e}");
}

/// `grasp-eval --set SCENE --pred PRED -o OUT --methods gssa --seeds 1` followed by `extra`.
fn grasp_eval_args<'a>(
    scene: &'a Path,
    pred: &'a Path,
    out: &'a Path,
    extra: &[&'a str],
) -> Vec<&'a str> {
    let mut a = vec![
        "grasp-eval",
        "--set",
        s(scene),
        "--pred",
        s(pred),
        "-o",
        s(out),
    ];
    a.extend(["--methods", "gssa", "--seeds", "1"]);
    a.extend_from_slice(extra);
    a
}

fn grasp_eval(scene: &Path, pred: &Path, out: &Path, extra: &[&str]) -> Vec<serde_json::Value> {
    let mut a = grasp_eval_args(scene, pred, out, &["--grasp-draws", "4", "--json"]);
    a.extend_from_slice(extra);
    json(&ok(&a))
}

#[test]
fn grasp_eval_takes_the_variants_of_eval_and_reports_reliability() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let rows = grasp_eval(
        &scene,
        &pred,
        &tmp.path().join("ge"),
        &[
            "--realign",
            "anchors",
            "--grasp-quality",
            "nominal,robust",
            "--gripper",
            "suction",
        ],
    );
    let labels: Vec<(String, String, String)> = rows
        .iter()
        .map(|r| {
            (
                r["method"].as_str().unwrap().into(),
                r["variant"].as_str().unwrap().into(),
                r["grasp_quality"].as_str().unwrap().into(),
            )
        })
        .collect();
    let l = |m: &str, v: &str, q: &str| (m.to_string(), v.to_string(), q.to_string());
    assert_eq!(
        labels,
        [
            l("gssa", "one-shot", "nominal"),
            l("gssa", "one-shot", "robust"),
            l("gssa", "realign-anchors", "nominal"),
            l("gssa", "realign-anchors", "robust"),
            l("gt", "-", "nominal"),
        ]
    );
    // the normalisation each row planned with: the relative-disparity predictions' default
    let norms: Vec<&str> = rows.iter().map(|r| r["norm"].as_str().unwrap()).collect();
    assert_eq!(
        norms,
        [
            "minmax-unit",
            "minmax-unit",
            "minmax-unit",
            "minmax-unit",
            "-"
        ]
    );
    // metric-depth predictions (simulated): minmax-unit, and raw none
    let metric = json(&ok(&[
        "grasp-eval",
        "--set",
        s(&scene),
        "--simulate",
        "--sim-kind",
        "metric-depth",
        "--methods",
        "gssa,raw",
        "--seeds",
        "1",
        "--grasp-draws",
        "4",
        "--gripper",
        "suction",
        "-o",
        s(&tmp.path().join("ge-metric")),
        "--json",
    ]));
    let labels: Vec<(&str, &str)> = metric
        .iter()
        .map(|r| (r["method"].as_str().unwrap(), r["norm"].as_str().unwrap()))
        .collect();
    assert_eq!(
        labels,
        [("gssa", "minmax-unit"), ("raw", "none"), ("gt", "-")]
    );
    for r in &rows {
        let trials = r["trials"].as_u64().unwrap();
        let rel = r["reliability"].as_array().unwrap();
        if r["method"] == "gt" {
            assert!(r["brier"].is_null() && rel.iter().all(|b| b["grasps"] == 0));
            assert!(r["brier_base_rate"].is_null(), "{r}");
            continue;
        }
        let b = r["brier"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&b), "{r}");
        let base = r["brier_base_rate"].as_f64().unwrap();
        assert!((0.0..=0.25).contains(&base), "{r}");
        assert_eq!(rel.len(), 5);
        let n: u64 = rel.iter().map(|b| b["grasps"].as_u64().unwrap()).sum();
        assert!(n <= trials && n > 0, "{r}");
        // the contract's bins, exactly as written (no 0.6000000000000001)
        let bins: Vec<&serde_json::Value> = rel.iter().map(|b| &b["bin"]).collect();
        assert_eq!(
            serde_json::json!(bins),
            serde_json::json!([[0.0, 0.2], [0.2, 0.4], [0.4, 0.6], [0.6, 0.8], [0.8, 1.0]]),
            "{r}"
        );
    }
    assert!(tmp.path().join("ge/sigma_coverage.json").is_file());
    assert!(tmp.path().join("ge/grasp_reliability.md").is_file());

    // few-shot, as `moma eval --calib-frames`
    let rows = grasp_eval(
        &scene,
        &pred,
        &tmp.path().join("ge2"),
        &["--calib-frames", "1,2", "--gripper", "parallel"],
    );
    let variants: Vec<&str> = rows
        .iter()
        .map(|r| r["variant"].as_str().unwrap())
        .collect();
    assert_eq!(variants, ["one-shot", "few-shot-2", "-"]);
    let ge3 = tmp.path().join("ge3");
    let e = fails(&grasp_eval_args(
        &scene,
        &pred,
        &ge3,
        &["--grasp-draws", "0"],
    ));
    assert!(e.contains("--grasp-draws"), "{e}");
}

/// A frame whose mask is empty (every object picked) is named as such, not as a mask "without
/// valid ground truth".
#[test]
fn a_frame_with_an_empty_mask_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let mask = scene.join("frames/frame_02/mask.png");
    let size = moma_io::read_mask(&mask).unwrap().size();
    let empty = moma_core::Mask::new(ndarray::Array2::from_elem(size.shape(), false));
    moma_io::write_mask(&mask, &empty).unwrap();
    let out = tmp.path().join("ge");
    let e = fails(&grasp_eval_args(&scene, &pred, &out, &[]));
    assert!(
        e.contains("frame_02") && e.contains("its mask is empty (no object in the frame)"),
        "{e}"
    );
}
