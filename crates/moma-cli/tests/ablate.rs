//! `moma ablate --calib-frames K` end to end on the bundled demo scene (3 frames, SIMULATED
//! relative-disparity predictions; no ../shared needed).

use std::path::Path;

mod common;
use common::{demo, fails, ok, s};

/// `ablate WHICH --set SCENE --pred PRED --seeds 2 -o OUT` followed by `extra`.
fn ablate<'a>(
    which: &'a str,
    scene: &'a Path,
    pred: &'a Path,
    out: &'a Path,
    extra: &[&'a str],
) -> Vec<&'a str> {
    let mut args = vec![
        "ablate",
        which,
        "--set",
        s(scene),
        "--pred",
        s(pred),
        "--seeds",
        "2",
        "-o",
        s(out),
    ];
    args.extend_from_slice(extra);
    args
}

/// The rows of an ablation's JSON detail file, without their fit times (wall-clock).
fn detail(path: &Path) -> Vec<serde_json::Value> {
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    v.as_array()
        .unwrap()
        .iter()
        .map(|r| {
            let mut r = r.clone();
            r.as_object_mut().unwrap().remove("fit_time_median_s");
            r
        })
        .collect()
}

#[test]
fn ablate_calibrates_on_the_first_k_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let dir = |name: &str| tmp.path().join(name);
    let (d0, d1, d2, d3) = (dir("default"), dir("k1"), dir("k2"), dir("k3"));
    let norms = ["--norms", "minmax,median", "--methods", "gssa,ssra"];

    // K = 1 (explicit) is the default: the same table, the same numbers
    let default = ok(&ablate("norm", &scene, &pred, &d0, &norms));
    let mut with_k1 = norms.to_vec();
    with_k1.extend(["--calib-frames", "1"]);
    let k1 = ok(&ablate("norm", &scene, &pred, &d1, &with_k1));
    assert_eq!(default, k1);
    assert!(
        default.contains("SIMULATED predictions — ablation (b): normalisation × method — 2 seeds"),
        "{default}"
    );
    let rows1 = detail(&d0.join("ablation_norm.json"));
    assert_eq!(rows1, detail(&d1.join("ablation_norm.json")));
    assert_eq!(rows1.len(), 4);
    assert!(
        rows1
            .iter()
            .all(|r| r["variant"] == "one-shot" && r["calib_frame"] == "frame_00")
    );

    // K = 2: the title says so; every row calibrates on frames 0 and 1 and scores frame 2
    let mut with_k2 = norms.to_vec();
    with_k2.extend(["--calib-frames", "2"]);
    let k2 = ok(&ablate("norm", &scene, &pred, &d2, &with_k2));
    assert!(
        k2.contains("few-shot: calibrated on the first 2 frames in sorted order")
            && k2.contains("scored on the frames after the first 2"),
        "{k2}"
    );
    let rows2 = detail(&d2.join("ablation_norm.json"));
    assert_eq!(rows2.len(), 4);
    for r in &rows2 {
        assert_eq!(r["variant"], "few-shot-2");
        assert_eq!(r["calib_frame"], "frame_00+frame_01");
        assert_eq!(r["eval_frames"], 1);
        assert_eq!(r["frames"][0]["frame"], "frame_02");
    }
    assert_ne!(rows1[0]["per_image"], rows2[0]["per_image"]);

    // the samples and source ablations take it too
    let counts = [
        "--methods",
        "gssa,ssra",
        "--calib-frames",
        "2",
        "--counts",
        "20,50",
    ];
    let a = ok(&ablate("samples", &scene, &pred, &d2, &counts));
    assert!(
        a.contains("few-shot: calibrated on the first 2 frames"),
        "{a}"
    );
    let rows = detail(&d2.join("ablation_samples.json"));
    assert_eq!(
        rows.len(),
        2 * 2,
        "2 counts × 2 methods (the first normalisation only)"
    );
    assert!(rows.iter().all(|r| r["calib_frame"] == "frame_00+frame_01"));

    // K = 3 leaves no frame to score: with no other set, nothing is evaluated and the command
    // fails with the reason (it wrote an empty table and succeeded)
    let mut with_k3 = norms.to_vec();
    with_k3.extend(["--calib-frames", "3"]);
    let e = fails(&ablate("norm", &scene, &pred, &d3, &with_k3));
    assert!(
        e.contains("no set could be evaluated")
            && e.contains("set 'scene' (few-shot-3): too few frames: 3, needs at least 4"),
        "{e}"
    );
    assert!(!d3.join("ablation_norm.json").exists());

    // bad K, and K > 1 with a calibration frame
    let mut zero = norms.to_vec();
    zero.extend(["--calib-frames", "0"]);
    let e = fails(&ablate("norm", &scene, &pred, &d3, &zero));
    assert!(
        e.contains("--calib-frames") && e.contains("at least 1"),
        "{e}"
    );
    let mut framed = with_k2.clone();
    framed.extend(["--calib-frame", "frame_01"]);
    let e = fails(&ablate("norm", &scene, &pred, &d3, &framed));
    assert!(e.contains("calibration frame"), "{e}");
}

/// The ablations run one-shot calibrations: `--realign` and `--robust`, which `ablate` shares with
/// `eval`, are refused by name before anything is written (they used to be accepted, and their
/// rows mixed into the ablation tables or skipped).
#[test]
fn ablate_refuses_the_variant_options_of_eval() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let out = tmp.path().join("ab");
    for (extra, named) in [
        (&["--realign", "anchors"][..], "--realign"),
        (&["--robust", "huber"][..], "--robust"),
    ] {
        let err = fails(&ablate("norm", &scene, &pred, &out, extra));
        assert!(
            err.contains(named) && err.contains("not supported by `moma ablate`"),
            "{err}"
        );
        assert!(!out.exists());
    }
}

/// The option a sweep replaces is refused, not silently overridden; its default and the sweep's
/// own repeats are checked too.
#[test]
fn ablate_refuses_the_option_its_sweep_replaces() {
    let tmp = tempfile::tempdir().unwrap();
    let (scene, pred) = demo(tmp.path());
    let out = tmp.path().join("ab");
    for (which, extra, says) in [
        (
            "samples",
            &["--samples", "20"][..],
            "--samples 20 does not apply to `moma ablate samples`",
        ),
        (
            "norm",
            &["--norm", "median"][..],
            "--norm does not apply to `moma ablate norm`",
        ),
        (
            "norm",
            &["--norms", "median,median"][..],
            "--norms names median twice",
        ),
    ] {
        let err = fails(&ablate(which, &scene, &pred, &out, extra));
        assert!(err.contains(says), "{which} {extra:?}: {err}");
    }
    // even the kind's default given explicitly (minmax for these relative-disparity
    // predictions): the sweep sets the normalisation
    let mut args = ablate("norm", &scene, &pred, &out, &["--norm", "minmax"]);
    args.extend_from_slice(&["--norms", "none", "--methods", "ssra"]);
    let err = fails(&args);
    assert!(err.contains("--norm does not apply"), "{err}");
    let mut args = ablate("norm", &scene, &pred, &out, &[]);
    args.extend_from_slice(&["--norms", "none", "--methods", "ssra"]);
    ok(&args);
    assert!(out.join("ablation_norm.json").is_file());
}
