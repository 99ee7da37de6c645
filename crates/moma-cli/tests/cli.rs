//! End-to-end tests of the `moma` binary on the bundled procedural scene (`moma demo` writes it),
//! so they need neither ../shared nor a network. Metrics are checked against an independent
//! implementation of docs/method.md §3 written here.

use std::path::{Path, PathBuf};
use std::process::Command;

mod common;
use common::{
    align_args, calibrate_args, calibrate_frame_00, demo, demo_frame, fails, moma, ok, s,
    shared_dir,
};

/// docs/method.md §3, written independently of moma-core: (d105, d110, d125, rel, rmse, mae, n).
fn reference_metrics(pred: &Path, gt: &Path, mask: &Path) -> [f64; 7] {
    let p = moma_io::read_depth(pred).unwrap().depth_m;
    let g = moma_io::read_depth(gt).unwrap().depth_m;
    let m = moma_io::read_mask(mask).unwrap();
    let (mut n, mut d) = (0usize, [0usize; 3]);
    let (mut rel, mut se, mut ae) = (0f64, 0f64, 0f64);
    for ((idx, &gv), &inside) in g.indexed_iter().zip(m.data().iter()) {
        let pv = p[idx];
        if !inside || !gv.is_finite() || gv <= 0.0 || !pv.is_finite() {
            continue;
        }
        let (pv, gv) = (f64::from(pv), f64::from(gv));
        n += 1;
        let ratio = if pv > 0.0 {
            (pv / gv).max(gv / pv)
        } else {
            f64::INFINITY
        };
        for (k, t) in [1.05, 1.10, 1.25].iter().enumerate() {
            if ratio < *t {
                d[k] += 1;
            }
        }
        rel += (pv - gv).abs() / gv;
        se += (pv - gv).powi(2);
        ae += (pv - gv).abs();
    }
    let nf = n as f64;
    [
        d[0] as f64 / nf,
        d[1] as f64 / nf,
        d[2] as f64 / nf,
        rel / nf,
        (se / nf).sqrt(),
        ae / nf,
        nf,
    ]
}

#[test]
fn calibrate_align_metrics_end_to_end() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let frames = scene.join("frames");
    let calib = tmp.path().join("calib.json");

    let camera = scene.join("camera.json");
    // frame 00 with the camera, seed 3 and `extra` settings, written to `out`
    let calibrate = |out: &Path, extra: &[&str]| {
        let mut args = vec![
            "--pred-kind",
            "relative-disparity",
            "--camera",
            s(&camera),
            "--seed",
            "3",
        ];
        args.extend_from_slice(extra);
        calibrate_frame_00(&scene, &pred, out, &args)
    };
    let summary: serde_json::Value =
        serde_json::from_str(&calibrate(&calib, &["--samples", "100", "--json"])).unwrap();
    assert_eq!(summary["method"], "ssra");
    assert_eq!(summary["n_used"], 100);
    // the normalisation taken, the default (the authors' code's, for a disparity as well),
    // and the kind
    assert_eq!(summary["normalisation"]["method"], "minmax-unit");
    assert_eq!(summary["normalisation"]["space"], "inverse");
    assert_eq!(summary["prediction_kind"], "relative-disparity");

    // LWLR's parameters hold its 100 samples: the terminal line counts them, the file keeps
    // them all
    let lwlr = tmp.path().join("lwlr.json");
    let text = calibrate(&lwlr, &["--method", "lwlr"]);
    let line = text
        .lines()
        .find(|l| l.starts_with("parameters ("))
        .unwrap_or_else(|| panic!("no parameters line in {text}"));
    assert!(
        line.contains("\"samples\":\"[100 entries: in the calibration file]\"")
            && line.contains("\"bandwidth_px\"")
            && line.len() < 600,
        "{line}"
    );
    let file: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&lwlr).unwrap()).unwrap();
    let samples = file["calibration"]["model"]["samples"].as_array();
    assert_eq!(
        samples.map(Vec::len),
        Some(100),
        "{:.300}",
        file.to_string()
    );
    // the grasp check of the calibration frame: both grippers, counts that add up, labelled
    let checked: serde_json::Value = serde_json::from_str(&calibrate(
        &tmp.path().join("checked.json"),
        &["--grasp-check", "suction,parallel", "--json"],
    ))
    .unwrap();
    let rows = checked["grasp_check"].as_array().unwrap();
    let grippers: Vec<&str> = rows
        .iter()
        .map(|r| r["gripper"].as_str().unwrap())
        .collect();
    assert_eq!(grippers, ["suction", "parallel"]);
    for r in rows {
        let (n, k) = (
            r["grasps"].as_u64().unwrap(),
            r["successes"].as_u64().unwrap(),
        );
        let failed: u64 = r["failures"]
            .as_object()
            .unwrap()
            .values()
            .map(|v| v.as_u64().unwrap())
            .sum();
        assert!(n > 0 && k + failed == n, "{r}");
        assert_eq!(r["scores"], "proxy");
        let p = r["mean_success_prob"].as_f64().unwrap();
        assert!(p > 0.0 && p < 1.0, "{r}");
    }
    // without a camera there are no metres to plan in: refused before anything is written
    let unchecked = tmp.path().join("unchecked.json");
    let e = fails(&[
        "calibrate",
        "--pred",
        s(&pred.join("frame_00.npy")),
        "--gt",
        s(&frames.join("frame_00/depth.png")),
        "--grasp-check",
        "suction",
        "-o",
        s(&unchecked),
    ]);
    assert!(e.contains("--camera"), "{e}");
    assert!(!unchecked.exists());

    let rms = summary["rms_residual_m"].as_f64().unwrap();
    assert!(
        rms > 0.0 && rms < 0.05,
        "RMS residual {rms} m on a table at ~0.7 m"
    );

    let out = tmp.path().join("aligned");
    let listing: serde_json::Value = serde_json::from_str(&ok(&[
        "align",
        "--calib",
        s(&calib),
        "--pred",
        s(&pred.join("frame_01.npy")),
        s(&pred.join("frame_02.npy")),
        "--pred-kind",
        "relative-disparity",
        "-o",
        s(&out),
        "--ply",
        "--colormap",
        "--json",
    ]))
    .unwrap();
    assert_eq!(listing.as_array().unwrap().len(), 2);
    for name in ["frame_01", "frame_02"] {
        for suffix in ["depth.png", "depth.npy", "color.png", "ply"] {
            assert!(
                out.join(format!("{name}.{suffix}")).is_file(),
                "{name}.{suffix} written"
            );
        }
    }
    let ply = std::fs::read(out.join("frame_01.ply")).unwrap();
    assert!(ply.starts_with(b"ply\nformat binary_little_endian 1.0\n"));

    // The millimetre PNG and the metre npy hold the same depth to rounding.
    let png = moma_io::read_depth(out.join("frame_01.depth.png"))
        .unwrap()
        .depth_m;
    let npy = moma_io::read_depth(out.join("frame_01.depth.npy"))
        .unwrap()
        .depth_m;
    let worst = png
        .iter()
        .zip(npy.iter())
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(worst <= 0.0005 + 1e-6, "PNG vs npy differ by {worst} m");

    // A fixed colour-map range, written as the help shows it (`0.4,1.2`), is the one recorded
    // in the colour map (the documented form used to be refused: "2 values required").
    let fixed = tmp.path().join("fixed");
    let align_range = |out: &Path, range: &str| {
        vec![
            "align".to_string(),
            "--calib".into(),
            s(&calib).into(),
            "--pred".into(),
            s(&pred.join("frame_01.npy")).into(),
            "--pred-kind".into(),
            "relative-disparity".into(),
            "-o".into(),
            s(out).into(),
            "--colormap".into(),
            format!("--range-m={range}"),
        ]
    };
    let mut args = align_range(&fixed, "");
    args.pop();
    args.extend(["--range-m".into(), "0.4,1.2".into()]);
    ok(&args.iter().map(String::as_str).collect::<Vec<_>>());
    let scale = moma_io::read_colour_scale(fixed.join("frame_01.color.png"))
        .unwrap()
        .expect("a colour scale");
    assert_eq!((scale.min_m, scale.max_m), (0.4, 1.2));
    for bad in ["1.2,0.4", "0.4", "nan,1", "-1,2", "0.4,inf"] {
        let args = align_range(&tmp.path().join("bad"), bad);
        let err = fails(&args.iter().map(String::as_str).collect::<Vec<_>>());
        assert!(
            err.contains("--range-m") && err.contains("MIN,MAX"),
            "{bad}: {err}"
        );
    }

    // `moma metrics --json` agrees with the independent implementation.
    let gt = frames.join("frame_01/depth.png");
    let mask = frames.join("frame_01/mask.png");
    let aligned = out.join("frame_01.depth.npy");
    let m: serde_json::Value = serde_json::from_str(&ok(&[
        "metrics",
        "--pred",
        s(&aligned),
        "--gt",
        s(&gt),
        "--mask",
        s(&mask),
        "--json",
    ]))
    .unwrap();
    let want = reference_metrics(&aligned, &gt, &mask);
    for (key, w) in ["d105", "d110", "d125", "rel", "rmse", "mae", "n"]
        .iter()
        .zip(want)
    {
        let got = m[key].as_f64().unwrap();
        assert!(
            (got - w).abs() <= 1e-9 + 1e-9 * w.abs(),
            "{key}: moma {got}, reference {w}"
        );
    }
    // SSRA on the simulated scene is accurate to a few centimetres inside the objects.
    assert!(want[5] < 0.05, "MAE {} m", want[5]);
}

#[test]
fn bad_input_is_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let frames = scene.join("frames");
    let calib = tmp.path().join("calib.json");

    // An RGB image given as ground truth: named, and no calibration file written.
    let rgb = frames.join("frame_00/rgb.png");
    let err = fails(&[
        "calibrate",
        "--pred",
        s(&pred.join("frame_00.npy")),
        "--gt",
        s(&rgb),
        "-o",
        s(&calib),
    ]);
    assert!(err.contains(s(&rgb)) && err.contains("16-bit"), "{err}");
    assert!(!calib.exists());

    calibrate_frame_00(
        &scene,
        &pred,
        &calib,
        &["--pred-kind", "relative-disparity"],
    );

    // Kind mismatch between calibration (and predictions.json) and run time.
    let frame1 = pred.join("frame_01.npy");
    let a = tmp.path().join("a");
    let err = fails(&align_args(
        &calib,
        &frame1,
        &a,
        &["--pred-kind", "metric-depth"],
    ));
    assert!(
        err.contains("relative-disparity") && err.contains("prediction kind mismatch"),
        "{err}"
    );

    // Two inputs with the same output name: refused, naming both, before anything is written
    // (the second's files used to replace the first's without a word).
    let other = tmp.path().join("other");
    std::fs::create_dir_all(&other).unwrap();
    let twin = other.join("frame_01.npy");
    std::fs::copy(pred.join("frame_02.npy"), &twin).unwrap();
    let err = fails(&[
        "align",
        "--calib",
        s(&calib),
        "--pred",
        s(&frame1),
        s(&twin),
        "-o",
        s(&a),
    ]);
    assert!(
        err.contains("same output name 'frame_01'") && err.contains(s(&twin)),
        "{err}"
    );
    assert!(!a.exists());

    // An output folder that is a file, and a calibration output that is a folder: named as such.
    let file = tmp.path().join("a_file");
    std::fs::write(&file, "x").unwrap();
    let err = fails(&align_args(
        &calib,
        &frame1,
        &file,
        &["--pred-kind", "relative-disparity"],
    ));
    assert!(
        err.contains("a_file") && err.contains("is a file, not a directory"),
        "{err}"
    );
    let (pred0, gt0) = demo_frame(&scene, &pred, 0);
    let err = fails(&calibrate_args(&[&pred0], &[&gt0], &["-o", s(tmp.path())]));
    assert!(
        err.contains("is a directory (give the name of a file"),
        "{err}"
    );
    let err = fails(&calibrate_args(
        &[&pred0],
        &[&gt0],
        &["-o", s(&file.join("c.json"))],
    ));
    assert!(err.contains("is a file, not a directory"), "{err}");

    // --ply without intrinsics.
    let err = fails(&align_args(
        &calib,
        &frame1,
        &a,
        &["--pred-kind", "relative-disparity", "--ply"],
    ));
    assert!(err.contains("intrinsics"), "{err}");

    // A truncated calibration file names the file.
    let text = std::fs::read_to_string(&calib).unwrap();
    let broken = tmp.path().join("broken.json");
    std::fs::write(&broken, &text[..text.len() / 2]).unwrap();
    let err = fails(&align_args(
        &broken,
        &frame1,
        &a,
        &["--pred-kind", "relative-disparity"],
    ));
    assert!(err.contains("broken.json") && err.contains("JSON"), "{err}");

    // A prediction with NaN: refused, naming the problem.
    let nan = tmp.path().join("nan.npy");
    let mut p = moma_io::read_prediction(
        pred.join("frame_01.npy"),
        moma_core::PredictionKind::RelativeDisparity,
    )
    .unwrap();
    p.values[[5, 7]] = f32::NAN;
    moma_io::write_prediction(&nan, &p).unwrap();
    let err = fails(&align_args(
        &calib,
        &nan,
        &a,
        &["--pred-kind", "relative-disparity"],
    ));
    assert!(
        err.contains("nan.npy")
            && err.contains("non-finite")
            && err.contains("a relative prediction has a value at every pixel"),
        "{err}"
    );
    // the output folder the failed run created is gone again (it wrote nothing into it); one
    // that was there before stays
    assert!(!a.exists());
    std::fs::create_dir_all(&a).unwrap();
    fails(&align_args(
        &calib,
        &nan,
        &a,
        &["--pred-kind", "relative-disparity"],
    ));
    assert!(a.is_dir());

    // A model source without weights.
    let err = fails(&["predict", s(&rgb), "-o", s(&tmp.path().join("p"))]);
    assert!(err.contains("--weights"), "{err}");
}

#[test]
fn depth_model_options_fail_clearly() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, _) = demo(tmp.path());
    let rgb = scene.join("frames/frame_00/rgb.png");
    let out = tmp.path().join("pred");
    let predict = |extra: &[&str]| {
        let mut args = vec!["predict", s(&rgb), "-o", s(&out)];
        args.extend_from_slice(extra);
        args.iter().map(|a| a.to_string()).collect::<Vec<_>>()
    };
    let fails_with = |args: Vec<String>, envs: &[(&str, &Path)]| {
        let out = Command::new(env!("CARGO_BIN_EXE_moma"))
            .args(&args)
            .envs(envs.iter().copied())
            .env("HF_HUB_OFFLINE", "1")
            .output()
            .expect("the moma binary runs");
        assert!(!out.status.success(), "moma {args:?} should fail");
        String::from_utf8(out.stderr).expect("utf-8 stderr")
    };

    // Unknown checkpoint name: the known ones are listed.
    let err = fails_with(predict(&["--hub", "vit-huge"]), &[]);
    assert!(err.contains("metric-hypersim-vits"), "{err}");
    // Known name, empty cache, offline: the download address is given.
    let cache = tmp.path().join("hf-cache");
    let err = fails_with(predict(&["--hub", "vits"]), &[("HF_HUB_CACHE", &cache)]);
    assert!(
        err.contains("https://huggingface.co/depth-anything/Depth-Anything-V2-Small/resolve/main/depth_anything_v2_vits.pth"),
        "{err}"
    );
    // --hub decides the network: --weights/--model with it is a usage error.
    let err = fails_with(predict(&["--hub", "vits", "--model", "vitl"]), &[]);
    assert!(err.contains("--model"), "{err}");

    // Devices the build cannot give: refused before anything is written.
    let weights = tmp.path().join("weights.safetensors");
    std::fs::write(&weights, b"not read before the device is opened").unwrap();
    // Without the `cuda` feature it is "built without", with it but no GPU "CUDA device 0: ...".
    if !candle_core_cuda_available() {
        let err = fails_with(
            predict(&["--weights", s(&weights), "--device", "cuda:0"]),
            &[],
        );
        assert!(err.to_lowercase().contains("cuda"), "{err}");
    }
    let err = fails_with(
        predict(&[
            "--weights",
            s(&weights),
            "--device",
            "cpu",
            "--dtype",
            "bf16",
        ]),
        &[],
    );
    // bf16 runs on the CPU now (packed kernels): what fails is this file, named
    assert!(
        err.contains("weights.safetensors") && !err.contains("needs a GPU"),
        "{err}"
    );
    let err = fails_with(predict(&["--weights", s(&weights), "--device", "tpu"]), &[]);
    assert!(err.contains("tpu"), "{err}");
    // An input size that only exhausts memory (140 000 px aborted, 2^64 − 2 panicked): refused
    // before the weights are read.
    for size in ["140000", "18446744073709551614", "4214"] {
        let err = fails_with(
            predict(&["--weights", s(&weights), "--input-size", size]),
            &[],
        );
        assert!(
            err.contains("--input-size") && err.contains(size) && err.contains("at most 4200"),
            "{err}"
        );
    }
    assert!(!out.exists());
}

/// Whether a CUDA GPU is visible (then `--device cuda:0` may legitimately succeed).
fn candle_core_cuda_available() -> bool {
    Path::new("/dev/nvidia0").exists()
}

/// `shared_dir()/reference/dav2`.
///
/// # Panics
/// As [`shared_dir`]; when it has no `vits-rel.safetensors`.
fn dav2_reference() -> PathBuf {
    let dir = shared_dir().join("reference/dav2");
    assert!(
        dir.join("vits-rel.safetensors").is_file(),
        "{} not found (no vits-rel.safetensors)",
        dir.display()
    );
    dir
}

/// `moma predict` as a user runs it, on the reference image and the ViT-S reference weights
/// (random weights): the written prediction is the official full-image output.
#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn predict_reproduces_the_official_full_image_output() {
    let dir = dav2_reference();
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("pred");
    let stdout = ok(&[
        "predict",
        "--weights",
        s(&dir.join("vits-rel.safetensors")),
        "--model",
        "vits",
        "--device",
        "cpu",
        s(&dir.join("input.png")),
        "-o",
        s(&out),
        "--json",
    ]);
    let index: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(index["prediction_kind"], "relative-disparity");
    assert_eq!(index["version"], moma_io::PREDICTIONS_VERSION);
    assert_eq!(index["model"]["backbone"], "vits");
    assert!(
        index["runtime"].as_str().unwrap().starts_with("candle"),
        "{index}"
    );
    // the labels `moma simulate`'s index has: a depth model's output, and which
    assert_eq!(index["simulated"], false);
    let source = index["source"].as_str().unwrap();
    assert!(
        source.starts_with("Depth Anything V2 ViT-S (relative head), weights ")
            && source.contains("vits"),
        "{index}"
    );
    assert!(out.join("input.color.png").is_file());
    let on_disk: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("predictions.json")).unwrap())
            .unwrap();
    assert_eq!(on_disk, index);

    let got = moma_io::read_prediction(
        out.join("input.npy"),
        moma_core::PredictionKind::RelativeDisparity,
    )
    .unwrap()
    .values;
    let want: ndarray::Array2<f32> =
        ndarray_npy::read_npy(dir.join("vits-rel.output_full.npy")).unwrap();
    assert_eq!(got.dim(), want.dim());
    let range = want.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b))
        - want.iter().fold(f32::INFINITY, |a, &b| a.min(b));
    let err = got
        .iter()
        .zip(&want)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    eprintln!(
        "moma predict vs official output_full: max abs err {err:.3e} ({:.3e} of range)",
        err / range
    );
    assert!(err / range < 1e-3, "{err} of range {range}");
}

/// The `error: ` line of a failed run, split at ": " into the parts of its chain.
fn error_parts(stderr: &str) -> (String, Vec<String>) {
    let line = stderr
        .lines()
        .find(|l| l.starts_with("error: "))
        .unwrap_or_else(|| panic!("no error line in:\n{stderr}"));
    let parts = line["error: ".len()..]
        .split(": ")
        .map(str::to_string)
        .collect();
    (line.to_string(), parts)
}

fn assert_each_part_once(line: &str, parts: &[String]) {
    for (i, p) in parts.iter().enumerate() {
        assert!(!parts[i + 1..].contains(p), "'{p}' repeated in: {line}");
    }
}

/// A nested error prints each part of its chain once: a corrupt file inside a set (set, frame,
/// file and the decoder's reason), and a missing file (the file, then the operating system's
/// reason).
#[test]
fn nested_errors_print_each_part_once() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    // frame_01's depth map cut in half: the set lists it, decoding it fails.
    let depth = scene.join("frames/frame_01/depth.png");
    let bytes = std::fs::read(&depth).unwrap();
    std::fs::write(&depth, &bytes[..bytes.len() / 2]).unwrap();
    let err = fails(&[
        "eval",
        "--set",
        s(&scene),
        "--simulate",
        "-o",
        s(&tmp.path().join("out")),
    ]);
    let (line, parts) = error_parts(&err);
    assert!(parts.len() >= 3, "{line}");
    assert_each_part_once(&line, &parts);
    assert_eq!(line.matches(s(&depth)).count(), 1, "{line}");
    assert!(line.contains("frame_01") && line.contains("PNG"), "{line}");

    // A missing ground-truth file: the path once, the OS reason once, as the last part.
    let missing = tmp.path().join("no-such-depth.png");
    let err = fails(&[
        "calibrate",
        "--pred",
        s(&pred.join("frame_00.npy")),
        "--pred-kind",
        "relative-disparity",
        "--gt",
        s(&missing),
        "-o",
        s(&tmp.path().join("c.json")),
    ]);
    let (line, parts) = error_parts(&err);
    assert_each_part_once(&line, &parts);
    assert_eq!(line.matches(s(&missing)).count(), 1, "{line}");
    assert_eq!(line.matches("os error 2").count(), 1, "{line}");
    assert!(
        parts.last().is_some_and(|p| p.contains("os error 2")),
        "{line}"
    );
}

/// `--samples` beyond the limit is refused with the limit named (not an overflow or a huge
/// allocation), for both sampling strategies.
#[test]
fn huge_sample_counts_fail_clearly() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    for sampling in ["random", "grid"] {
        let calib = tmp.path().join(format!("calib-{sampling}.json"));
        let err = fails(&[
            "calibrate",
            "--pred",
            s(&pred.join("frame_00.npy")),
            "--pred-kind",
            "relative-disparity",
            "--gt",
            s(&scene.join("frames/frame_00/depth.png")),
            "--samples",
            "18446744073709551615",
            "--sampling",
            sampling,
            "-o",
            s(&calib),
        ]);
        assert!(
            err.contains("18446744073709551615") && err.contains("exceeds the limit of 10000 ("),
            "{err}"
        );
        assert!(!calib.exists());
    }
    // a huge seed count is refused by every command that evaluates, not allocated and aborted
    let set = s(&scene).to_string();
    let preds = s(&pred).to_string();
    for cmd in [
        vec!["eval", "--set", &set, "--pred", &preds],
        vec!["ablate", "norm", "--set", &set, "--pred", &preds],
        vec!["grasp-eval", "--set", &set, "--pred", &preds],
    ] {
        let mut args = cmd.clone();
        args.extend(["--methods", "ssra", "--seeds", "1000000000000"]);
        let err = fails(&args);
        assert!(
            err.contains("--seeds 1000000000000 is more than the limit of 10000"),
            "{cmd:?}: {err}"
        );
    }
}

/// `calibrate --edge-margin-px`: every stored sample lies more than the margin from a depth
/// discontinuity of the ground truth (checked here with a 5 % jump, stricter than the library's
/// 3 %); a margin that leaves no pixel fails naming it and writes no file; `eval` takes it too.
#[test]
fn edge_margin_keeps_samples_off_object_boundaries() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let gt_png = scene.join("frames/frame_00/depth.png");
    let gt = moma_io::read_depth(&gt_png).unwrap().depth_m;
    let (h, w) = (gt.nrows() as i64, gt.ncols() as i64);
    let z = |v: i64, u: i64| gt[[v as usize, u as usize]];
    let boundary = |v: i64, u: i64| {
        [(0, 1), (1, 0)].iter().any(|&(dv, du)| {
            let (vv, uu) = (v + dv, u + du);
            vv < h && uu < w && {
                let (a, b) = (z(v, u), z(vv, uu));
                a > 0.0 && b > 0.0 && (a - b).abs() > 0.05 * a.min(b)
            }
        })
    };
    let pred0 = pred.join("frame_00.npy");
    let calibrate = |margin: &'static str, out: &Path| {
        let mut args = vec![
            "calibrate",
            "--pred",
            s(&pred0),
            "--pred-kind",
            "relative-disparity",
        ];
        args.extend([
            "--gt",
            s(&gt_png),
            "--samples",
            "400",
            "--edge-margin-px",
            margin,
        ]);
        args.extend(["-o", s(out)]);
        args.into_iter().map(String::from).collect::<Vec<_>>()
    };
    let samples_of = |margin: &'static str| -> Vec<(i64, i64)> {
        let calib = tmp.path().join(format!("calib-{margin}.json"));
        ok(&calibrate(margin, &calib)
            .iter()
            .map(String::as_str)
            .collect::<Vec<_>>());
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&calib).unwrap()).unwrap();
        v["calibration"]["samples"]["samples"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| {
                (
                    p["v"].as_f64().unwrap() as i64,
                    p["u"].as_f64().unwrap() as i64,
                )
            })
            .collect()
    };
    // within 3 px of a boundary pixel or its lower/right neighbour
    let near = |(v, u): (i64, i64)| {
        (v - 4..=v + 3).any(|vv| {
            (u - 4..=u + 3).any(|uu| vv >= 0 && uu >= 0 && vv < h && uu < w && boundary(vv, uu))
        })
    };
    assert!(
        samples_of("0").into_iter().any(near),
        "the demo scene has boundaries"
    );
    let kept = samples_of("3");
    assert_eq!(kept.len(), 400);
    assert!(!kept.into_iter().any(near));

    let calib = tmp.path().join("none.json");
    let err = fails(
        &calibrate("100000", &calib)
            .iter()
            .map(String::as_str)
            .collect::<Vec<_>>(),
    );
    assert!(err.contains("edge margin of 100000 px"), "{err}");
    assert!(!calib.exists());

    let out = tmp.path().join("eval");
    let rows = common::eval_rows(
        &scene,
        &pred,
        &out,
        &["--methods", "gssa", "--seeds", "2", "--edge-margin-px", "3"],
    );
    assert_eq!(rows.len(), 1, "{rows:?}");
    // the table says how the samples were drawn, and results.json records it
    let md = std::fs::read_to_string(out.join("results.md")).unwrap();
    assert!(
        md.contains("n = 100 samples (more than 3 px from depth edges)"),
        "{md}"
    );
    let full: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("results.json")).unwrap()).unwrap();
    assert_eq!(full[0]["edge_margin_px"], 3);
}

#[test]
fn a_misspelt_simulator_setting_is_an_error_not_ignored() {
    // `--sim-config` reads any subset of the simulator's strengths; a misspelt name used to be
    // dropped silently, so the run used the default the user meant to change.
    let tmp = tempfile::tempdir().unwrap();
    let (scene, _) = demo(tmp.path());
    let cfg = tmp.path().join("sim.json");
    let out = tmp.path().join("pred");
    let args = [
        "simulate",
        "--set",
        s(&scene),
        "--sim-config",
        s(&cfg),
        "-o",
        s(&out),
    ];
    std::fs::write(&cfg, r#"{"frame_fluctuaton": 0.1}"#).unwrap();
    let err = fails(&args);
    assert!(
        err.contains("sim.json") && err.contains("frame_fluctuaton"),
        "{err}"
    );
    assert!(!out.exists());
    std::fs::write(&cfg, r#"{"frame_fluctuation": 0.1}"#).unwrap();
    ok(&args);
}

#[test]
fn a_brightness_too_dark_for_the_simulated_response_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, _) = demo(tmp.path());
    let err = fails(&[
        "eval",
        "--set",
        s(&scene),
        "--simulate",
        "--methods",
        "gssa",
        "--seeds",
        "1",
        "--realign",
        "anchors",
        "--brightness",
        "1e-30",
    ]);
    assert!(
        err.contains("brightness factor") && err.contains("too dark") && err.contains("4.540e-5"),
        "{err}"
    );
}

#[test]
fn demo_frame_counts_outside_2_to_100_are_refused() {
    // 0 and 1 used to become 2 silently; 100 000 rendered for minutes; past 100 the frame ids
    // (`frame_{i:02}`) no longer sort in frame order.
    let tmp = tempfile::tempdir().unwrap();
    for n in ["0", "1", "101", "100000"] {
        let err = fails(&["demo", "-o", s(&tmp.path().join("d")), "--frames", n]);
        assert!(err.contains("--frames") && err.contains("2..=100"), "{err}");
    }
    assert!(!tmp.path().join("d").exists());
    // the evaluation's settings too are checked before the scene is written
    for (flag, value, says) in [
        ("--samples", "0", "--samples"),
        ("--gt-outliers", "2", "--gt-outliers"),
        ("--seeds", "1000000", "--seeds"),
    ] {
        let err = fails(&["demo", "-o", s(&tmp.path().join("d")), flag, value]);
        assert!(err.contains(says), "{flag} {value}: {err}");
        assert!(!tmp.path().join("d").exists(), "{flag} {value}");
    }
}

/// `grasp-eval` shares `eval`'s options and variants (re-alignment, robust fits, few-shot; see
/// tests/grasp_robust.rs); what it cannot score is refused, and ground-truth outliers, which it
/// applies, are named in every row's source. Every object region below --min-object-px is an
/// error too (it used to give 0 trials and a "NaN %" success rate).
#[test]
fn grasp_eval_refuses_what_it_cannot_score_and_labels_outliers() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, _) = demo(tmp.path());
    let out = tmp.path().join("ge");
    for (extra, expected) in [
        (
            &["--calib-frames", "2", "--robust", "huber"][..],
            ["few-shot", "does not combine"],
        ),
        (&["--grasp-draws", "0"][..], ["--grasp-draws", "at least 1"]),
        (
            &["--norm", "minmax,median"][..],
            ["--norm", "one normalisation"],
        ),
        (
            &["--min-object-px", "100000000"][..],
            ["no object region of at least 100000000 px", "'scene'"],
        ),
    ] {
        let err = fails(&grasp_eval_args(&[&scene], &out, extra));
        assert!(expected.iter().all(|e| err.contains(e)), "{extra:?}: {err}");
        assert!(!out.join("grasp_results.json").exists());
    }
    let rows: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string({
            ok(&grasp_eval_args(&[&scene], &out, &["--gt-outliers", "0.2"]));
            out.join("grasp_results.json")
        })
        .unwrap(),
    )
    .unwrap();
    let rows = rows.as_array().unwrap();
    let gssa: Vec<&serde_json::Value> = rows.iter().filter(|r| r["method"] == "gssa").collect();
    assert!(!gssa.is_empty());
    for r in gssa {
        let source = r["source"].as_str().unwrap();
        assert!(
            source.contains("SIMULATED") && source.contains("20.0 % SIMULATED outliers"),
            "{source}"
        );
    }
    let md = std::fs::read_to_string(out.join("grasp_results.md")).unwrap();
    assert!(md.contains("20.0 % SIMULATED outliers"), "{md}");
}

/// `moma COMMAND --help` prints the command's own documentation (its formats, protocol and
/// examples), not only the one-line summary of `moma --help`: a doc comment on the subcommand
/// variant used to replace it, which left "(JSON, see above)" in `grasp --help` pointing at
/// nothing.
#[test]
fn every_command_help_prints_its_long_documentation() {
    let cases: &[(&[&str], &str)] = &[
        (&["calibrate"], "each frame is normalised on its own"),
        (&["align"], "NAME.ply        with --ply"),
        (&["metrics"], "REL = mean |p−g|/g"),
        (&["predict"], "NAME.npy"),
        (&["simulate"], "viewpoint/intrinsics mismatch"),
        (&["eval"], "Protocol (docs/method.md §4)"),
        (&["ablate"], "ablation_<name>"),
        (&["grasp"], "camera_to_base"),
        (&["grasp-eval"], "8-connected component"),
        (&["demo"], "ray-cast exact depth"),
    ];
    for (cmd, marker) in cases {
        let mut args = cmd.to_vec();
        args.push("--help");
        let long = ok(&args);
        assert!(
            long.contains(marker),
            "`moma {} --help` lacks {marker:?}:\n{long}",
            cmd.join(" ")
        );
        // examples paste into a shell as printed: none re-wrapped (clap wraps at 100
        // columns), so no continuation backslash on a line of its own and no example command
        // line that the wrap split
        for line in long.lines() {
            assert!(
                line.trim() != "\\" && line.chars().count() <= 100,
                "`moma {} --help` has a wrapped line: {line:?}",
                cmd.join(" ")
            );
        }
    }
    // the overview keeps its one-line summaries
    let overview = ok(&["--help"]);
    assert!(overview.contains("Plan parallel-jaw or suction grasps"));
    assert!(!overview.contains("camera_to_base"));
}

/// A depth model's raw output is not metres: `metrics --pred` and `grasp --depth` refuse a `.npy`
/// that the `predictions.json` beside it lists (they used to score and plan on disparities as
/// if they were metres), and still take the aligned maps.
#[test]
fn raw_predictions_are_refused_where_metres_are_expected() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let frames = scene.join("frames");
    let raw = pred.join("frame_01.npy");
    let gt = frames.join("frame_01/depth.png");
    let err = fails(&["metrics", "--pred", s(&raw), "--gt", s(&gt)]);
    assert!(
        err.contains(s(&raw))
            && err.contains("raw SIMULATED relative-disparity prediction")
            && err.contains("not metres")
            && err.contains("moma align"),
        "{err}"
    );
    let err = fails(&[
        "grasp",
        "--depth",
        s(&raw),
        "--camera",
        s(&scene.join("camera.json")),
        "--gripper",
        "suction",
    ]);
    assert!(
        err.contains("not metres") && err.contains("--calib"),
        "{err}"
    );
    // a metric head's raw output (kind metric-depth) is nominally metres: read, with a note
    let metric = tmp.path().join("metric");
    std::fs::create_dir_all(&metric).unwrap();
    let depth = moma_io::read_depth(&gt).unwrap();
    moma_io::write_prediction(
        metric.join("f_01.npy"),
        &moma_core::Prediction::new(depth.depth_m, moma_core::PredictionKind::MetricDepth),
    )
    .unwrap();
    let index = |kind_and_more: &str| {
        std::fs::write(
            metric.join("predictions.json"),
            format!(
                r#"{{"format": "moma-predictions", "prediction_kind": {kind_and_more},
                    "frames": ["f_01"]}}"#
            ),
        )
        .unwrap()
    };
    // an old index's bare `depth` records no metric model: relative depth, refused as metres
    // (docs/formats.md "Prediction kinds") ...
    index(r#""depth""#);
    let err = fails(&[
        "metrics",
        "--pred",
        s(&metric.join("f_01.npy")),
        "--gt",
        s(&gt),
    ]);
    assert!(
        err.contains("relative-depth") && err.contains("not metres"),
        "{err}"
    );
    // ... unless its writer recorded a metric head (`moma predict`'s model spec)
    index(
        r#""depth", "model": {"backbone": "vits", "head": {"head": "metric", "max_depth_m": 20}}"#,
    );
    ok(&[
        "metrics",
        "--pred",
        s(&metric.join("f_01.npy")),
        "--gt",
        s(&gt),
    ]);
    index(r#""metric-depth""#);
    let out = moma(&[
        "metrics",
        "--pred",
        s(&metric.join("f_01.npy")),
        "--gt",
        s(&gt),
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stderr).contains("used as metres without calibration"));
    let m: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(m["mae"].as_f64().unwrap() < 1e-6, "{m}");
    assert_eq!(m["simulated"], false, "{m}");
    // listed as simulated: the numbers say so, as an evaluation's rows do
    index(r#""metric-depth", "simulated": true, "source": "SIMULATED""#);
    let m: serde_json::Value = serde_json::from_str(&ok(&[
        "metrics",
        "--pred",
        s(&metric.join("f_01.npy")),
        "--gt",
        s(&gt),
        "--json",
    ]))
    .unwrap();
    assert_eq!(m["simulated"], true, "{m}");
    // the same map once aligned is metres: accepted
    let calib = tmp.path().join("calib.json");
    calibrate_frame_00(&scene, &pred, &calib, &[]);
    let aligned = tmp.path().join("aligned");
    ok(&align_args(&calib, &raw, &aligned, &[]));
    let m: serde_json::Value = serde_json::from_str(&ok(&[
        "metrics",
        "--pred",
        s(&aligned.join("frame_01.depth.npy")),
        "--gt",
        s(&gt),
        "--json",
    ]))
    .unwrap();
    assert!(m["d125"].as_f64().unwrap() > 0.9, "{m}");
}

/// Provenance travels with the calibration: one fitted on SIMULATED predictions records it, and
/// `align` / `grasp` label what they produce with it; `grasp --calib` takes the intrinsics the
/// calibration records when no `--camera` is given, and plans exactly the same grasps.
#[test]
fn simulated_provenance_and_intrinsics_travel_with_the_calibration() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let camera = scene.join("camera.json");
    let calib = tmp.path().join("calib.json");
    calibrate_frame_00(&scene, &pred, &calib, &["--camera", s(&camera)]);
    let file: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&calib).unwrap()).unwrap();
    assert_eq!(file["created"]["simulated_predictions"], true);

    // a copy of the prediction without its predictions.json: only the calibration knows
    let loose = tmp.path().join("loose");
    std::fs::create_dir_all(&loose).unwrap();
    let frame1 = loose.join("frame_01.npy");
    std::fs::copy(pred.join("frame_01.npy"), &frame1).unwrap();
    let out = moma(&align_args(
        &calib,
        &frame1,
        &tmp.path().join("a"),
        &["--json"],
    ));
    assert!(out.status.success());
    let rows: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(rows[0]["simulated"], true);
    assert!(String::from_utf8_lossy(&out.stderr).contains("fitted on SIMULATED predictions"));

    let grasp = |extra: &[&str]| {
        let mut a = vec![
            "grasp",
            "--calib",
            s(&calib),
            "--pred",
            s(&frame1),
            "--gripper",
            "suction",
            "--top",
            "3",
            "--json",
        ];
        a.extend_from_slice(extra);
        moma(&a)
    };
    let with_camera = grasp(&["--camera", s(&camera)]);
    let without = grasp(&[]);
    assert!(with_camera.status.success() && without.status.success());
    assert_eq!(with_camera.stdout, without.stdout);
    let grasps: serde_json::Value = serde_json::from_slice(&without.stdout).unwrap();
    assert!(!grasps.as_array().unwrap().is_empty(), "{grasps}");
    assert!(String::from_utf8_lossy(&without.stderr).contains("SIMULATED predictions"));

    // a depth map carries no intrinsics
    let aligned = tmp.path().join("a").join("frame_01.depth.npy");
    let err = fails(&["grasp", "--depth", s(&aligned), "--gripper", "suction"]);
    assert!(err.contains("--camera camera.json is needed"), "{err}");

    // ... but the folder `align` wrote records its provenance: scored later, the depth is
    // SIMULATED, in the PNG as in the .npy
    let gt = scene.join("frames/frame_01/depth.png");
    let metrics = |depth: &Path| {
        let out = moma(&["metrics", "--pred", s(depth), "--gt", s(&gt), "--json"]);
        let err = String::from_utf8_lossy(&out.stderr).to_string();
        assert!(out.status.success(), "{err}");
        let m: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        (m["simulated"].as_bool().unwrap(), err)
    };
    let png = tmp.path().join("a").join("frame_01.depth.png");
    for depth in [&aligned, &png] {
        let (simulated, err) = metrics(depth);
        assert!(
            simulated && err.contains("SIMULATED") && err.contains("aligned.json"),
            "{err}"
        );
    }
    let index: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(tmp.path().join("a").join("aligned.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(index["format"], "moma-aligned");
    assert_eq!(index["files"][0]["file"], "frame_01.depth.png");
    assert_eq!(index["files"][1]["file"], "frame_01.depth.npy");
    assert_eq!(index["files"][0]["calibration"], s(&calib));
    // the pictures and maps made from that depth are recorded as SIMULATED too (only the files
    // asked for)
    let pictures = tmp.path().join("pictures");
    ok(&align_args(
        &calib,
        &frame1,
        &pictures,
        &["--colormap", "--sigma-map"],
    ));
    let index: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(pictures.join("aligned.json")).unwrap())
            .unwrap();
    let mut listed: Vec<&str> = index["files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            assert_eq!(f["simulated"], true, "{f}");
            f["file"].as_str().unwrap()
        })
        .collect();
    listed.sort_unstable();
    assert_eq!(
        listed,
        [
            "frame_01.color.png",
            "frame_01.depth.npy",
            "frame_01.depth.png",
            "frame_01.sigma.npy",
            "frame_01.sigma.png"
        ]
    );
    for f in &listed {
        assert!(pictures.join(f).is_file(), "{f} listed but not written");
    }
    // `grasp -o` writes the frame's depth with its provenance too
    let planned = tmp.path().join("planned");
    assert!(grasp(&["-o", s(&planned)]).status.success());
    let (simulated, err) = metrics(&planned.join("depth.npy"));
    assert!(simulated && err.contains("SIMULATED"), "{err}");
    // ... and its overlay says so, in its caption (the PNG's Description chunk holds its text)
    let caption = moma_io::read_png_description(planned.join("overlay.png"))
        .unwrap()
        .expect("a caption");
    assert!(
        caption.contains("SIMULATED predictions")
            && caption.contains("success_prob: PROXY, under the calibration's error model")
            && caption.contains("aligned by")
            && caption.contains("#1  success_prob"),
        "{caption}"
    );
    // a depth file of no recorded origin is not called SIMULATED, nor checked
    let plain = tmp.path().join("plain");
    let on_depth = moma(&[
        "grasp",
        "--depth",
        s(&gt),
        "--camera",
        s(&scene.join("camera.json")),
        "--gripper",
        "suction",
        "-o",
        s(&plain),
    ]);
    assert!(on_depth.status.success());
    let caption = moma_io::read_png_description(plain.join("overlay.png"))
        .unwrap()
        .expect("a caption");
    assert!(
        !caption.contains("SIMULATED predictions (")
            && caption.contains("no record of its origin says SIMULATED")
            && caption.contains("success_prob: n/a (no error model)"),
        "{caption}"
    );
    // the same frame name aligned again into that folder from a sensor's metres (no index, a
    // calibration on them): its entry is replaced, the depth is not simulated
    let metres = tmp.path().join("metres");
    std::fs::create_dir_all(&metres).unwrap();
    for id in ["00", "01"] {
        let d = moma_io::read_depth(scene.join(format!("frames/frame_{id}/depth.png"))).unwrap();
        moma_io::write_npy_f32(metres.join(format!("frame_{id}.npy")), d.depth_m.view()).unwrap();
    }
    let sensor_calib = tmp.path().join("sensor.json");
    ok(&[
        "calibrate",
        "--pred",
        s(&metres.join("frame_00.npy")),
        "--pred-kind",
        "metric-depth",
        "--gt",
        s(&scene.join("frames/frame_00/depth.png")),
        "-o",
        s(&sensor_calib),
    ]);
    ok(&align_args(
        &sensor_calib,
        &metres.join("frame_01.npy"),
        &tmp.path().join("a"),
        &[],
    ));
    let (simulated, err) = metrics(&aligned);
    assert!(!simulated && !err.contains("SIMULATED"), "{err}");
    // a run that fails on a frame records nothing for it: the earlier run's SIMULATED entry of
    // frame_01 stays beside the new frame_00
    let b = tmp.path().join("b");
    let text = ok(&align_args(&calib, &frame1, &b, &[]));
    // the summary names the normalisation (the default: the authors' code's)
    assert!(
        text.contains("with ssra (normalisation minmax-unit) into"),
        "{text}"
    );
    let small = tmp.path().join("small");
    std::fs::create_dir_all(&small).unwrap();
    moma_io::write_npy_f32(
        small.join("frame_01.npy"),
        ndarray::Array2::<f32>::from_elem((10, 10), 0.7).view(),
    )
    .unwrap();
    let err = fails(&[
        "align",
        "--calib",
        s(&sensor_calib),
        "--pred",
        s(&metres.join("frame_00.npy")),
        s(&small.join("frame_01.npy")),
        "-o",
        s(&b),
    ]);
    assert!(err.contains("frame_01.npy"), "{err}");
    assert!(
        metrics(&b.join("frame_01.depth.npy")).0,
        "the earlier run's label"
    );
    // ... and one whose write fails keeps the SIMULATED label of the file it did not replace
    std::fs::remove_file(b.join("frame_01.depth.png")).unwrap();
    std::fs::create_dir(b.join("frame_01.depth.png")).unwrap();
    fails(&align_args(
        &sensor_calib,
        &metres.join("frame_01.npy"),
        &b,
        &[],
    ));
    let (simulated, err) = metrics(&b.join("frame_01.depth.npy"));
    assert!(simulated && err.contains("SIMULATED"), "{err}");
    // `grasp --depth` of that depth: its SIMULATED label follows into grasp -o's folder
    let replanned = tmp.path().join("replanned");
    let out = moma(&[
        "grasp",
        "--depth",
        s(&b.join("frame_01.depth.npy")),
        "--camera",
        s(&camera),
        "--gripper",
        "suction",
        "-o",
        s(&replanned),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && err.contains("SIMULATED"), "{err}");
    assert!(metrics(&replanned.join("depth.npy")).0);
    // another tool's aligned.json: `align` refuses to write beside it (left as it is), `metrics`
    // says the provenance is not known
    let foreign = tmp.path().join("a").join("aligned.json");
    std::fs::write(&foreign, r#"{"format": "something-else"}"#).unwrap();
    let err = fails(&align_args(&calib, &frame1, &tmp.path().join("a"), &[]));
    assert!(
        err.contains("aligned.json") && err.contains("another tool's file"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_to_string(&foreign).unwrap(),
        r#"{"format": "something-else"}"#
    );
    let (simulated, err) = metrics(&aligned);
    assert!(
        !simulated && err.contains("not moma's aligned-depth index"),
        "{err}"
    );
}

/// With several sets, one without any object region is noted (on stderr and in the table's
/// title) and skipped; the others are scored. It used to stop the whole run after the earlier
/// sets were done. With no set left, it is an error naming each.
#[test]
fn grasp_eval_skips_a_set_without_objects_among_several() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, _) = demo(tmp.path());
    // a copy of the scene whose masks select a 5 × 5 speck: below the 200 px of a trial
    let bare = tmp.path().join("bare");
    for entry in walk(&scene) {
        let rel = entry.strip_prefix(&scene).unwrap();
        let to = bare.join(rel);
        std::fs::create_dir_all(to.parent().unwrap()).unwrap();
        if to.file_name().unwrap() == "mask.png" {
            let m = moma_io::read_mask(&entry).unwrap();
            let speck =
                moma_core::Mask::new(ndarray::Array2::from_shape_fn(m.data().dim(), |(v, u)| {
                    (100..105).contains(&v) && (100..105).contains(&u)
                }));
            moma_io::write_mask(&to, &speck).unwrap();
        } else {
            std::fs::copy(&entry, &to).unwrap();
        }
    }
    let out = tmp.path().join("ge");
    let run = |sets: &[&Path]| moma(&grasp_eval_args(sets, &out, &["--json"]));
    let both = run(&[&scene, &bare]);
    let err = String::from_utf8_lossy(&both.stderr);
    assert!(both.status.success(), "{err}");
    assert!(
        err.contains("set 'bare': no object region") && err.contains("skipped"),
        "{err}"
    );
    let rows: serde_json::Value = serde_json::from_slice(&both.stdout).unwrap();
    let sets: Vec<&str> = rows
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["set"].as_str().unwrap())
        .collect();
    assert!(
        !sets.is_empty() && sets.iter().all(|&s| s == "scene"),
        "{sets:?}"
    );
    let md = std::fs::read_to_string(out.join("grasp_results.md")).unwrap();
    assert!(md.contains("skipped: set 'bare'"), "{md}");
    // nothing left: an error naming the set, and no table written
    std::fs::remove_dir_all(&out).unwrap();
    let bare2 = linked_copy(&bare, &tmp.path().join("bare2"));
    let none = run(&[&bare, &bare2]);
    assert!(!none.status.success());
    assert!(String::from_utf8_lossy(&none.stderr).contains("no set has anything to grasp"));
    assert!(!out.exists());
}

/// `grasp-eval` on `sets` with SIMULATED predictions, GSSA, one seed, the suction cup, into
/// `out`, followed by `extra`.
fn grasp_eval_args<'a>(sets: &[&'a Path], out: &'a Path, extra: &[&'a str]) -> Vec<&'a str> {
    let mut a = vec!["grasp-eval"];
    for set in sets {
        a.extend(["--set", s(set)]);
    }
    a.extend([
        "--simulate",
        "--methods",
        "gssa",
        "--seeds",
        "1",
        "--gripper",
        "suction",
        "-o",
        s(out),
    ]);
    a.extend_from_slice(extra);
    a
}

/// Every file under `dir`, recursively.
fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            files.extend(walk(&p));
        } else {
            files.push(p);
        }
    }
    files
}

/// `moma calibrate` says how far its samples reach (`sample_reach` in `--json`), and warns when
/// they leave part of the image beyond reach, where the alignment extrapolates: samples
/// drawn in the left half of the demo scene against samples spread over it.
#[test]
fn calibrate_warns_when_its_samples_reach_part_of_the_image() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let calib = tmp.path().join("calib.json");
    let reach = |out: &str| {
        let v: serde_json::Value = serde_json::from_str(out).unwrap();
        let r = &v["sample_reach"];
        (
            r["p90_px"].as_f64().unwrap(),
            r["uniform_p90_px"].as_f64().unwrap(),
            r["partial"].as_bool().unwrap(),
        )
    };
    let (p90, uniform, partial) = reach(&calibrate_frame_00(&scene, &pred, &calib, &["--json"]));
    assert!(
        !partial && p90 < 1.5 * uniform,
        "{p90} px against {uniform} px"
    );

    let gt = scene.join("frames/frame_00/depth.png");
    let (w, h) = image::image_dimensions(&gt).unwrap();
    let left = tmp.path().join("left.png");
    image::GrayImage::from_fn(w, h, |u, _| image::Luma([if u < w / 2 { 255 } else { 0 }]))
        .save(&left)
        .unwrap();
    let frame = pred.join("frame_00.npy");
    let args = [
        "calibrate",
        "--pred",
        s(&frame),
        "--gt",
        s(&gt),
        "--mask",
        s(&left),
        "-o",
        s(&calib),
        "--json",
    ];
    let out = moma(&args);
    assert!(out.status.success());
    let (p90, uniform, partial) = reach(&String::from_utf8(out.stdout).unwrap());
    // the right half lies up to w/2 from the samples: 90 % of the pixels within about 0.4 w
    assert!(
        partial && p90 > 0.3 * f64::from(w),
        "{p90} px against {uniform} px"
    );
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(
        err.contains("warning: the 100 calibration samples reach only part of the image")
            && err.contains("--mask"),
        "{err}"
    );
    // the calibration fitted the error model's distance part, and the warning says how far σ
    // grows
    let file: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&calib).unwrap()).unwrap();
    let gain = file["calibration"]["error_model"]["sample_distance_gain"]
        .as_f64()
        .unwrap_or(0.0);
    assert!(gain > 0.0, "{}", file["calibration"]["error_model"]);
    assert!(
        err.contains("grows from") && err.contains(&format!("{p90:.0} px away")),
        "{err}"
    );
}

/// What an evaluation would silently mix up is refused, naming it: two sets of one name (their
/// rows and folders would be one), a prediction file the folder's index does not list (left by
/// another run, its kind unknown), two sources of predictions, a set's missing predictions
/// folder, a repeated list value, a negative depth range. (An audit of the commands found each.)
#[test]
fn evaluations_refuse_what_they_would_mix_up() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let (sc, pr) = (s(&scene).to_string(), s(&pred).to_string());
    // a second set folder of the same name
    let dup = tmp.path().join("dup");
    std::fs::create_dir(&dup).unwrap();
    linked_copy(&scene, &dup.join("scene"));
    let dup_scene = s(&dup.join("scene")).to_string();
    let out = s(&tmp.path().join("sim")).to_string();
    let e = fails(&["simulate", "--set", &sc, "--set", &dup_scene, "-o", &out]);
    assert!(e.contains("both named 'scene'"), "{e}");
    assert!(!tmp.path().join("sim").exists());
    for cmd in ["eval", "grasp-eval"] {
        let e = fails(&[cmd, "--set", &sc, "--set", &dup_scene, "--simulate"]);
        assert!(e.contains("both named 'scene'"), "{cmd}: {e}");
    }
    let e = fails(&[
        "ablate",
        "norm",
        "--set",
        &sc,
        "--set",
        &dup_scene,
        "--simulate",
    ]);
    assert!(e.contains("both named 'scene'"), "{e}");

    let eo = s(&tmp.path().join("eval-bad")).to_string();
    let eval = |extra: &[&str]| {
        let mut a = vec![
            "eval",
            "--set",
            &sc,
            "--methods",
            "ssra",
            "--seeds",
            "1",
            "-o",
            &eo,
        ];
        a.extend_from_slice(extra);
        a.iter().map(|x| x.to_string()).collect::<Vec<_>>()
    };
    let run = |a: Vec<String>| fails(&a.iter().map(String::as_str).collect::<Vec<_>>());
    // a frame the index does not list: refused, not read with the index's kind
    let partial = tmp.path().join("partial");
    std::fs::create_dir(&partial).unwrap();
    for f in std::fs::read_dir(&pred).unwrap() {
        let f = f.unwrap().path();
        std::fs::copy(&f, partial.join(f.file_name().unwrap())).unwrap();
    }
    let index = partial.join("predictions.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&index).unwrap()).unwrap();
    let frames = v["frames"]
        .as_array_mut()
        .expect("the index lists its frames");
    frames.retain(|f| f.as_str() != Some("frame_01") && f["name"].as_str() != Some("frame_01"));
    std::fs::write(&index, v.to_string()).unwrap();
    let e = run(eval(&["--pred", s(&partial)]));
    assert!(
        e.contains("frame_01.npy is not listed in") && e.contains("predictions.json"),
        "{e}"
    );
    // two sources of predictions
    let e = run(eval(&["--pred", &pr, "--weights", "w.safetensors"]));
    assert!(e.contains("does not combine with --pred"), "{e}");
    // one --pred root for two sets, one of whose folders is missing
    let other = linked_copy(&scene, &tmp.path().join("other"));
    let root = tmp.path().join("root");
    std::fs::create_dir(&root).unwrap();
    std::os::unix::fs::symlink(&pred, root.join("scene")).unwrap();
    let o = moma(&[
        "eval",
        "--set",
        &sc,
        "--set",
        s(&other),
        "--pred",
        s(&root),
        "--methods",
        "ssra",
        "--seeds",
        "1",
        "-o",
        s(&tmp.path().join("eval-out")),
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        e.contains("no predictions folder")
            && e.contains("set 'other'")
            && e.contains("ROOT/<set name>"),
        "{e}"
    );
    // repeated values and a negative range
    let e = run(eval(&["--pred", &pr, "--robust", "huber,huber"]));
    assert!(e.contains("--robust names huber twice"), "{e}");
    let e = run(eval(&["--pred", &pr, "--max-gt-depth", "-1"]));
    assert!(
        e.contains("--max-gt-depth -1 must be a depth in metres"),
        "{e}"
    );
}

/// A set folder `to` of its own name whose entries link to `from`'s (a second set with the
/// same content; a link to `from` itself would resolve to `from`'s name).
fn linked_copy(from: &Path, to: &Path) -> PathBuf {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap().path();
        std::os::unix::fs::symlink(&e, to.join(e.file_name().unwrap())).unwrap();
    }
    to.to_path_buf()
}

/// What `calibrate` and `align` would have ignored or misread is refused before anything is
/// written (an audit found each accepted with exit 0): a calibration whose cross-validation
/// fails replaced the earlier file; ground truth in millimetres as float `.npy`; depth-model
/// options beside `--pred`; `--cv-loss` for LWLR; `--realign-rgb` / `--ply-rgb` with `--rgb`;
/// `--range-m` without `--colormap`, `--camera` without `--ply`; a prediction its folder's index
/// does not list.
#[test]
fn calibrate_and_align_refuse_what_they_would_ignore_or_misread() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let calib = tmp.path().join("calib.json");
    calibrate_frame_00(&scene, &pred, &calib, &[]);
    let good = std::fs::read(&calib).unwrap();
    let (p0, gt0) = (
        pred.join("frame_00.npy"),
        scene.join("frames/frame_00/depth.png"),
    );
    let calibrate = |extra: &[&str]| {
        let mut a = vec![
            "calibrate",
            "--pred",
            s(&p0),
            "--gt",
            s(&gt0),
            "-o",
            s(&calib),
        ];
        a.extend_from_slice(extra);
        fails(&a)
    };
    // 4 samples fit SSRA exactly but cannot be cross-validated: the earlier file stays
    let e = calibrate(&["--samples", "4"]);
    assert!(
        e.contains("nothing written") && e.contains("too few"),
        "{e}"
    );
    assert_eq!(
        std::fs::read(&calib).unwrap(),
        good,
        "the earlier calibration is kept"
    );
    // ground truth of millimetres in a float .npy
    let gt = moma_io::read_depth(&gt0).unwrap();
    let mm = tmp.path().join("gt_mm.npy");
    moma_io::write_depth(
        &mm,
        &moma_core::MetricDepth::new(gt.depth_m.mapv(|z| z * 1000.0)),
    )
    .unwrap();
    let e = fails(&[
        "calibrate",
        "--pred",
        s(&p0),
        "--gt",
        s(&mm),
        "-o",
        s(&calib),
    ]);
    assert!(
        e.contains("gt_mm.npy") && e.contains("looks like millimetres"),
        "{e}"
    );
    // depth-model options with --pred files, and CV settings for LWLR
    for (extra, says) in [
        (
            &["--weights", "/nonexistent.pth"][..],
            "--weights: depth-model options",
        ),
        (&["--head", "metric"][..], "--head: depth-model options"),
        (
            &["--input-size", "56", "--lora", "x"][..],
            "--input-size, --lora: depth-model",
        ),
        (
            &["--method", "lwlr", "--cv-loss", "rel"][..],
            "ssra-local, gssa-local and auto only, not lwlr",
        ),
    ] {
        let e = calibrate(extra);
        assert!(e.contains(says), "{extra:?}: {e}");
    }
    assert_eq!(std::fs::read(&calib).unwrap(), good);
    // raw values in the tens of thousands under the paper's minmax (which adds z_min back):
    // SSRA's features are degenerate, and the message says which normalisation fits them
    let raw: ndarray::Array2<f32> = ndarray_npy::read_npy(&p0).unwrap();
    let big = tmp.path().join("big.npy");
    ndarray_npy::write_npy(&big, &raw.mapv(|z| z * 30_000.0)).unwrap();
    let mut big_args = vec![
        "calibrate",
        "--pred",
        s(&big),
        "--gt",
        s(&gt0),
        "-o",
        s(&calib),
    ];
    big_args.extend(["--pred-kind", "relative-disparity", "--method", "ssra"]);
    let mut paper = big_args.clone();
    paper.extend(["--norm", "minmax"]);
    let e = fails(&paper);
    assert!(
        e.contains("linearly dependent") && e.contains("minmax-unit"),
        "{e}"
    );
    // the default, minmax-unit, fits them
    ok(&big_args);

    // align: flags that need another flag, or that --rgb inputs replace
    let out = tmp.path().join("aligned");
    let p1 = pred.join("frame_01.npy");
    let align = |extra: &[&str]| {
        let mut a = vec![
            "align",
            "--calib",
            s(&calib),
            "--pred",
            s(&p1),
            "-o",
            s(&out),
        ];
        a.extend_from_slice(extra);
        fails(&a)
    };
    let rgb = scene.join("frames/frame_01/rgb.png");
    for (extra, says) in [
        (&["--range-m", "0.4,1.2"][..], "--colormap"),
        (&["--camera", s(&scene.join("camera.json"))][..], "--ply"),
        (&["--device", "cpu"][..], "--device: depth-model options"),
    ] {
        let e = align(extra);
        assert!(e.contains(says), "{extra:?}: {e}");
    }
    for flag in ["--realign-rgb", "--ply-rgb"] {
        let mut a = vec![
            "align",
            "--calib",
            s(&calib),
            "--rgb",
            s(&rgb),
            "-o",
            s(&out),
        ];
        a.extend(["--realign", "anchors", "--ply", flag, s(&rgb)]);
        let e = fails(&a);
        assert!(e.contains(flag) && e.contains("--rgb"), "{flag}: {e}");
    }
    // a prediction beside an index that does not list it
    let extra = pred.join("zz_extra.npy");
    std::fs::copy(&p1, &extra).unwrap();
    let e = fails(&[
        "align",
        "--calib",
        s(&calib),
        "--pred",
        s(&extra),
        "-o",
        s(&out),
    ]);
    assert!(
        e.contains("zz_extra.npy is not listed in") && e.contains("--pred-kind"),
        "{e}"
    );
    assert!(!out.exists(), "nothing written");
    // the kind stated, it is read with a note (tests/align_batch.rs aligns copies that way)
    let o = moma(&[
        "align",
        "--calib",
        s(&calib),
        "--pred",
        s(&extra),
        "--pred-kind",
        "relative-disparity",
        "-o",
        s(&out),
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{e}");
    assert!(
        e.contains("zz_extra.npy is not listed in") && e.contains("read as --pred-kind"),
        "{e}"
    );
    assert!(out.join("zz_extra.depth.npy").is_file());
}

/// `ros2-replay`'s timing values become `Duration`s: a value no `Duration` holds is an error
/// naming the flag, before any network is touched (1e30 s panicked).
#[test]
fn replay_timing_beyond_a_duration_is_an_error() {
    for (flag, value, says) in [
        (
            "--warmup-s",
            "1e30",
            "--warmup-s 1000000000000000000000000000000 must be",
        ),
        ("--warmup-s", "-1", "--warmup-s -1 must be"),
        ("--warmup-s", "NaN", "--warmup-s NaN must be"),
        (
            "--rate",
            "1e-30",
            "--rate 0.000000000000000000000000000001 must be",
        ),
        // a period that a Duration holds but an Instant cannot add
        ("--rate", "1e-19", "--rate 0.0000000000000000001 must be"),
        ("--rate", "0", "--rate 0 must be"),
        ("--rate", "inf", "--rate inf must be"),
    ] {
        let e = common::fails(&["ros2-replay", "--set", "no-such-set", flag, value]);
        assert!(e.contains(says), "{flag} {value}: {e}");
        assert!(!e.contains("panicked"), "{e}");
    }
}

/// A second demo into the same folder replaces the first: a run of fewer frames left the other
/// frames' files beside the new ones (and `moma eval` on the folder then refused a prediction
/// its index did not list). A folder with files of its own is refused and left as it is.
#[test]
fn demo_replaces_an_earlier_demo_and_refuses_a_foreign_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().join("d");
    let run = |frames: &str| {
        ok(&[
            "demo",
            "-o",
            s(&d),
            "--frames",
            frames,
            "--seeds",
            "1",
            "--no-exports",
        ])
    };
    run("3");
    assert!(d.join("predictions/frame_02.npy").is_file());
    run("2");
    for stale in [
        "predictions/frame_02.npy",
        "scene/frames/frame_02",
        "figures/frame_02.png",
    ] {
        assert!(!d.join(stale).exists(), "{stale} left by the earlier demo");
    }
    let (scene, pred, eval) = (
        d.join("scene"),
        d.join("predictions"),
        tmp.path().join("eval"),
    );
    common::eval_rows(&scene, &pred, &eval, &["--seeds", "1", "--methods", "gssa"]);
    // an earlier demo's scene as this run's input: refused, nothing removed
    let e = fails(&[
        "demo",
        "--set",
        s(&d.join("scene")),
        "--pred",
        s(&d.join("predictions")),
        "-o",
        s(&d),
        "--seeds",
        "1",
    ]);
    assert!(e.contains("holds this run's input"), "{e}");
    assert!(d.join("scene/camera.json").is_file() && d.join("predictions").is_dir());
    let mine = tmp.path().join("mine");
    std::fs::create_dir_all(&mine).unwrap();
    std::fs::write(mine.join("notes.txt"), "keep").unwrap();
    let e = fails(&["demo", "-o", s(&mine), "--frames", "2", "--seeds", "1"]);
    assert!(e.contains("holds notes.txt"), "{e}");
    assert_eq!(std::fs::read_dir(&mine).unwrap().count(), 1);
}

/// One source of predictions, and no option of another: a depth-model option beside the
/// simulator or --pred folders, a simulator option beside --pred, --pred-kind without --pred
/// are refused by name (they were ignored).
#[test]
fn prediction_options_of_an_unused_source_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let eval = |extra: &[&str]| -> String {
        let mut args = vec![
            "eval",
            "--set",
            s(&scene),
            "--seeds",
            "1",
            "--methods",
            "gssa",
        ];
        args.extend_from_slice(extra);
        fails(&args)
    };
    for (extra, says) in [
        (
            &["--pred", s(&pred), "--lora", "a.safetensors"][..],
            "--lora",
        ),
        (&["--simulate", "--dtype", "int8"][..], "--dtype"),
        (&["--simulate", "--hub", "vits"][..], "does not combine"),
        (&["--pred", s(&pred), "--sim-seed", "3"][..], "--sim-seed"),
        (&["--pred", s(&pred), "--off", "bumps"][..], "--off"),
        (
            &["--simulate", "--pred-kind", "metric-depth"][..],
            "--pred-kind",
        ),
    ] {
        let e = eval(extra);
        assert!(e.contains(says), "{extra:?}: {e}");
    }
    // ablate source: its sources are --source folders or the simulator's two kinds
    let src = format!("p:relative-disparity:{}", s(&pred));
    for (extra, says) in [
        (
            vec!["--pred", s(&pred)],
            "--pred, --pred-kind and --simulate do not apply",
        ),
        (vec!["--lora", "a.safetensors"], "--lora"),
        (vec!["--sim-kind", "metric-depth"], "simulates both kinds"),
        (vec!["--source", &src, "--off", "bumps"], "--off"),
    ] {
        let abl = tmp.path().join("abl");
        let mut args = vec!["ablate", "source", "--set", s(&scene), "--seeds", "1"];
        args.extend(["-o", s(&abl)]);
        args.extend(extra.iter().copied());
        let e = fails(&args);
        assert!(e.contains(says), "{extra:?}: {e}");
    }
    for (extra, says) in [
        (&["--lora", "a.safetensors"][..], "--lora"),
        (&["--input-size", "28"][..], "--input-size"),
        (&["--pred-kind", "metric-depth"][..], "--pred-kind"),
        (&["--hub", "vits"][..], "simulated predictions only"),
    ] {
        let d2 = tmp.path().join("d2");
        let mut args = vec!["demo", "-o", s(&d2)];
        args.extend_from_slice(extra);
        let e = fails(&args);
        assert!(e.contains(says), "{extra:?}: {e}");
        assert!(!d2.exists(), "{extra:?}");
    }
}

/// A sample count that the method's fit allows but its cross-validation (one sample held out)
/// does not: the error says how many are needed and names the inputs (it said "need at least
/// 4" for 3 samples, then "need at least 5" for 4, and "gssa: 1" for LWLR).
#[test]
fn too_few_samples_to_cross_validate_say_how_many() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let (pred0, gt0) = common::demo_frame(&scene, &pred, 0);
    for (method, samples, need) in [("ssra", "4", "5"), ("gssa", "2", "3"), ("lwlr", "2", "3")] {
        let out = tmp.path().join(format!("{method}.json"));
        let e = fails(&common::calibrate_args(
            &[&pred0],
            &[&gt0],
            &["--method", method, "--samples", samples, "-o", s(&out)],
        ));
        assert!(
            e.contains(&format!("give at least {need} --samples"))
                && e.contains(&format!("{method} needs"))
                && e.contains("frame_00.npy"),
            "{method} {samples}: {e}"
        );
        assert!(!out.exists());
        // the count it asks for works
        let mut args = common::calibrate_args(
            &[&pred0],
            &[&gt0],
            &["--method", method, "--samples", need, "-o", s(&out)],
        );
        args.extend(["--seed", "1"]);
        ok(&args);
    }
}

/// A closed stdout (`moma calibrate … | head -1`) ends the program quietly: `println!` panicked on
/// the broken pipe, with a backtrace on stderr.
#[cfg(unix)]
#[test]
fn a_closed_stdout_ends_quietly() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let mut child = Command::new(env!("CARGO_BIN_EXE_moma"))
        .args([
            "calibrate",
            "--pred",
            s(&pred.join("frame_00.npy")),
            "--gt",
            s(&scene.join("frames/frame_00/depth.png")),
            "-o",
            s(&tmp.path().join("c.json")),
        ])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // the reader goes away before the calibration prints anything
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
    // ended by SIGPIPE, as `cat` would be, after the file was written
    use std::os::unix::process::ExitStatusExt;
    assert_eq!(out.status.signal(), Some(13), "{:?}", out.status);
    assert!(tmp.path().join("c.json").is_file());
}

/// Ctrl-C while outputs are being written: the program ends by the signal, as before, and
/// leaves no temporary file (`.NAME.XXXXXX.tmp`, tens of megabytes for an ASCII point cloud)
/// and no half-written output.
#[cfg(unix)]
#[test]
fn an_interrupted_run_leaves_no_temporary_files() {
    use std::os::unix::process::ExitStatusExt;
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let calib = tmp.path().join("calib.json");
    let camera = scene.join("camera.json");
    calibrate_frame_00(
        &scene,
        &pred,
        &calib,
        &["--pred-kind", "relative-disparity", "--camera", s(&camera)],
    );
    // 24 frames (copies of one) with ASCII point clouds: seconds of writing
    let inputs = tmp.path().join("inputs");
    std::fs::create_dir_all(&inputs).unwrap();
    let frames: Vec<PathBuf> = (0..24)
        .map(|k| {
            let p = inputs.join(format!("f{k:02}.npy"));
            std::fs::copy(pred.join("frame_01.npy"), &p).unwrap();
            p
        })
        .collect();
    let out = tmp.path().join("out");
    let temporaries = |dir: &Path| -> Vec<String> {
        std::fs::read_dir(dir)
            .map(|d| {
                d.filter_map(|e| e.ok())
                    .map(|e| e.file_name().to_string_lossy().into_owned())
                    .filter(|n| n.ends_with(".tmp"))
                    .collect()
            })
            .unwrap_or_default()
    };
    // `moma align` into `out`, `signal` sent while a point cloud is being written, with
    // `ignore` ignored by the child from its start (as `nohup` ignores SIGHUP)
    let interrupted = |out: &Path, signal: i32, ignore: Option<i32>| {
        use std::os::unix::process::CommandExt;
        let mut command = Command::new(env!("CARGO_BIN_EXE_moma"));
        command
            .args(["align", "--calib", s(&calib), "--pred"])
            .args(frames.iter().map(|p| s(p)))
            .args([
                "--pred-kind",
                "relative-disparity",
                "--ply",
                "--ply-ascii",
                "-o",
                s(out),
            ])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null());
        if let Some(ignored) = ignore {
            // SAFETY: signal(2) is async-signal-safe, as code between fork and exec must be.
            unsafe {
                command.pre_exec(move || {
                    libc::signal(ignored, libc::SIG_IGN);
                    Ok(())
                });
            }
        }
        let mut child = command.spawn().unwrap();
        let started = std::time::Instant::now();
        let seen = loop {
            if temporaries(out).iter().any(|n| n.contains(".ply.")) {
                break true;
            }
            if child.try_wait().unwrap().is_some() || started.elapsed().as_secs() > 120 {
                break false;
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        };
        assert!(
            seen,
            "the run ended before a point cloud's temporary file was seen"
        );
        // SAFETY: a signal to the child this test started and has not reaped.
        assert_eq!(unsafe { libc::kill(child.id() as i32, signal) }, 0);
        child.wait().unwrap()
    };
    // an ignored SIGHUP stays ignored: the run goes on to write every cloud
    let nohup = tmp.path().join("nohup");
    let status = interrupted(&nohup, libc::SIGHUP, Some(libc::SIGHUP));
    assert!(status.success(), "{status:?}");
    let clouds = std::fs::read_dir(&nohup)
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .path()
                .extension()
                .is_some_and(|x| x == "ply")
        })
        .count();
    assert_eq!(clouds, frames.len());
    // Ctrl-C: ended by the signal, no temporary file left
    let status = interrupted(&out, libc::SIGINT, None);
    assert_eq!(status.signal(), Some(libc::SIGINT), "{status:?}");
    assert_eq!(temporaries(&out), Vec::<String>::new());
    // every point cloud there is complete: as many vertices as its header says
    for entry in std::fs::read_dir(&out).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "ply") {
            let text = std::fs::read_to_string(&path).unwrap();
            let header_end = text.find("end_header\n").unwrap() + "end_header\n".len();
            let vertices: usize = text
                .lines()
                .find_map(|l| l.strip_prefix("element vertex "))
                .unwrap()
                .parse()
                .unwrap();
            assert_eq!(
                text[header_end..].lines().count(),
                vertices,
                "{}",
                path.display()
            );
        }
    }
}

/// A remap to a name ROS refuses fails at once, naming the character, before any DDS socket is
/// opened (the replay reads no set before it).
#[test]
fn a_bad_remap_fails_before_dds_starts() {
    for (remap, says) in [
        (
            "image:=/cam/image raw",
            "' ' is not allowed in a topic name",
        ),
        (
            "depth_sensor:=~/depth",
            "'~' is not allowed in a topic name",
        ),
    ] {
        let err = fails(&["ros2-replay", "--set", "/nonexistent", "--remap", remap]);
        assert!(err.contains(remap) && err.contains(says), "{err}");
        // the same rule as a launch file gives it
        let err = fails(&[
            "ros2-replay",
            "--set",
            "/nonexistent",
            "--ros-args",
            "-r",
            remap,
        ]);
        assert!(err.contains(remap) && err.contains(says), "{err}");
    }
    let err = fails(&["ros2-replay", "--set", "/x", "--ros-args", "--bogus"]);
    assert!(err.contains("\"--bogus\" is not a ROS 2 argument"), "{err}");
    let err = fails(&["ros2-replay", "--set", "/x", "--ros-args", "-r"]);
    assert!(err.contains("-r needs a value"), "{err}");
}

/// One glitched pixel of a prediction (far below the rest) moves a min-max normalised frame as
/// a whole, with no error: `moma align` and `moma grasp` name it (a note with the pixel and the
/// value); the clean frame gives no such note.
#[test]
fn align_and_grasp_name_a_glitched_pixel_the_normalisation_follows() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let calib = tmp.path().join("calib.json");
    let camera = scene.join("camera.json");
    calibrate_frame_00(&scene, &pred, &calib, &["--camera", s(&camera)]);
    let clean = pred.join("frame_01.npy");
    let mut values: ndarray::Array2<f32> = ndarray_npy::read_npy(&clean).unwrap();
    let low = values.iter().copied().fold(f32::INFINITY, f32::min);
    let high = values.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    values[[20, 30]] = low - 2.0 * (high - low);
    let glitched = tmp.path().join("glitched.npy");
    ndarray_npy::write_npy(&glitched, &values).unwrap();
    let says = "1 pixel(s) of the prediction lie far below the rest of its values";
    // in the calibration frame, where the fit learns it: calibrate names it
    let glitched_calib = tmp.path().join("glitched_calib.json");
    let out = moma(&[
        "calibrate",
        "--pred",
        s(&glitched),
        "--pred-kind",
        "relative-disparity",
        "--gt",
        s(&scene.join("frames/frame_01/depth.png")),
        "--camera",
        s(&camera),
        "-o",
        s(&glitched_calib),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains(&format!("note: the calibration frame: {says}")),
        "{err}"
    );
    for (frame, noted) in [(&clean, false), (&glitched, true)] {
        let out = moma(&align_args(
            &calib,
            frame,
            &tmp.path().join("a"),
            &["--json"],
        ));
        assert!(out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(err.contains(says), noted, "{err}");
        // and in --json, for scripts
        let rows: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        let note = rows[0]["normalisation_note"].as_str();
        assert_eq!(note.is_some_and(|n| n.contains(says)), noted, "{rows}");
        if noted {
            assert!(err.contains("at pixel (u=30, v=20)"), "{err}");
        }
        let out = moma(&[
            "grasp",
            "--calib",
            s(&calib),
            "--pred",
            s(frame),
            "--gripper",
            "suction",
            "--json",
        ]);
        assert!(out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(err.contains(says), noted, "{err}");
    }
}
