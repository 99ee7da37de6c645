//! Choosing and loading a backend: the one entry point applications call.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::{DepthError, DepthModel, ModelSpec, Result};

/// Inference backend.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// Pure-Rust candle (`.safetensors` weights; feature `candle`, GPU with `cuda` / `metal`).
    Candle,
    /// ONNX Runtime (`.onnx` models; feature `onnx`, runtime library loaded at run time).
    Onnx,
}

/// Loads `weights` for `spec` with `backend`. The candle backend runs on the best device this
/// build supports (CUDA, then Metal, else the CPU).
///
/// # Errors
/// [`DepthError::Unavailable`] when this build lacks the backend (or the ONNX Runtime library is
/// missing); [`DepthError::Weights`] for unreadable or mismatching weights.
pub fn load_model(
    weights: impl AsRef<Path>,
    spec: ModelSpec,
    backend: Backend,
) -> Result<Box<dyn DepthModel>> {
    let weights = weights.as_ref();
    if !weights.is_file() {
        return Err(DepthError::Weights {
            path: weights.display().to_string(),
            reason: "no such file".into(),
        });
    }
    match backend {
        #[cfg(feature = "candle")]
        Backend::Candle => {
            let device = crate::candle::DeviceChoice::best_available().device()?;
            Ok(Box::new(crate::candle::CandleDepthModel::load_spec(weights, &spec, &device)?))
        }
        #[cfg(not(feature = "candle"))]
        Backend::Candle => Err(DepthError::Unavailable(
            "this build has no candle backend (rebuild with `--features candle`)".into(),
        )),
        #[cfg(feature = "onnx")]
        Backend::Onnx => Ok(Box::new(crate::onnx::OnnxDepthModel::load(weights, spec)?)),
        #[cfg(not(feature = "onnx"))]
        Backend::Onnx => Err(DepthError::Unavailable(
            "this build has no ONNX Runtime backend (rebuild with `--features onnx`, see docs/depth-model.md)".into(),
        )),
    }
}
