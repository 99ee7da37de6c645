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

/// The network output of the weights at `path` in `precision` on the CPU, loaded by the
/// constructor of `moma_depth::load` and of the Python package (`load_with_precision`).
fn forward(
    path: &std::path::Path,
    config: &DepthAnythingConfig,
    input: &ndarray::Array3<f32>,
    precision: moma_depth::Precision,
) -> ndarray::Array2<f32> {
    let dev = candle_core::Device::Cpu;
    CandleDepthModel::load_with_precision(path, config.clone(), &dev, precision, None)
        .unwrap()
        .forward_net(input)
        .unwrap()
}

/// The network output of `name` in f32 and in `precision`.
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
    (
        forward(&path, &config, &input, moma_depth::Precision::F32),
        forward(&path, &config, &input, precision),
    )
}

/// The max and mean absolute error of `q` against `f`, over `f`'s output range.
fn relative_errors(q: &ndarray::Array2<f32>, f: &ndarray::Array2<f32>) -> (f32, f32) {
    let (err, range) = max_abs_err(q, f);
    let mean = q.iter().zip(f).map(|(x, y)| (x - y).abs()).sum::<f32>() / q.len() as f32;
    (err / range, mean / range)
}

#[test]
#[ignore = "needs ../shared/reference/dav2 (run with --include-ignored)"]
fn int8_and_bf16_errors_on_the_references() {
    use moma_depth::Precision;
    for precision in [Precision::Int8, Precision::Bf16] {
        for name in ["vits-rel", "tiny-rel", "tiny-metric"] {
            let (f, q) = f32_and(name, precision);
            let (max, mean) = relative_errors(&q, &f);
            eprintln!(
                "{name}: {precision:?} vs f32: max {max:.3e}, mean {mean:.3e} of the output range"
            );
            // issue 26's budget: max error ≤ 1e-2 of the output range (measured: int8 ViT-S
            // 9.0e-3, tiny 2.6e-3 and 3.3e-3; bf16 below them)
            assert!(max <= 1e-2, "{name} {precision:?}: max {max}");
            assert!(mean <= 2e-3, "{name} {precision:?}: mean {mean}");
            // and it is not the f32 output
            assert!(max > 0.0, "{name} {precision:?}: output equals f32");
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

/// `name`'s weights with two channels of every block's LayerNorm gains (`norm1`, `norm2`) made
/// `factor`× larger: the few huge activation channels trained ViTs have at the inputs of qkv and
/// fc1 (random weights have none), written to `dir`.
fn with_outlier_channels(name: &str, factor: f32, dir: &std::path::Path) -> std::path::PathBuf {
    use safetensors::SafeTensors;
    let bytes = std::fs::read(reference_dir().join(format!("{name}.safetensors"))).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let mut owned: Vec<(String, safetensors::Dtype, Vec<usize>, Vec<u8>)> = Vec::new();
    let mut scaled = 0;
    for (key, view) in st.tensors() {
        let mut data = view.data().to_vec();
        if key.contains(".norm1.weight") || key.contains(".norm2.weight") {
            assert_eq!(view.dtype(), safetensors::Dtype::F32);
            for c in [5usize, 40] {
                let b = &mut data[4 * c..4 * c + 4];
                let v = f32::from_le_bytes([b[0], b[1], b[2], b[3]]) * factor;
                b.copy_from_slice(&v.to_le_bytes());
            }
            scaled += 1;
        }
        owned.push((key, view.dtype(), view.shape().to_vec(), data));
    }
    assert!(scaled >= 8, "{scaled} LayerNorm gains scaled");
    let views: Vec<(String, safetensors::tensor::TensorView<'_>)> = owned
        .iter()
        .map(|(k, d, s, b)| {
            (
                k.clone(),
                safetensors::tensor::TensorView::new(*d, s.clone(), b).unwrap(),
            )
        })
        .collect();
    let out = dir.join(format!("{name}-outliers-{factor}.safetensors"));
    safetensors::serialize_to_file(views, None, &out).unwrap();
    out
}

/// Network-level outlier injection (issue 26 item 3): int8's per-token activation scales against
/// f32 on the tiny model with two LayerNorm channels 20× and 60× larger than the rest, the
/// failure mode of per-token int8 on trained ViTs; bf16 (a per-value exponent) for contrast.
/// Measured (docs/depth-model.md): the budget holds without outliers and **fails with them**.
/// int8 max 3.0e-2 of the range at ×20 and 0.23 at ×60, with the outlier channels found per
/// chunk and multiplied in f32 (4.4e-2 and 0.29 without that split); bf16 7.5e-3 and 0.14: the
/// perturbed network amplifies every rounding error (bf16's grows 7× at ×20). What is
/// asserted: the budget at ×1; that int8's error grows with the outliers and stays above
/// bf16's, so the test notices both a fix (then tighten it) and a change that stops injecting
/// anything; and that the split keeps ×20 below 3.5e-2.
#[test]
#[ignore = "needs ../shared/reference/dav2 (run with --include-ignored)"]
fn int8_with_outlier_channels_injected_into_the_network() {
    use moma_depth::Precision;
    let dir = tempfile::tempdir().unwrap();
    let name = "tiny-rel";
    let config = tiny_config(&reference_dir(), name);
    let input = reference_input(&reference_dir(), name);
    let mut errors = Vec::new();
    for factor in [1.0f32, 20.0, 60.0] {
        let path = with_outlier_channels(name, factor, dir.path());
        let f = forward(&path, &config, &input, Precision::F32);
        for p in [Precision::Int8, Precision::Bf16] {
            let q = forward(&path, &config, &input, p);
            let (max, mean) = relative_errors(&q, &f);
            eprintln!(
                "{name}, LayerNorm channels ×{factor}: {p:?} vs f32: max {max:.3e}, mean {mean:.3e} of the output range"
            );
            errors.push((factor, p, max, mean));
        }
    }
    let max =
        |factor: f32, p: Precision| errors.iter().find(|e| e.0 == factor && e.1 == p).unwrap().2;
    for p in [Precision::Int8, Precision::Bf16] {
        let e = errors.iter().find(|e| e.0 == 1.0 && e.1 == p).unwrap();
        assert!(e.2 <= 1e-2 && e.3 <= 2e-3, "without outliers: {e:?}");
    }
    assert!(
        max(1.0, Precision::Int8) < max(20.0, Precision::Int8)
            && max(20.0, Precision::Int8) < max(60.0, Precision::Int8),
        "{errors:?}"
    );
    assert!(
        max(20.0, Precision::Int8) > 2.0 * max(20.0, Precision::Bf16),
        "{errors:?}"
    );
    assert!(max(20.0, Precision::Int8) < 3.5e-2, "{errors:?}");
}
