//! `moma align` over many files: frames run in bounded parallel batches, and what is written
//! and reported does not depend on the number of threads (same bytes, input order), and a bad
//! file among many is named.

mod common;
use std::path::Path;
use std::process::Command;

use common::{calibrate_frame_00, demo, s};

/// Runs `moma align --json` with `threads` rayon threads over `preds` into `out`; returns the
/// summaries without their timings.
fn align(threads: usize, calib: &Path, preds: &[String], out: &Path) -> Vec<serde_json::Value> {
    let mut args = vec!["align".to_string(), "--calib".into(), s(calib).into()];
    // copies beside a copy of the index, which lists the originals: the kind is stated
    args.extend(["--pred-kind".into(), "relative-disparity".into()]);
    args.push("--pred".into());
    args.extend(preds.iter().cloned());
    args.extend([
        "-o".into(),
        s(out).into(),
        "--colormap".into(),
        "turbo".into(),
    ]);
    args.push("--json".into());
    let o = Command::new(env!("CARGO_BIN_EXE_moma"))
        .args(&args)
        .env("RAYON_NUM_THREADS", threads.to_string())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut v: Vec<serde_json::Value> = serde_json::from_slice(&o.stdout).unwrap();
    for f in &mut v {
        f.as_object_mut().unwrap().remove("align_ms");
    }
    v
}

#[test]
fn many_frames_give_the_same_files_and_order_on_any_thread_count() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let calib = tmp.path().join("calib.json");
    calibrate_frame_00(&scene, &pred, &calib, &[]);
    // 13 inputs (more than one batch on any machine with few cores): the 3 frames, copied
    let many = tmp.path().join("many");
    std::fs::create_dir(&many).unwrap();
    std::fs::copy(pred.join("predictions.json"), many.join("predictions.json")).unwrap();
    let mut preds = Vec::new();
    for k in 0..13 {
        let to = many.join(format!("f{k:02}.npy"));
        std::fs::copy(pred.join(format!("frame_{:02}.npy", k % 3)), &to).unwrap();
        preds.push(s(&to).to_string());
    }
    let (one, two) = (tmp.path().join("one"), tmp.path().join("two"));
    let a = align(1, &calib, &preds, &one);
    let b = align(2, &calib, &preds, &two);
    let names: Vec<&str> = a.iter().map(|f| f["name"].as_str().unwrap()).collect();
    let want: Vec<String> = (0..13).map(|k| format!("f{k:02}")).collect();
    assert_eq!(names, want);
    let strip = |v: &[serde_json::Value], dir: &Path| {
        let d = s(dir).to_string();
        serde_json::to_string(v).unwrap().replace(&d, "OUT")
    };
    assert_eq!(strip(&a, &one), strip(&b, &two));
    for k in 0..13 {
        for suffix in ["depth.png", "depth.npy", "color.png"] {
            let f = format!("f{k:02}.{suffix}");
            assert_eq!(
                std::fs::read(one.join(&f)).unwrap(),
                std::fs::read(two.join(&f)).unwrap(),
                "{f}"
            );
        }
    }
    // the same frame copied gives the same bytes as its first copy
    assert_eq!(
        std::fs::read(one.join("f00.depth.npy")).unwrap(),
        std::fs::read(one.join("f03.depth.npy")).unwrap()
    );

    // a corrupt file among many: the error names it
    std::fs::write(many.join("f07.npy"), b"not a numpy file").unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_moma"))
        .args([
            "align",
            "--calib",
            s(&calib),
            "--pred-kind",
            "relative-disparity",
        ])
        .arg("--pred")
        .args(&preds)
        .args(["-o", s(&tmp.path().join("bad"))])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("f07.npy"), "{err}");

    // inputs that do not fit are refused before a frame's files are written: a camera of
    // another size (named, nothing written), an RGB for the cloud of another size (that
    // frame's depth and σ maps are not left behind without their cloud)
    let frame = s(&pred.join("frame_01.npy")).to_string();
    let camera = |w: usize, h: usize, name: &str| {
        let path = tmp.path().join(name);
        let k = moma_core::Intrinsics {
            width: w,
            height: h,
            fx: w as f64,
            fy: w as f64,
            cx: w as f64 / 2.0,
            cy: h as f64 / 2.0,
        };
        moma_io::write_camera(&path, &k).unwrap();
        path
    };
    let size = moma_io::read_prediction(&frame, moma_core::PredictionKind::RelativeDisparity)
        .unwrap()
        .size();
    let right = camera(size.width, size.height, "camera.json");
    let small = camera(size.width / 2, size.height / 2, "camera-small.json");
    let small_rgb = tmp.path().join("small.png");
    moma_io::write_rgb(&small_rgb, &image::RgbImage::new(8, 6)).unwrap();
    // `moma align` of frame_01 into `dir` with its σ map and cloud, and `extra`
    let args = |dir: &Path, extra: &[&str]| -> Vec<String> {
        let mut a: Vec<String> = [
            "align",
            "--calib",
            s(&calib),
            "--pred",
            &frame,
            "-o",
            s(dir),
        ]
        .iter()
        .map(|x| x.to_string())
        .collect();
        a.extend(["--sigma-map", "--ply"].iter().map(|x| x.to_string()));
        a.extend(extra.iter().map(|x| x.to_string()));
        a
    };
    for (out, extra, names) in [
        ("cam", vec!["--camera", s(&small)], "camera-small.json"),
        (
            "rgb",
            vec!["--camera", s(&right), "--ply-rgb", s(&small_rgb)],
            "small.png",
        ),
    ] {
        let dir = tmp.path().join(out);
        let err = common::fails(&strs(&args(&dir, &extra)));
        assert!(err.contains(names), "{err}");
        let left: Vec<_> = std::fs::read_dir(&dir)
            .map(|d| d.map(|e| e.unwrap().file_name()).collect())
            .unwrap_or_default();
        assert!(left.is_empty(), "{out}: {left:?} written");
    }
    // and with both right, every file is written
    let dir = tmp.path().join("ok");
    common::ok(&strs(&args(&dir, &["--camera", s(&right)])));
    for suffix in ["depth.png", "depth.npy", "sigma.npy", "sigma.png", "ply"] {
        assert!(dir.join(format!("frame_01.{suffix}")).is_file(), "{suffix}");
    }
}

/// `&str`s of owned arguments, for `common::ok` and `common::fails`.
fn strs(a: &[String]) -> Vec<&str> {
    a.iter().map(String::as_str).collect()
}
