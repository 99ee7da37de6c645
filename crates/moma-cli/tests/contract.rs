//! The command-line contract: prediction kinds are never guessed, RAW needs metric
//! depth and `--norm none`, a calibration file is self-contained (its workspace embedded) and
//! still aligns after being copied elsewhere, and bad calibration files are refused clearly.
//! Runs on the bundled demo scene (no ../shared needed).

mod common;
use common::{demo, fails, moma, ok, s};

#[test]
fn the_kind_comes_from_predictions_json_and_a_contradiction_is_an_error() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let index: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(pred.join("predictions.json")).unwrap())
            .unwrap();
    assert_eq!(index["format"], "moma-predictions");
    assert_eq!(index["prediction_kind"], "relative-disparity");
    assert_eq!(index["version"], moma_io::PREDICTIONS_VERSION);
    assert_eq!(index["simulated"], true);
    let gt = scene.join("frames/frame_00/depth.png");
    let calib = tmp.path().join("calib.json");
    // no --pred-kind: read from predictions.json
    ok(&[
        "calibrate",
        "--pred",
        s(&pred.join("frame_00.npy")),
        "--gt",
        s(&gt),
        "-o",
        s(&calib),
    ]);
    let file: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&calib).unwrap()).unwrap();
    assert_eq!(file["prediction_kind"], "relative-disparity");
    assert_eq!(file["normalisation"]["space"], "inverse");
    // a contradicting --pred-kind is an error naming both
    let e = fails(&[
        "calibrate",
        "--pred",
        s(&pred.join("frame_00.npy")),
        "--pred-kind",
        "metric-depth",
        "--gt",
        s(&gt),
        "-o",
        s(&calib),
    ]);
    assert!(
        e.contains("prediction kind mismatch") && e.contains("predictions.json"),
        "{e}"
    );
    // without an index and without --pred-kind the kind is unknown
    let lone = tmp.path().join("lone");
    std::fs::create_dir(&lone).unwrap();
    std::fs::copy(pred.join("frame_00.npy"), lone.join("p.npy")).unwrap();
    let e = fails(&[
        "calibrate",
        "--pred",
        s(&lone.join("p.npy")),
        "--gt",
        s(&gt),
        "-o",
        s(&calib),
    ]);
    assert!(
        e.contains("prediction kind is unknown") && e.contains("--pred-kind"),
        "{e}"
    );
    // align takes the kind from the calibration file; a contradicting --pred-kind fails
    let out = tmp.path().join("aligned");
    ok(&[
        "align",
        "--calib",
        s(&calib),
        "--pred",
        s(&lone.join("p.npy")),
        "-o",
        s(&out),
    ]);
    let e = fails(&[
        "align",
        "--calib",
        s(&calib),
        "--pred",
        s(&lone.join("p.npy")),
        "--pred-kind",
        "metric-depth",
        "-o",
        s(&out),
    ]);
    assert!(
        e.contains("prediction kind mismatch") && e.contains("calibration file"),
        "{e}"
    );
}

/// `args` as the `&[&str]` that [`ok`] and [`fails`] take.
fn strs(args: &[String]) -> Vec<&str> {
    args.iter().map(String::as_str).collect()
}

#[test]
fn raw_needs_norm_none_and_metric_depth() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let gt = scene.join("frames/frame_00/depth.png");
    let calib = tmp.path().join("calib.json");
    // relative-disparity predictions: refused whatever the normalisation
    let e = fails(&[
        "calibrate",
        "--pred",
        s(&pred.join("frame_00.npy")),
        "--gt",
        s(&gt),
        "--method",
        "raw",
        "-o",
        s(&calib),
    ]);
    assert!(
        e.contains("--method raw takes a metric-depth prediction") && !e.contains("--norm"),
        "{e}"
    );
    // a metric depth map: --method raw with another normalisation fails clearly; without
    // --norm it takes none, as with --norm none
    let depth_dir = tmp.path().join("metric");
    std::fs::create_dir(&depth_dir).unwrap();
    let d = moma_io::read_depth(&gt).unwrap();
    moma_io::write_npy_f32(depth_dir.join("p.npy"), d.depth_m.view()).unwrap();
    let p = depth_dir.join("p.npy");
    // `calibrate --method raw` of the metric map as `kind`, with `--norm N` when given, into `out`
    let raw = |kind: &'static str, norm: Option<&'static str>, out: &std::path::Path| {
        let mut a = vec![
            "calibrate",
            "--pred",
            s(&p),
            "--pred-kind",
            kind,
            "--gt",
            s(&gt),
            "--method",
            "raw",
        ];
        if let Some(n) = norm {
            a.extend(["--norm", n]);
        }
        a.push("-o");
        a.into_iter()
            .map(str::to_string)
            .chain([s(out).to_string()])
            .collect::<Vec<String>>()
    };
    let raw_none = |kind: &'static str, out: &std::path::Path| raw(kind, Some("none"), out);
    let e = fails(&strs(&raw("metric-depth", Some("minmax"), &calib)));
    assert!(
        e.contains("--norm minmax") && e.contains("normalisation 'none', got 'minmax'"),
        "{e}"
    );
    assert!(!calib.exists(), "nothing written on error");
    let by_default = tmp.path().join("raw-default.json");
    ok(&strs(&raw("metric-depth", None, &by_default)));
    ok(&strs(&raw_none("metric-depth", &calib)));
    let json = |p: &std::path::Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
    };
    let (given, default) = (json(&calib), json(&by_default));
    assert_eq!(default["normalisation"]["method"], "none");
    for part in ["model", "normalisation", "samples", "error_model"] {
        assert_eq!(
            given["calibration"][part], default["calibration"][part],
            "{part}"
        );
    }
    // raw uses the values as metres: refused for relative depth, and for the old name `depth`,
    // which claims no unit (docs/formats.md "Prediction kinds")
    for kind in ["relative-depth", "depth"] {
        let e = fails(&strs(&raw_none(kind, &tmp.path().join("refused.json"))));
        assert!(
            e.contains("'relative-depth'") && e.contains("metric-depth"),
            "{e}"
        );
    }
    // the raw (metric-depth) calibration refuses a relative depth map at run time ...
    let align = |calib: &std::path::Path, kind: &str, out: &str| {
        moma(&[
            "align",
            "--calib",
            s(calib),
            "--pred",
            s(&p),
            "--pred-kind",
            kind,
            "-o",
            s(&tmp.path().join(out)),
        ])
    };
    let refused = align(&calib, "relative-depth", "r");
    assert!(!refused.status.success());
    let e = String::from_utf8_lossy(&refused.stderr);
    assert!(e.contains("prediction kind mismatch"), "{e}");
    // ... while a relative-depth calibration also aligns a metric model's output (metric depth is
    // relative depth with a known scale), to the same metres as it aligns the same values given
    // as relative depth
    let rel = tmp.path().join("rel.json");
    ok(&[
        "calibrate",
        "--pred",
        s(&p),
        "--pred-kind",
        "relative-depth",
        "--gt",
        s(&gt),
        "--method",
        "gssa",
        "-o",
        s(&rel),
    ]);
    assert!(align(&rel, "metric-depth", "m").status.success());
    assert!(align(&rel, "relative-depth", "d").status.success());
    let read = |out: &str| {
        moma_io::read_depth(tmp.path().join(out).join("p.depth.npy"))
            .unwrap()
            .depth_m
    };
    let (m, d) = (read("m"), read("d"));
    assert!(m.iter().any(|z| z.is_finite()));
    assert_eq!(
        m.iter().map(|z| z.to_bits()).collect::<Vec<_>>(),
        d.iter().map(|z| z.to_bits()).collect::<Vec<_>>()
    );
}

#[test]
fn a_calibration_with_a_workspace_still_aligns_after_being_copied() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let gt = scene.join("frames/frame_00/depth.png");
    let size = moma_io::read_depth(&gt).unwrap().size();
    let ws = tmp.path().join("ws.png");
    let mask = moma_core::Mask::new(ndarray::Array2::from_shape_fn(size.shape(), |(v, _)| {
        v > size.height / 4
    }));
    moma_io::write_mask(&ws, &mask).unwrap();
    let calib = tmp.path().join("calib.json");
    ok(&[
        "calibrate",
        "--pred",
        s(&pred.join("frame_00.npy")),
        "--gt",
        s(&gt),
        "--workspace",
        s(&ws),
        "-o",
        s(&calib),
    ]);
    let a = tmp.path().join("a");
    ok(&[
        "align",
        "--calib",
        s(&calib),
        "--pred",
        s(&pred.join("frame_01.npy")),
        "-o",
        s(&a),
    ]);
    // copy the calibration elsewhere and delete the mask: the same output
    let other = tempfile::tempdir().unwrap();
    let moved = other.path().join("calib.json");
    std::fs::copy(&calib, &moved).unwrap();
    std::fs::remove_file(&ws).unwrap();
    let b = tmp.path().join("b");
    ok(&[
        "align",
        "--calib",
        s(&moved),
        "--pred",
        s(&pred.join("frame_01.npy")),
        "-o",
        s(&b),
    ]);
    let x = moma_io::read_npy_f32(a.join("frame_01.depth.npy")).unwrap();
    let y = moma_io::read_npy_f32(b.join("frame_01.depth.npy")).unwrap();
    assert_eq!(x.dim(), y.dim());
    assert!(
        x.iter()
            .zip(&y)
            .all(|(p, q)| p == q || (p.is_nan() && q.is_nan()))
    );
    // and without the workspace the result differs (the workspace is really used)
    let plain = tmp.path().join("plain.json");
    ok(&[
        "calibrate",
        "--pred",
        s(&pred.join("frame_00.npy")),
        "--gt",
        s(&gt),
        "-o",
        s(&plain),
    ]);
    let c = tmp.path().join("c");
    ok(&[
        "align",
        "--calib",
        s(&plain),
        "--pred",
        s(&pred.join("frame_01.npy")),
        "-o",
        s(&c),
    ]);
    let z = moma_io::read_npy_f32(c.join("frame_01.depth.npy")).unwrap();
    assert!(x.iter().zip(&z).any(|(p, q)| (p - q).abs() > 1e-4));
    // another mask given to align is a mismatch
    let other_ws = tmp.path().join("other.png");
    moma_io::write_mask(&other_ws, &moma_core::Mask::full(size)).unwrap();
    let e = fails(&[
        "align",
        "--calib",
        s(&moved),
        "--pred",
        s(&pred.join("frame_01.npy")),
        "--workspace",
        s(&other_ws),
        "-o",
        s(&c),
    ]);
    assert!(e.contains("workspace mismatch"), "{e}");
}

#[test]
fn bad_calibration_files_and_sample_counts_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let gt = scene.join("frames/frame_00/depth.png");
    let calib = tmp.path().join("calib.json");
    ok(&[
        "calibrate",
        "--pred",
        s(&pred.join("frame_00.npy")),
        "--gt",
        s(&gt),
        "--method",
        "lwlr",
        "-o",
        s(&calib),
    ]);
    let good: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&calib).unwrap()).unwrap();
    let out = tmp.path().join("out");
    let try_file = |v: &serde_json::Value| {
        let p = tmp.path().join("bad.json");
        std::fs::write(&p, serde_json::to_string(v).unwrap()).unwrap();
        fails(&[
            "align",
            "--calib",
            s(&p),
            "--pred",
            s(&pred.join("frame_01.npy")),
            "-o",
            s(&out),
        ])
    };
    let mut v = good.clone();
    v["calibration"]["model"]["bandwidth_px"] = serde_json::json!(-5.0);
    let e = try_file(&v);
    assert!(e.contains("bad.json") && e.contains("bandwidth"), "{e}");
    let mut v = good.clone();
    v["calibration"]["model"]["bandwidth_px"] = serde_json::json!(0.0);
    assert!(try_file(&v).contains("bandwidth"));
    let mut v = good.clone();
    v["calibration"]["extra"] = serde_json::json!(1);
    assert!(try_file(&v).contains("unknown field `extra`"));
    // huge --samples: an error, not an overflow or an allocation failure
    for sampling in ["random", "grid"] {
        let e = fails(&[
            "calibrate",
            "--pred",
            s(&pred.join("frame_00.npy")),
            "--gt",
            s(&gt),
            "--samples",
            "18446744073709551615",
            "--sampling",
            sampling,
            "-o",
            s(&calib),
        ]);
        assert!(e.contains("exceeds the limit"), "{e}");
    }
}
