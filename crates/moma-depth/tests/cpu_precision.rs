//! `--dtype int8` and `--dtype bf16` on the CPU (issue 26): the error against f32, on the
//! random-weight references of
//! `shared/reference/dav2` (ViT-S and the tiny models), and the failure mode of per-token
//! activation scales: a few huge activation channels, as trained ViTs have (random weights do
//! not), injected by scaling LayerNorm weights.
//!
//! The tests need `../shared/reference/dav2` (or `$MOMA_SHARED_DIR/reference/dav2`): they are
//! `#[ignore]`d and run with `--include-ignored`, which fails if the folder is missing.
#![cfg(feature = "candle")]

mod common;

use common::{max_abs_err, reference_dir, reference_input, tiny_config};
use moma_depth::candle::{CandleDepthModel, DepthAnythingConfig};
use moma_depth::{DepthModel, Head};

/// The network output of `name` in f32 and in `precision`, loaded by the constructor of
/// `moma_depth::load` and of the Python package (`load_with_precision`).
fn f32_and(
    name: &str,
    precision: moma_depth::Precision,
) -> (ndarray::Array2<f32>, ndarray::Array2<f32>) {
    let dir = reference_dir();
    let config = if name == "vits-rel" {
        DepthAnythingConfig::vit_small(Head::Relative)
    } else {
        tiny_config(&dir, name)
    };
    let path = dir.join(format!("{name}.safetensors"));
    let input = reference_input(&dir, name);
    let run = |p: moma_depth::Precision| {
        let dev = candle_core::Device::Cpu;
        CandleDepthModel::load_with_precision(&path, config.clone(), &dev, p, None)
            .unwrap()
            .forward_net(&input)
            .unwrap()
    };
    (run(moma_depth::Precision::F32), run(precision))
}

fn mean_abs(a: &ndarray::Array2<f32>, b: &ndarray::Array2<f32>) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum::<f32>() / a.len() as f32
}

#[test]
#[ignore = "needs ../shared/reference/dav2 (run with --include-ignored)"]
fn int8_and_bf16_errors_on_the_references() {
    use moma_depth::Precision;
    for precision in [Precision::Int8, Precision::Bf16] {
        for name in ["vits-rel", "tiny-rel", "tiny-metric"] {
            let (f, q) = f32_and(name, precision);
            let (err, range) = max_abs_err(&q, &f);
            let mean = mean_abs(&q, &f);
            eprintln!(
                "{name}: {precision:?} vs f32: max {:.3e}, mean {:.3e} of the output range",
                err / range,
                mean / range
            );
            // issue 26's budget: max error ≤ 1e-2 of the output range (measured: int8 ViT-S
            // 9.0e-3, tiny 2.6e-3 and 3.3e-3; bf16 below them)
            assert!(
                err / range <= 1e-2,
                "{name} {precision:?}: max {}",
                err / range
            );
            assert!(
                mean / range <= 2e-3,
                "{name} {precision:?}: mean {}",
                mean / range
            );
            // and it is not the f32 output
            assert!(err > 0.0, "{name} {precision:?}: output equals f32");
        }
    }
}

#[test]
#[ignore = "needs ../shared/reference/dav2 (run with --include-ignored)"]
fn a_packed_model_cannot_go_back_to_f32() {
    // packing frees the f32 weights of the packed layers: asking for f32 again is refused
    let dir = reference_dir();
    let mut m = CandleDepthModel::load_with_precision(
        dir.join("tiny-rel.safetensors"),
        tiny_config(&dir, "tiny-rel"),
        &candle_core::Device::Cpu,
        moma_depth::Precision::Int8,
        None,
    )
    .unwrap();
    // the provenance written to predictions.json names the packed precision
    assert!(m.runtime().contains("int8"), "{}", m.runtime());
    assert_eq!(m.packed_precision(), Some(moma_depth::Precision::Int8));
    let e = m.pack_cpu(moma_depth::Precision::F32).unwrap_err();
    let why = std::error::Error::source(&e)
        .map(|s| s.to_string())
        .unwrap_or_default();
    assert!(why.contains("load it again"), "{e}: {why}");
}

#[test]
#[ignore = "needs ../shared/reference/dav2 (run with --include-ignored)"]
fn the_runtime_names_the_precision_it_runs() {
    let dir = reference_dir();
    for (precision, name) in [
        (moma_depth::Precision::F32, None),
        (moma_depth::Precision::Bf16, Some("bf16")),
        (moma_depth::Precision::Int8, Some("int8")),
    ] {
        let m = CandleDepthModel::load_with_precision(
            dir.join("tiny-rel.safetensors"),
            tiny_config(&dir, "tiny-rel"),
            &candle_core::Device::Cpu,
            precision,
            None,
        )
        .unwrap();
        let runtime = m.runtime();
        match name {
            Some(n) => assert!(runtime.contains(n), "{precision:?}: {runtime}"),
            None => assert!(
                !runtime.contains("int8") && !runtime.contains("bf16"),
                "{runtime}"
            ),
        }
    }
}

#[test]
fn int8_is_a_cpu_precision_named_int8() {
    let p: moma_depth::Precision = "int8".parse().unwrap();
    assert_eq!(p, moma_depth::Precision::Int8);
    let dev = candle_core::Device::Cpu;
    assert_eq!(
        moma_depth::candle::precision_dtype(p, &dev).unwrap(),
        candle_core::DType::F32
    );
    let e = "int4".parse::<moma_depth::Precision>().unwrap_err();
    assert!(e.contains("int8"), "{e}");
}
