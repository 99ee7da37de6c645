//! `moma calibrate --robust` and `moma eval --robust` end to end on the bundled demo scene
//! (SIMULATED predictions; no ../shared, no network).

mod common;
use common::{
    align_args, calibrate_args, demo, demo_frame, eval_rows, fails, method_variants, ok, s,
};

#[test]
fn calibrate_and_eval_with_robust_fits() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let calib = tmp.path().join("calib.json");
    let (pred0, gt0) = demo_frame(&scene, &pred, 0);
    let base = calibrate_args(
        &[&pred0],
        &[&gt0],
        &[
            "--pred-kind",
            "relative-disparity",
            "--method",
            "gssa",
            "--seed",
            "3",
            "-o",
            s(&calib),
        ],
    );
    let with = |extra: &[&'static str]| -> Vec<&str> {
        base.iter().copied().chain(extra.iter().copied()).collect()
    };
    // plain: no robust block in the summary or in the file
    let plain: serde_json::Value = serde_json::from_str(&ok(&with(&["--json"]))).unwrap();
    assert!(plain.get("robust").is_none(), "{plain}");
    assert!(
        !std::fs::read_to_string(&calib)
            .unwrap()
            .contains("\"robust\"")
    );

    for kind in ["huber", "tukey", "ransac"] {
        let summary: serde_json::Value = serde_json::from_str(&ok(&with(&[
            "--robust",
            kind,
            "--robust-threshold-m",
            "0.02",
            "--json",
        ])))
        .unwrap();
        let r = &summary["robust"];
        assert_eq!(r["kind"], kind);
        assert_eq!(r["threshold_m"], 0.02);
        assert!(
            r.get("auto").is_none(),
            "a fixed threshold has no auto block: {summary}"
        );
        let inliers = r["inliers"].as_u64().unwrap();
        assert!(inliers > 0 && inliers <= 100, "{summary}");
        // the file keeps the report and reads back (align accepts it)
        let text = std::fs::read_to_string(&calib).unwrap();
        assert!(text.contains("\"robust\""), "{text}");
        ok(&align_args(
            &calib,
            &pred.join("frame_01.npy"),
            &tmp.path().join("aligned"),
            &["--pred-kind", "relative-disparity"],
        ));
    }
    let text = ok(&with(&[
        "--robust",
        "ransac",
        "--robust-threshold-m",
        "0.01",
    ]));
    assert!(
        text.contains("inliers") && text.contains("threshold 10.0 mm"),
        "{text}"
    );
    // a fixed threshold far below the scatter: the fit succeeds (Huber is then least absolute
    // deviations, Tukey follows a minority) but says so; a threshold above it says nothing
    for (kind, threshold, warned) in [
        ("huber", "0.00001", true),
        ("tukey", "0.0002", true),
        ("huber", "0.05", false),
    ] {
        let out = common::moma(&with(&[
            "--robust",
            kind,
            "--robust-threshold-m",
            threshold,
        ]));
        assert!(out.status.success(), "{out:?}");
        let (stdout, stderr) = (
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr),
        );
        let inliers: usize = stdout
            .split("): ")
            .nth(1)
            .and_then(|t| t.split(" of ").next())
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("no inlier count: {stdout}"));
        assert_eq!(
            stderr.contains("lie within the fixed robust threshold"),
            warned,
            "{kind} {threshold}: {stdout}{stderr}"
        );
        assert_eq!(warned, inliers < 50, "{kind} {threshold}: {stdout}");
        if inliers == 0 {
            assert!(stdout.contains("(RMS none)"), "{stdout}");
        }
    }
    assert!(
        ok(&with(&[
            "--robust",
            "huber",
            "--robust-threshold-m",
            "0.00001"
        ]))
        .contains("threshold 1.0e-2 mm"),
        "a threshold under 0.1 mm is printed as 0.0 mm"
    );

    // the default threshold is `auto`: the summary and the file record the scale it estimated
    let text = ok(&with(&["--robust", "ransac"]));
    assert!(text.contains("threshold auto: 2.5 × scale"), "{text}");
    for kind in ["huber", "tukey", "ransac"] {
        for explicit in [false, true] {
            let mut extra = vec!["--robust", kind, "--json"];
            if explicit {
                extra.extend(["--robust-threshold-m", "auto"]);
            }
            let summary: serde_json::Value = serde_json::from_str(&ok(&with(&extra))).unwrap();
            let r = &summary["robust"];
            let auto = &r["auto"];
            let scale = auto["scale_m"].as_f64().unwrap();
            let factor = auto["factor"].as_f64().unwrap();
            let want = match kind {
                "huber" => 1.345,
                "tukey" => 4.685,
                _ => 2.5,
            };
            assert_eq!(factor, want, "{summary}");
            assert!((1e-4..0.1).contains(&scale), "{summary}");
            let t = r["threshold_m"].as_f64().unwrap();
            assert!((t - factor * scale).abs() < 1e-12, "{summary}");
            assert!(
                (auto["inlier_bound_m"].as_f64().unwrap() - 4.685 * scale).abs() < 1e-12,
                "{summary}"
            );
            let file: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&calib).unwrap()).unwrap();
            assert_eq!(file["calibration"]["report"]["robust"]["auto"], *auto);
        }
    }
    assert!(
        fails(&with(&["--robust", "huber", "--robust-threshold-m", "abc"]))
            .contains("neither 'auto' nor a number")
    );

    // bad input: unknown kind, bad threshold, unsupported method, threshold without --robust
    assert!(fails(&with(&["--robust", "lsq"])).contains("huber, tukey, ransac"));
    assert!(
        fails(&with(&["--robust", "huber", "--robust-threshold-m", "0"])).contains("threshold")
    );
    let e = fails(
        &base
            .iter()
            .map(|a| if *a == "gssa" { "lwlr" } else { a })
            .chain(["--robust", "tukey"])
            .collect::<Vec<_>>(),
    );
    assert!(e.contains("lwlr") && e.contains("robust"), "{e}");
    assert!(fails(&with(&["--robust-threshold-m", "0.02"])).contains("--robust"));

    // eval: one-shot and robust rows, with simulated ground-truth outliers
    let rows = eval_rows(
        &scene,
        &pred,
        &tmp.path().join("eval"),
        &[
            "--methods",
            "gssa,lwlr",
            "--seeds",
            "2",
            "--robust",
            "tukey,ransac",
            "--gt-outliers",
            "0.2",
        ],
    );
    let got = method_variants(&rows);
    let want: Vec<(String, String)> = [
        ("gssa", "one-shot"),
        ("gssa", "robust-tukey"),
        ("gssa", "robust-ransac"),
        ("lwlr", "one-shot"),
    ]
    .iter()
    .map(|(a, b)| (a.to_string(), b.to_string()))
    .collect();
    assert_eq!(got, want);
}
