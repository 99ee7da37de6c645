//! Helpers shared by the CLI tests: run the `moma` binary and check how it ended.
#![allow(dead_code)] // each test file uses its own subset

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Runs `moma ARGS`.
pub fn moma(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_moma"))
        .args(args)
        .output()
        .expect("the moma binary runs")
}

/// Runs `moma ARGS`, asserts success, returns stdout.
pub fn ok(args: &[&str]) -> String {
    let out = moma(args);
    assert!(
        out.status.success(),
        "moma {args:?} failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("utf-8 stdout")
}

/// Runs `moma ARGS`, asserts failure, returns stderr.
pub fn fails(args: &[&str]) -> String {
    let out = moma(args);
    assert!(!out.status.success(), "moma {args:?} should fail");
    String::from_utf8(out.stderr).expect("utf-8 stderr")
}

/// Runs `moma calibrate` on the demo scene's first frame (`PRED/frame_00.npy` against
/// `SCENE/frames/frame_00/depth.png`) into `out`, with `extra` arguments; asserts success,
/// returns stdout.
pub fn calibrate_frame_00(scene: &Path, pred: &Path, out: &Path, extra: &[&str]) -> String {
    let (p, gt) = (
        pred.join("frame_00.npy"),
        scene.join("frames/frame_00/depth.png"),
    );
    let mut args = vec!["calibrate", "--pred", s(&p), "--gt", s(&gt), "-o", s(out)];
    args.extend_from_slice(extra);
    ok(&args)
}

/// The configuration of the tiny random-weight metric Depth Anything V2 of
/// `../shared/reference/dav2` (random weights: plumbing, not depth quality).
pub const TINY_METRIC_CONFIG: &str = r#"{"embed_dim":64,"depth":4,"num_heads":2,"intermediate_layers":[0,1,2,3],"features":16,"out_channels":[8,16,32,64],"head":"metric","max_depth":20}"#;

/// The tiny metric model: writes its configuration into `dir` and returns (its weights under
/// `shared`, the configuration file), for `--weights W --model CONFIG`.
pub fn tiny_metric_model(shared: &Path, dir: &Path) -> (PathBuf, PathBuf) {
    let config = dir.join("tiny-metric.json");
    std::fs::write(&config, TINY_METRIC_CONFIG).expect("the configuration is written");
    (
        shared.join("reference/dav2/tiny-metric.safetensors"),
        config,
    )
}

/// A path as `&str` for an argument list.
pub fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// Writes the bundled demo scene under `dir` (`moma demo --frames 3 --no-exports --seeds 1`:
/// 3 frames, SIMULATED relative-disparity predictions with predictions.json) and checks that it did;
/// returns (the moma set folder, the predictions folder).
pub fn demo(dir: &Path) -> (PathBuf, PathBuf) {
    let out = dir.join("demo");
    ok(&[
        "demo",
        "-o",
        s(&out),
        "--frames",
        "3",
        "--no-exports",
        "--seeds",
        "1",
    ]);
    let (scene, pred) = (out.join("scene"), out.join("predictions"));
    assert!(
        scene.join("camera.json").is_file(),
        "demo writes a moma set"
    );
    assert!(
        pred.join("frame_00.npy").is_file(),
        "demo writes predictions"
    );
    (scene, pred)
}

/// Frame `k`'s files of the demo scene: (prediction `.npy`, ground truth `depth.png`).
pub fn demo_frame(scene: &Path, pred: &Path, k: usize) -> (PathBuf, PathBuf) {
    (
        pred.join(format!("frame_{k:02}.npy")),
        scene.join(format!("frames/frame_{k:02}/depth.png")),
    )
}

/// `eval --set SCENE --pred PRED -o OUT` followed by `extra`.
pub fn eval_args<'a>(
    scene: &'a Path,
    pred: &'a Path,
    out: &'a Path,
    extra: &[&'a str],
) -> Vec<&'a str> {
    let mut args = vec!["eval", "--set", s(scene), "--pred", s(pred), "-o", s(out)];
    args.extend_from_slice(extra);
    args
}

/// Runs [`eval_args`] with `--json`, asserts success, returns the rows of the JSON contract.
pub fn eval_rows(scene: &Path, pred: &Path, out: &Path, extra: &[&str]) -> Vec<serde_json::Value> {
    let mut args = eval_args(scene, pred, out, extra);
    args.push("--json");
    let rows: serde_json::Value = serde_json::from_str(&ok(&args)).expect("--json prints JSON");
    rows.as_array().expect("--json prints an array").clone()
}

/// The `(method, variant)` of each JSON row, in order.
pub fn method_variants(rows: &[serde_json::Value]) -> Vec<(String, String)> {
    rows.iter()
        .map(|r| {
            (
                r["method"].as_str().expect("method").to_string(),
                r["variant"].as_str().expect("variant").to_string(),
            )
        })
        .collect()
}

/// `calibrate --pred P... --gt G...` followed by `extra` (one --pred and one --gt flag, each with
/// every path).
pub fn calibrate_args<'a>(preds: &[&'a Path], gts: &[&'a Path], extra: &[&'a str]) -> Vec<&'a str> {
    let mut args = vec!["calibrate", "--pred"];
    args.extend(preds.iter().map(|p| s(p)));
    args.push("--gt");
    args.extend(gts.iter().map(|g| s(g)));
    args.extend_from_slice(extra);
    args
}

/// `align --calib CALIB --pred PRED -o OUT` followed by `extra`.
pub fn align_args<'a>(
    calib: &'a Path,
    pred: &'a Path,
    out: &'a Path,
    extra: &[&'a str],
) -> Vec<&'a str> {
    let mut args = vec![
        "align",
        "--calib",
        s(calib),
        "--pred",
        s(pred),
        "-o",
        s(out),
    ];
    args.extend_from_slice(extra);
    args
}

/// The shared folder: `$MOMA_SHARED_DIR`, else `../shared` beside the workspace. Tests calling
/// it are `#[ignore = "needs ../shared ..."]` and run with `-- --include-ignored` (CI does).
///
/// # Panics
/// When it does not exist, naming where it was looked for.
pub fn shared_dir() -> PathBuf {
    let (dir, from) = match std::env::var_os("MOMA_SHARED_DIR") {
        Some(d) => (PathBuf::from(d), "$MOMA_SHARED_DIR"),
        None => (
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"),
            "../shared beside the workspace (MOMA_SHARED_DIR unset)",
        ),
    };
    assert!(
        dir.is_dir(),
        "this test needs the shared folder, not found at {} ({from}); set MOMA_SHARED_DIR, \
         or run without --include-ignored to skip it",
        dir.display()
    );
    dir
}
