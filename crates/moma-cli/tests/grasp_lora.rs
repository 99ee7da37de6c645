//! `moma grasp --rgb --weights --lora`: the adapter is merged into the depth model that `moma grasp`
//! runs, exactly as in `moma predict --lora`, on the tiny random-weight metric model of
//! `shared/reference/dav2` and a frame of a shared moma set. Random weights predict nothing
//! meaningful: this checks the plumbing (same prediction, hence the same grasps and reasons), not
//! grasp quality.
#![cfg(feature = "candle")]

use std::path::{Path, PathBuf};

mod common;
use common::{fails, moma, ok, s, tiny_metric_model};

fn shared() -> PathBuf {
    let shared = std::env::var_os("MOMA_SHARED_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"));
    assert!(
        shared
            .join("reference/dav2/tiny-metric.safetensors")
            .is_file()
            && shared.join("data/gqcnn-primesense/camera.json").is_file(),
        "this test needs the shared folder (reference/dav2, data/gqcnn-primesense), not found at {} (set MOMA_SHARED_DIR)",
        shared.display()
    );
    shared
}

/// The `.npy` that `moma predict -o out` wrote.
fn npy_in(out: &Path) -> PathBuf {
    std::fs::read_dir(out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "npy"))
        .unwrap()
}

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn grasp_with_lora_runs_the_adapted_model() {
    let shared = shared();
    let tmp = tempfile::tempdir().unwrap();
    let (weights, config) = tiny_metric_model(&shared, tmp.path());
    let set = shared.join("data/gqcnn-primesense");
    let frame = set.join("frames/single_object_0");
    let (rgb, gt, camera) = (
        frame.join("rgb.png"),
        frame.join("depth.png"),
        set.join("camera.json"),
    );
    let model = [
        "--weights",
        s(&weights),
        "--model",
        s(&config),
        "--input-size",
        "56",
        "--device",
        "cpu",
    ];
    // A small adapter: a few steps move LoRA's B matrices away from zero.
    let adapter = tmp.path().join("a.safetensors");
    let mut a: Vec<&str> = vec!["finetune", "--set", s(&set)];
    a.extend(model);
    a.extend([
        "--steps",
        "4",
        "--lr",
        "1e-2",
        "--lora-rank",
        "4",
        "--seed",
        "1",
        "-o",
        s(&adapter),
    ]);
    ok(&a);

    // Predictions with and without the adapter, and a calibration on the adapted one.
    let predict = |extra: &[&str], out: &Path| {
        let mut a: Vec<&str> = vec!["predict"];
        a.extend(model);
        a.extend(["-o", s(out), s(&rgb)]);
        a.extend(extra);
        ok(&a);
        npy_in(out)
    };
    let pred_lora = predict(&["--lora", s(&adapter)], &tmp.path().join("p_lora"));
    let pred_base = predict(&[], &tmp.path().join("p_base"));
    let cal = tmp.path().join("cal.json");
    ok(&[
        "calibrate",
        "--pred",
        s(&pred_lora),
        "--gt",
        s(&gt),
        "--camera",
        s(&camera),
        "-o",
        s(&cal),
    ]);

    // `moma grasp` on the RGB image through the adapted model = on the adapted prediction.
    let grasp = |source: &[&str], out: &Path| {
        let mut a: Vec<&str> = vec!["grasp", "--calib", s(&cal), "--camera", s(&camera)];
        a.extend(source);
        a.extend(["--gripper", "suction", "--top", "5", "--json", "-o", s(out)]);
        let run = moma(&a);
        assert!(
            run.status.success(),
            "moma {a:?} failed:\n{}",
            String::from_utf8_lossy(&run.stderr)
        );
        let stdout = String::from_utf8(run.stdout).unwrap();
        let grasps: serde_json::Value = serde_json::from_str(&stdout).unwrap();
        let written = std::fs::read_to_string(out.join("grasps.json")).unwrap();
        (grasps, written)
    };
    let mut rgb_lora: Vec<&str> = vec!["--rgb", s(&rgb)];
    rgb_lora.extend(model);
    rgb_lora.extend(["--lora", s(&adapter)]);
    let via_rgb = grasp(&rgb_lora, &tmp.path().join("g_rgb"));
    let via_pred = grasp(&["--pred", s(&pred_lora)], &tmp.path().join("g_pred"));
    let via_base = grasp(&["--pred", s(&pred_base)], &tmp.path().join("g_base"));
    eprintln!("grasps via --rgb --lora: {}", via_rgb.1);
    assert!(via_rgb.0.is_array());
    assert_eq!(
        via_rgb, via_pred,
        "--rgb --lora differs from the adapted prediction"
    );
    // The adapter changes the prediction, so the base model's grasps are those of another depth.
    let (a, b): (ndarray::Array2<f32>, ndarray::Array2<f32>) = (
        ndarray_npy::read_npy(&pred_lora).unwrap(),
        ndarray_npy::read_npy(&pred_base).unwrap(),
    );
    let diff = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max);
    assert!(
        diff > 1e-4,
        "the adapter did not change the prediction ({diff:.2e})"
    );
    let _ = via_base;

    // The adapter on other base weights, and a corrupt adapter: errors, the latter naming it.
    let other_w = shared.join("reference/dav2/tiny-metric-392.safetensors");
    let corrupt = tmp.path().join("corrupt.safetensors");
    std::fs::write(&corrupt, b"not an adapter").unwrap();
    for (w, lora, expect) in [
        (&other_w, &adapter, "other base weights"),
        (&weights, &corrupt, "corrupt.safetensors"),
    ] {
        let mut bad: Vec<&str> = vec!["grasp", "--calib", s(&cal), "--camera", s(&camera)];
        bad.extend(["--rgb", s(&rgb), "--weights", s(w), "--model", s(&config)]);
        bad.extend(["--input-size", "56", "--device", "cpu", "--lora", s(lora)]);
        bad.extend(["--gripper", "suction"]);
        let e = fails(&bad);
        assert!(e.contains(expect), "{e}");
    }
}
