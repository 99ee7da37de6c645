//! Choosing and loading a backend: the one entry point applications call.

use std::fmt;
use std::path::PathBuf;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use crate::{DepthError, DepthModel, ModelSpec, Result};

/// Inference backend.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// Pure-Rust candle (`.safetensors` or PyTorch `.pth` weights; feature `candle`, GPU with
    /// `cuda` / `metal`).
    Candle,
    /// ONNX Runtime (`.onnx` models; feature `onnx`, runtime library loaded at run time).
    Onnx,
}

/// Where the network should run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DeviceRequest {
    /// The first GPU this build supports and the machine has (CUDA, then Metal), else the CPU.
    #[default]
    Auto,
    /// The CPU (all cores).
    Cpu,
    /// CUDA GPU with this ordinal (candle built with feature `cuda`).
    Cuda(usize),
    /// Metal GPU with this ordinal (candle built with feature `metal`).
    Metal(usize),
}

impl FromStr for DeviceRequest {
    type Err = String;

    /// `auto`, `cpu`, `cuda`, `cuda:N`, `metal`, `metal:N`.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let s = s.trim().to_ascii_lowercase();
        let (name, ordinal) = match s.split_once(':') {
            Some((name, n)) => {
                let n = n
                    .parse::<usize>()
                    .map_err(|_| format!("bad device ordinal in {s:?} (expected e.g. cuda:0)"))?;
                (name, Some(n))
            }
            None => (s.as_str(), None),
        };
        match (name, ordinal) {
            ("auto", None) => Ok(Self::Auto),
            ("cpu", None) => Ok(Self::Cpu),
            ("cuda", n) => Ok(Self::Cuda(n.unwrap_or(0))),
            ("metal", n) => Ok(Self::Metal(n.unwrap_or(0))),
            _ => Err(format!(
                "unknown device {s:?} (expected auto, cpu, cuda[:N] or metal[:N])"
            )),
        }
    }
}

impl fmt::Display for DeviceRequest {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Auto => f.write_str("auto"),
            Self::Cpu => f.write_str("cpu"),
            Self::Cuda(i) => write!(f, "cuda:{i}"),
            Self::Metal(i) => write!(f, "metal:{i}"),
        }
    }
}

/// Arithmetic precision of the network. Outputs are always returned as `f32`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// 32-bit floats: the reference precision (parity ≤ 1e-5 of the output range).
    #[default]
    F32,
    /// IEEE half precision (GPU; on the CPU it works but is slower than f32).
    F16,
    /// bfloat16: on a GPU the whole network; on the CPU the ViT encoder's linear layers and
    /// attention products (bf16 weights and activations, f32 sums, AVX512-BF16 where the CPU
    /// has it), the rest f32.
    Bf16,
    /// int8 linear layers in the ViT encoder (qkv, proj, MLP), the rest f32: CPU only (candle).
    /// Weights per output channel, activations per token, AVX512-VNNI where the CPU has it.
    Int8,
}

impl FromStr for Precision {
    type Err = String;

    /// `f32`/`float32`, `f16`/`float16`, `bf16`/`bfloat16`, `int8`/`i8`, case-insensitive.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "f32" | "float32" => Ok(Self::F32),
            "f16" | "float16" => Ok(Self::F16),
            "bf16" | "bfloat16" => Ok(Self::Bf16),
            "int8" | "i8" => Ok(Self::Int8),
            _ => Err(format!(
                "unknown dtype '{s}' (expected one of: f32, f16, bf16, int8)"
            )),
        }
    }
}

/// How to load a model: backend, device and precision.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct LoadOptions {
    /// Inference backend.
    pub backend: Backend,
    /// Device (candle; the ONNX backend runs on the CPU execution provider).
    pub device: DeviceRequest,
    /// Arithmetic precision (candle; the ONNX backend runs the model's own precision).
    pub precision: Precision,
}

impl LoadOptions {
    /// `backend` on the best available device, in `f32`.
    pub fn new(backend: Backend) -> Self {
        Self {
            backend,
            device: DeviceRequest::Auto,
            precision: Precision::F32,
        }
    }
}

/// What to load: the one input of [`load`].
#[derive(Debug, Clone, PartialEq)]
pub struct LoadSpec {
    /// The weights: `.safetensors` or PyTorch `.pth` (candle), `.onnx` (ONNX Runtime).
    pub weights: PathBuf,
    /// The network: backbone, head and input size.
    pub model: ModelSpec,
    /// Backend, device and precision.
    pub options: LoadOptions,
    /// A LoRA adapter file merged into the weights at load time (candle backend only).
    pub adapter: Option<PathBuf>,
}

impl LoadSpec {
    /// `weights` for `model` with `backend`, in `f32` on the best device this build supports,
    /// without an adapter.
    pub fn new(weights: impl Into<PathBuf>, model: ModelSpec, backend: Backend) -> Self {
        Self {
            weights: weights.into(),
            model,
            options: LoadOptions::new(backend),
            adapter: None,
        }
    }
}

/// Loads a depth model as `spec` says: what `moma predict`/`align`/`grasp`/`eval`, Python's
/// `DepthModel` and the trainer's reload check all call.
///
/// # Errors
/// [`DepthError::Unavailable`] when this build lacks the backend or device (or the ONNX Runtime
/// library is missing), the precision is not supported there, or an adapter is given to the ONNX
/// backend; [`DepthError::Weights`] for unreadable or mismatching weights, or an unreadable
/// adapter or one made for other base weights or another model size.
#[cfg_attr(
    not(any(feature = "candle", feature = "onnx")),
    allow(unused_variables)
)]
pub fn load(spec: &LoadSpec) -> Result<Box<dyn DepthModel>> {
    let weights = spec.weights.as_path();
    if !weights.is_file() {
        return Err(DepthError::Weights {
            path: weights.display().to_string(),
            reason: "no such file".into(),
        });
    }
    let options = &spec.options;
    match options.backend {
        #[cfg(feature = "candle")]
        Backend::Candle => {
            let device = crate::candle::open_device(options.device)?;
            Ok(Box::new(
                crate::candle::CandleDepthModel::load_with_precision(
                    weights,
                    crate::candle::DepthAnythingConfig::from_spec(&spec.model),
                    &device,
                    options.precision,
                    spec.adapter.as_deref(),
                )?,
            ))
        }
        #[cfg(not(feature = "candle"))]
        Backend::Candle => Err(DepthError::Unavailable(
            "this build has no candle backend (rebuild with `--features candle`)".into(),
        )),
        Backend::Onnx if spec.adapter.is_some() => Err(DepthError::Unavailable(
            "LoRA adapters are merged by the candle backend (use --backend candle, or `moma lora merge` for other runtimes)".into(),
        )),
        #[cfg(feature = "onnx")]
        Backend::Onnx => {
            if !matches!(options.device, DeviceRequest::Auto | DeviceRequest::Cpu) {
                return Err(DepthError::Unavailable(format!(
                    "the ONNX Runtime backend runs on the CPU execution provider only (asked for {}); use --backend candle on a GPU",
                    options.device
                )));
            }
            if options.precision != Precision::F32 {
                return Err(DepthError::Unavailable(
                    "the ONNX Runtime backend runs the model's own precision; --dtype applies to the candle backend".into(),
                ));
            }
            Ok(Box::new(crate::onnx::OnnxDepthModel::load(
                weights,
                spec.model,
                &crate::onnx::OnnxOptions::default(),
            )?))
        }
        #[cfg(not(feature = "onnx"))]
        Backend::Onnx => Err(DepthError::Unavailable(
            "this build has no ONNX Runtime backend (rebuild with `--features onnx`, see docs/depth-model.md)".into(),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_once_with_the_valid_names_in_the_error() {
        assert_eq!("VitS".parse::<crate::Backbone>(), Ok(crate::Backbone::Vits));
        assert!(
            "vitx"
                .parse::<crate::Backbone>()
                .unwrap_err()
                .contains("vits, vitb, vitl")
        );
        assert_eq!("bfloat16".parse::<Precision>(), Ok(Precision::Bf16));
        assert!(
            "f64"
                .parse::<Precision>()
                .unwrap_err()
                .contains("f32, f16, bf16")
        );
        assert_eq!(
            crate::Head::from_name("relative", f32::NAN),
            Ok(crate::Head::Relative)
        );
        assert_eq!(
            crate::Head::from_name("Metric", 20.0),
            Ok(crate::Head::Metric { max_depth_m: 20.0 })
        );
        assert!(crate::Head::from_name("metric", 0.0).is_err());
        assert!(
            crate::Head::from_name("ordinal", 20.0)
                .unwrap_err()
                .contains("relative, metric")
        );
    }

    #[test]
    fn device_requests_parse_and_print() {
        for (s, want) in [
            ("auto", DeviceRequest::Auto),
            ("CPU", DeviceRequest::Cpu),
            ("cuda", DeviceRequest::Cuda(0)),
            ("cuda:1", DeviceRequest::Cuda(1)),
            ("metal:0", DeviceRequest::Metal(0)),
        ] {
            assert_eq!(s.parse::<DeviceRequest>(), Ok(want), "{s}");
        }
        assert_eq!(DeviceRequest::Cuda(2).to_string(), "cuda:2");
        assert_eq!(
            "cuda:2".parse::<DeviceRequest>(),
            Ok(DeviceRequest::Cuda(2))
        );
        for bad in ["gpu", "cuda:x", "cpu:1", ""] {
            assert!(bad.parse::<DeviceRequest>().is_err(), "{bad}");
        }
    }
}
