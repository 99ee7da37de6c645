//! Parity of the ONNX Runtime backend against `shared/reference/dav2` (see its README): for each
//! of the five reference exports `NAME.onnx`,
//! - network only: `NAME.input.npy` → net vs `NAME.output_net.npy`, max abs error ≤ 1e-3 of the
//!   output range;
//! - full image: `input.png` → [`moma_depth::preprocess::preprocess`] → net →
//!   [`moma_depth::preprocess::resize_bilinear_align_corners`] vs `NAME.output_full.npy`.
//!
//! The tests need the reference folder (`$MOMA_SHARED_DIR/reference/dav2`, else
//! `../shared/reference/dav2` beside the workspace) and the ONNX Runtime library
//! (`$ORT_DYLIB_PATH`, see `moma_depth::onnx`): they are `#[ignore]`d (listed as ignored) and run
//! with `--include-ignored`, which fails if either is missing. Run in release mode for speed:
//! `cargo test -p moma-depth --release --no-default-features --features onnx --test onnx_parity -- --include-ignored --nocapture`
#![cfg(feature = "onnx")]

mod common;

use std::path::{Path, PathBuf};

use common::{
    MODELS, max_abs_err, reference_dir, reference_image, reference_input, reference_json,
    reference_output,
};
use moma_depth::onnx::{OnnxDepthModel, OnnxOptions};
use moma_depth::{Backbone, DepthError, DepthModel, Head, ModelSpec};
use ndarray::Array3;

/// Tolerance of the README / issue: max abs error ≤ 1e-3 × output range (float32).
const REL_TOL: f32 = 1e-3;

/// Loads the ONNX Runtime library (`$ORT_DYLIB_PATH`, see `moma_depth::onnx`).
///
/// # Panics
/// When it cannot be loaded: these tests are `#[ignore]`d and run only when asked for.
fn runtime() {
    match moma_depth::onnx::init_runtime() {
        Ok(lib) => eprintln!("ONNX Runtime library: {}", lib.display()),
        Err(e) => {
            panic!("this test needs ONNX Runtime: {e}; or run without --include-ignored to skip it")
        }
    }
}

/// The reference folder, with ONNX Runtime loaded.
///
/// # Panics
/// When either is missing.
fn setup() -> PathBuf {
    let dir = reference_dir();
    runtime();
    dir
}

fn spec_of(dir: &Path, name: &str) -> ModelSpec {
    let json = reference_json(dir, name);
    let head = match json["head"].as_str() {
        Some("metric") => Head::Metric {
            max_depth_m: json["max_depth"].as_f64().expect("max_depth") as f32,
        },
        _ => Head::Relative,
    };
    ModelSpec {
        backbone: Backbone::Vits,
        head,
        input_size: json["input_size"].as_u64().expect("input_size") as usize,
    }
}

fn load(dir: &Path, name: &str) -> OnnxDepthModel {
    let opts = OnnxOptions {
        intra_threads: Some(2),
        ..OnnxOptions::default()
    };
    OnnxDepthModel::load(dir.join(format!("{name}.onnx")), spec_of(dir, name), &opts)
        .expect("load onnx")
}

/// (max abs error, output range of the reference, max abs error / range).
fn compare(got: &ndarray::Array2<f32>, want: &ndarray::Array2<f32>) -> (f32, f32, f32) {
    let (err, range) = max_abs_err(got, want);
    (err, range, err / range.max(f32::MIN_POSITIVE))
}

#[test]
#[ignore = "needs ../shared and ONNX Runtime (ORT_DYLIB_PATH): run with --include-ignored (CI does)"]
fn onnx_net_parity_all_reference_models() {
    let dir = setup();
    let mut failures = Vec::new();
    eprintln!(
        "{:<16} {:>12} {:>12} {:>12}",
        "model", "max_abs", "range", "rel"
    );
    for name in MODELS {
        let mut model = load(&dir, name);
        let input = reference_input(&dir, name);
        let want = reference_output(&dir, name, "net");
        assert_eq!(
            model.fixed_input_hw(),
            Some((input.dim().1, input.dim().2)),
            "{name}: fixed input shape"
        );
        let got = model.forward_net(&input).expect("forward_net");
        let (err, range, rel) = compare(&got, &want);
        eprintln!("{name:<16} {err:>12.3e} {range:>12.4} {rel:>12.3e}   [net]");
        if rel.is_nan() || rel > REL_TOL {
            failures.push(format!("{name}: rel {rel:.3e} > {REL_TOL:.0e}"));
        }
    }
    assert!(failures.is_empty(), "net parity failures: {failures:?}");
}

#[test]
#[ignore = "needs ../shared and ONNX Runtime (ORT_DYLIB_PATH): run with --include-ignored (CI does)"]
fn onnx_full_image_parity_all_reference_models() {
    let dir = setup();
    let rgb = reference_image(&dir);
    let mut failures = Vec::new();
    eprintln!(
        "{:<16} {:>12} {:>12} {:>12}",
        "model", "max_abs", "range", "rel"
    );
    for name in MODELS {
        let mut model = load(&dir, name);
        let want = reference_output(&dir, name, "full");
        let pred = model.predict(&rgb).expect("predict");
        assert_eq!(
            pred.kind,
            model.spec().head.prediction_kind(),
            "{name}: prediction kind"
        );
        let (err, range, rel) = compare(&pred.values, &want);
        eprintln!("{name:<16} {err:>12.3e} {range:>12.4} {rel:>12.3e}   [full]");
        if rel.is_nan() || rel > REL_TOL {
            failures.push(format!("{name}: rel {rel:.3e} > {REL_TOL:.0e}"));
        }
    }
    assert!(
        failures.is_empty(),
        "full-image parity failures: {failures:?}"
    );
}

#[test]
#[ignore = "needs ../shared and ONNX Runtime (ORT_DYLIB_PATH): run with --include-ignored (CI does)"]
fn onnx_fixed_shape_mismatch_is_a_clear_error() {
    let dir = setup();
    let mut model = load(&dir, "tiny-rel-392");
    let wrong = Array3::<f32>::zeros((3, 518, 686));
    match model.forward_net(&wrong) {
        Err(DepthError::Shape(msg)) => {
            assert!(
                msg.contains("392x518"),
                "message names the fixed size: {msg}"
            );
            assert!(
                msg.contains("set the input size to 392 (`--input-size`, `input_size=`)"),
                "message suggests the input size, as the user gives it: {msg}"
            );
        }
        other => panic!("expected a shape error, got {other:?}"),
    }
    let not_rgb = Array3::<f32>::zeros((1, 392, 518));
    assert!(matches!(
        model.forward_net(&not_rgb),
        Err(DepthError::Shape(_))
    ));
}

#[test]
#[ignore = "needs ../shared and ONNX Runtime (ORT_DYLIB_PATH): run with --include-ignored (CI does)"]
fn onnx_bad_model_files_are_errors() {
    let dir = setup();
    let spec = spec_of(&dir, "tiny-rel");
    let missing = OnnxDepthModel::load(
        dir.join("does-not-exist.onnx"),
        spec,
        &OnnxOptions::default(),
    );
    assert!(
        matches!(missing, Err(DepthError::Weights { .. })),
        "{missing:?}"
    );
    // Not an ONNX file at all.
    let not_onnx = OnnxDepthModel::load(dir.join("tiny-rel.json"), spec, &OnnxOptions::default());
    // ONNX Runtime's own error is kept as the typed source, under a message naming the file.
    match not_onnx {
        Err(err @ DepthError::Onnx { .. }) => {
            let msg = err.to_string();
            assert!(
                msg.contains("cannot load the model") && msg.contains("tiny-rel.json"),
                "{msg}"
            );
            let source = std::error::Error::source(&err).expect("ort error as source");
            assert!(!msg.contains(&source.to_string()), "{msg}");
            eprintln!("not-ONNX file: {msg}: {source}");
        }
        other => panic!("expected ONNX Runtime's error, got {other:?}"),
    }
}
