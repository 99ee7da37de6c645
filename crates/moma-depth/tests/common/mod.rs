//! Shared helpers of the depth-model tests (both backends): locating `../shared/reference/dav2` and reading it.
#![allow(dead_code)]

use std::path::PathBuf;

#[cfg(feature = "candle")]
use moma_depth::candle::DepthAnythingConfig;
#[cfg(feature = "candle")]
use moma_depth::{Backbone, Head};
use ndarray::{Array2, Array3};
use ndarray_npy::read_npy;

/// The five parity reference models of `shared/reference/dav2/README.md`.
pub const MODELS: [&str; 5] = [
    "tiny-rel",
    "tiny-rel-392",
    "tiny-metric",
    "tiny-metric-392",
    "vits-rel",
];

/// The shared folder: `$MOMA_SHARED_DIR`, else `../shared` beside the workspace
/// (`CARGO_MANIFEST_DIR/../../../shared`).
///
/// Tests that call this are `#[ignore = "needs ../shared ..."]`: they run only when asked for
/// (`-- --include-ignored`, as CI does), so a missing folder is a failure, never a silent pass.
///
/// # Panics
/// When the folder does not exist, naming where it was looked for.
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

/// `shared_dir()/reference/dav2`, the Depth Anything V2 reference data.
///
/// # Panics
/// As [`shared_dir`]; when the folder has no `input.png`.
pub fn reference_dir() -> PathBuf {
    let dir = shared_dir().join("reference/dav2");
    assert!(
        dir.join("input.png").is_file(),
        "Depth Anything V2 reference data not found at {} (no input.png)",
        dir.display()
    );
    dir
}

/// `NAME.input.npy`: the official pre-processed network input `(3, H, W)`.
pub fn reference_input(dir: &std::path::Path, name: &str) -> Array3<f32> {
    read_npy(dir.join(format!("{name}.input.npy"))).expect("read input.npy")
}

/// `NAME.output_net.npy` (`which = "net"`) or `NAME.output_full.npy` (`which = "full"`).
pub fn reference_output(dir: &std::path::Path, name: &str, which: &str) -> Array2<f32> {
    read_npy(dir.join(format!("{name}.output_{which}.npy"))).expect("read output npy")
}

/// `input.png` as 8-bit RGB.
pub fn reference_image(dir: &std::path::Path) -> image::RgbImage {
    image::open(dir.join("input.png"))
        .expect("read input.png")
        .to_rgb8()
}

/// `NAME.json` parsed.
pub fn reference_json(dir: &std::path::Path, name: &str) -> serde_json::Value {
    let text = std::fs::read_to_string(dir.join(format!("{name}.json"))).expect("read json");
    serde_json::from_str(&text).expect("parse json")
}

/// Maximum absolute difference and the output range (max − min) of the reference.
pub fn max_abs_err(got: &Array2<f32>, want: &Array2<f32>) -> (f32, f32) {
    assert_eq!(got.dim(), want.dim(), "shape");
    let err = got
        .iter()
        .zip(want)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    let lo = want.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = want.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    (err, hi - lo)
}

/// The tiny reference architecture (`shared/reference/dav2/README.md`): ViT embed 64, depth 4,
/// 2 heads, layers [0, 1, 2, 3]; DPT features 16, out_channels [8, 16, 32, 64]; head and input size
/// from `NAME.json`.
#[cfg(feature = "candle")]
pub fn tiny_config(dir: &std::path::Path, name: &str) -> DepthAnythingConfig {
    let json = reference_json(dir, name);
    let head = match json["head"].as_str().unwrap() {
        "relative" => Head::Relative,
        "metric" => Head::Metric {
            max_depth_m: json["max_depth"].as_f64().unwrap() as f32,
        },
        other => panic!("unknown head {other}"),
    };
    DepthAnythingConfig {
        backbone: Backbone::Vits,
        embed_dim: 64,
        depth: 4,
        num_heads: 2,
        mlp_hidden_dim: 256,
        intermediate_layers: [0, 1, 2, 3],
        features: 16,
        out_channels: [8, 16, 32, 64],
        head,
        input_size: json["input_size"].as_u64().unwrap() as usize,
        ..DepthAnythingConfig::vit_small(head)
    }
}

/// A committed parity reference (safetensors written by a benches/pytorch script): tensors as
/// f64 on the CPU, and its metadata.
#[cfg(feature = "candle")]
pub struct ParityReference {
    /// Tensors by name, f64.
    pub tensors: std::collections::HashMap<String, candle_core::Tensor>,
    /// The `__metadata__` strings.
    pub meta: std::collections::HashMap<String, String>,
}

#[cfg(feature = "candle")]
impl ParityReference {
    /// Reads `tests/data/FILE` and checks its `format` metadata.
    ///
    /// # Panics
    /// A missing or unreadable file, another format.
    pub fn load(file: &str, format: &str) -> Self {
        use candle_core::{DType, Device};
        let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data")
            .join(file);
        let bytes = std::fs::read(&path)
            .unwrap_or_else(|e| panic!("reading {}: {e} (committed test data)", path.display()));
        let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
        let meta = header.metadata().clone().unwrap_or_default();
        assert_eq!(meta.get("format").map(String::as_str), Some(format));
        let tensors = candle_core::safetensors::load(&path, &Device::Cpu)
            .unwrap()
            .into_iter()
            .map(|(k, v)| (k, v.to_dtype(DType::F64).unwrap()))
            .collect();
        Self { tensors, meta }
    }

    /// The tensor `key`.
    ///
    /// # Panics
    /// When the file lacks it.
    pub fn get(&self, key: &str) -> &candle_core::Tensor {
        self.tensors
            .get(key)
            .unwrap_or_else(|| panic!("reference file lacks {key}"))
    }

    /// What the training cases run on: the tiny network of `reference`, the `crop` of its
    /// reference input, and the stored ground truth `gt_m` (metres, row-major) of that crop.
    ///
    /// # Panics
    /// Without ../shared, or a file lacking these entries.
    pub fn training_crop(&self) -> (DepthAnythingConfig, Array3<f32>, Vec<f32>, (usize, usize)) {
        use ndarray::s;
        let dir = reference_dir();
        let name = self.meta["reference"].clone();
        let config = tiny_config(&dir, &name);
        let crop = self.meta_json("crop");
        let c = |k: &str| crop[k].as_u64().unwrap() as usize;
        let (y0, x0, h, w) = (c("y0"), c("x0"), c("h"), c("w"));
        let input = reference_input(&dir, &name)
            .slice(s![.., y0..y0 + h, x0..x0 + w])
            .to_owned();
        let gt: Vec<f32> = self.tensors["gt_m"]
            .to_dtype(candle_core::DType::F32)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        (config, input, gt, (h, w))
    }

    /// The metadata value `key` as JSON.
    pub fn meta_json(&self, key: &str) -> serde_json::Value {
        serde_json::from_str(&self.meta[key]).unwrap()
    }
}

/// A tensor's values as f64.
#[cfg(feature = "candle")]
pub fn flat(t: &candle_core::Tensor) -> Vec<f64> {
    t.to_dtype(candle_core::DType::F64)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

/// `max |got − want| / max |want|` (the max-abs norm of the difference relative to the
/// reference tensor's max-abs value; the plain max-abs difference when the reference is 0).
#[cfg(feature = "candle")]
pub fn rel_max(got: &candle_core::Tensor, want: &candle_core::Tensor) -> f64 {
    assert_eq!(got.dims(), want.dims(), "shape");
    let (g, w) = (flat(got), flat(want));
    let err = g
        .iter()
        .zip(&w)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    let scale = w.iter().map(|b| b.abs()).fold(0.0, f64::max);
    if scale == 0.0 { err } else { err / scale }
}
