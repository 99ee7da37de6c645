//! Parity of the candle backend with the official PyTorch Depth Anything V2
//! (`shared/reference/dav2`, random weights): network output fed the reference input, and the full
//! image → own pre-processing → network → post-processing path.
//!
//! The tests need `../shared/reference/dav2` (or `$MOMA_SHARED_DIR/reference/dav2`): they are
//! `#[ignore]`d (listed as ignored) and run with `--include-ignored`, which fails if the folder is
//! missing. The ViT-S test runs the full-size network twice (a few seconds each in release, over
//! a minute each in a debug build, whose CPU kernels in this crate are unoptimised); CI runs
//! `cargo test --release ... -- --include-ignored`.
#![cfg(feature = "candle")]

mod common;

use std::collections::HashMap;
use std::path::Path;

use common::{
    max_abs_err, reference_dir, reference_image, reference_input, reference_output, tiny_config,
};
use moma_depth::candle::{CandleDepthModel, DepthAnythingConfig};
use moma_depth::{DepthError, DepthModel, Head};

fn config_for(dir: &Path, name: &str) -> DepthAnythingConfig {
    if name == "vits-rel" {
        DepthAnythingConfig::vit_small(Head::Relative)
    } else {
        tiny_config(dir, name)
    }
}

/// Net and full-image parity of one reference model; returns the relative errors.
fn check_model(dir: &Path, name: &str) -> (f32, f32) {
    let config = config_for(dir, name);
    let path = dir.join(format!("{name}.safetensors"));
    let mut model = CandleDepthModel::load(
        &path,
        config,
        &candle_core::Device::Cpu,
        candle_core::DType::F32,
        None,
    )
    .unwrap();

    let input = reference_input(dir, name);
    let t = std::time::Instant::now();
    let net = model.forward_net(&input).unwrap();
    let secs = t.elapsed().as_secs_f64();
    let want = reference_output(dir, name, "net");
    let (err, range) = max_abs_err(&net, &want);
    let rel_net = err / range;
    eprintln!(
        "{name}: net  max abs err {err:.3e}, range {range:.4}, rel {rel_net:.3e} ({secs:.2} s)"
    );

    let rgb = reference_image(dir);
    let pred = model.predict(&rgb).unwrap();
    let want = reference_output(dir, name, "full");
    let (err, range) = max_abs_err(&pred.values, &want);
    let rel_full = err / range;
    eprintln!("{name}: full max abs err {err:.3e}, range {range:.4}, rel {rel_full:.3e}");
    assert_eq!(pred.kind, model.spec().head.prediction_kind());
    (rel_net, rel_full)
}

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn tiny_models_match_reference() {
    let dir = reference_dir();
    for name in ["tiny-rel", "tiny-rel-392", "tiny-metric", "tiny-metric-392"] {
        let (rel_net, rel_full) = check_model(&dir, name);
        assert!(rel_net < 1e-3, "{name}: net rel err {rel_net}");
        // Own OpenCV-exact pre-processing: the full path stays within the same tolerance.
        assert!(rel_full < 1e-3, "{name}: full rel err {rel_full}");
    }
}

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn vits_matches_reference() {
    let dir = reference_dir();
    let (rel_net, rel_full) = check_model(&dir, "vits-rel");
    assert!(rel_net < 1e-3, "vits-rel: net rel err {rel_net}");
    assert!(rel_full < 1e-3, "vits-rel: full rel err {rel_full}");
}

/// Other dtypes run candle's own ops instead of this crate's CPU `f32` kernels: the code path of
/// CUDA and Metal. In `f64` it must match the reference as tightly as `f32`; in `f16` (the GPU
/// fast path) within 1e-2 of the output range.
#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn generic_ops_path_matches_reference_in_f64_and_f16() {
    let dir = reference_dir();
    let device = candle_core::Device::Cpu;
    for name in ["tiny-rel", "tiny-metric-392"] {
        let path = dir.join(format!("{name}.safetensors"));
        let input = reference_input(&dir, name);
        let want = reference_output(&dir, name, "net");
        for (dtype, tol) in [
            (candle_core::DType::F64, 1e-4f32),
            (candle_core::DType::F16, 1e-2),
        ] {
            let mut model =
                CandleDepthModel::load(&path, config_for(&dir, name), &device, dtype, None)
                    .unwrap();
            assert_eq!(model.dtype(), dtype);
            let net = model.forward_net(&input).unwrap();
            let (err, range) = max_abs_err(&net, &want);
            eprintln!(
                "{name} {dtype:?}: net max abs err {err:.3e}, rel {:.3e}",
                err / range
            );
            assert!(
                err / range < tol,
                "{name} {dtype:?}: rel err {}",
                err / range
            );
        }
    }
    // f16 has no CPU kernel: packing for it is refused, naming the reason.
    let mut model = CandleDepthModel::load(
        dir.join("tiny-rel.safetensors"),
        config_for(&dir, "tiny-rel"),
        &candle_core::Device::Cpu,
        candle_core::DType::F32,
        None,
    )
    .unwrap();
    let err = model
        .pack_cpu(moma_depth::Precision::F16)
        .expect_err("f16 on the CPU is refused");
    assert!(matches!(err, DepthError::Unavailable(_)), "{err:?}");
}

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn mismatched_checkpoint_is_a_weights_error() {
    let dir = reference_dir();
    let device = candle_core::Device::Cpu;
    let mut tensors: HashMap<String, candle_core::Tensor> =
        candle_core::safetensors::load(dir.join("tiny-rel.safetensors"), &device).unwrap();
    // Rename one key, drop one, change one shape.
    let t = tensors.remove("pretrained.norm.weight").unwrap();
    tensors.insert("pretrained.final_norm.weight".into(), t);
    tensors.remove("depth_head.scratch.output_conv1.bias");
    tensors.insert(
        "pretrained.cls_token".into(),
        candle_core::Tensor::zeros((1, 1, 65), candle_core::DType::F32, &device).unwrap(),
    );
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("broken.safetensors");
    candle_core::safetensors::save(&tensors, &path).unwrap();

    let err = CandleDepthModel::load(
        &path,
        tiny_config(&dir, "tiny-rel"),
        &device,
        candle_core::DType::F32,
        None,
    )
    .unwrap_err();
    let DepthError::Weights { reason, .. } = &err else {
        panic!("expected Weights error, got {err:?}")
    };
    eprintln!("{err}");
    assert!(reason.contains("missing keys"), "{reason}");
    assert!(reason.contains("pretrained.norm.weight"), "{reason}");
    assert!(
        reason.contains("depth_head.scratch.output_conv1.bias"),
        "{reason}"
    );
    assert!(
        reason.contains("unexpected keys: pretrained.final_norm.weight"),
        "{reason}"
    );
    assert!(
        reason.contains("pretrained.cls_token: expected [1, 1, 64], found [1, 1, 65]"),
        "{reason}"
    );

    // The right file with the wrong architecture is refused too (ViT-S preset on a tiny checkpoint).
    let err = CandleDepthModel::load(
        dir.join("tiny-rel.safetensors"),
        DepthAnythingConfig::vit_small(Head::Relative),
        &device,
        candle_core::DType::F32,
        None,
    )
    .unwrap_err();
    assert!(matches!(err, DepthError::Weights { .. }), "{err:?}");
    // A missing file is a Weights error as well.
    let err = CandleDepthModel::load(
        tmp.path().join("none.safetensors"),
        tiny_config(&dir, "tiny-rel"),
        &device,
        candle_core::DType::F32,
        None,
    )
    .unwrap_err();
    assert!(matches!(err, DepthError::Weights { .. }), "{err:?}");
}
