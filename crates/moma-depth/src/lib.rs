//! # moma-depth — Depth Anything V2 as a MOMA prediction source
//!
//! One [`DepthModel`] interface, shared exact pre/post-processing ([`preprocess`]), and backends:
//! candle (pure Rust, default feature `candle`; `cuda` / `metal` passed through) and ONNX Runtime
//! (feature `onnx`, runtime library loaded dynamically).
//!
//! CONTRACT between the work items: keep [`DepthModel`], [`ModelSpec`] and the [`preprocess`]
//! function names; backends live in their own modules.
//!
//! One frame: RGB → [`DepthModel::predict`] → [`Prediction`] (with its kind) at the image's
//! size, which `moma_core::Calibration::align` turns into metres. The network input keeps the
//! image's aspect (docs/method.md §5):
//!
//! ```
//! use moma_core::ImageSize;
//! use moma_depth::preprocess::network_input_size;
//! // 640×480 → 686×518: both sides ≥ 518 and multiples of 14
//! assert_eq!(network_input_size(ImageSize::new(640, 480), 518)?, ImageSize::new(686, 518));
//! # Ok::<(), moma_depth::DepthError>(())
//! ```
//!
//! ```no_run
//! use moma_depth::{Backbone, Backend, Head, LoadSpec, ModelSpec, load};
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let model = ModelSpec { backbone: Backbone::Vits, head: Head::Relative, input_size: 518 };
//! let spec = LoadSpec::new("depth_anything_v2_vits.safetensors", model, Backend::Candle);
//! let mut model = load(&spec)?;
//! let rgb = image::open("frame.png")?.to_rgb8(); // moma_io::read_rgb checks sizes and bit depth
//! let prediction = model.predict(&rgb)?; // inverse depth (relative head), H×W
//! # Ok(()) }
//! ```

#[cfg(feature = "candle")]
pub mod candle;
mod config;
pub mod error;
pub mod hub;
mod loader;
#[cfg(feature = "onnx")]
pub mod onnx;
pub mod preprocess;
pub mod weights_limits;

pub use config::{CustomArch, ModelConfigFile};
pub use error::{DepthError, Result};
pub use loader::{Backend, DeviceRequest, LoadOptions, LoadSpec, Precision, load};

use moma_core::{Prediction, PredictionKind};
use ndarray::{Array2, Array3};
use serde::{Deserialize, Serialize};

/// Backbone size.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backbone {
    /// ViT-S (embed 384, depth 12, 6 heads).
    Vits,
    /// ViT-B (embed 768, depth 12, 12 heads).
    Vitb,
    /// ViT-L (embed 1024, depth 24, 16 heads).
    Vitl,
    /// Any other size, e.g. the tiny test models (from a JSON file, see [`ModelConfigFile`]).
    Custom(CustomArch),
}

impl std::str::FromStr for Backbone {
    type Err = String;

    /// A preset by name, case-insensitive: `vits`, `vitb`, `vitl` (a custom size comes from a
    /// configuration file instead).
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "vits" => Ok(Self::Vits),
            "vitb" => Ok(Self::Vitb),
            "vitl" => Ok(Self::Vitl),
            _ => Err(format!(
                "unknown model '{s}' (expected one of: vits, vitb, vitl)"
            )),
        }
    }
}

/// Output head.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase", tag = "head")]
pub enum Head {
    /// Relative head: ReLU, inverse depth (arbitrary scale).
    Relative,
    /// Metric head: Sigmoid × `max_depth_m`, depth in metres.
    Metric {
        /// Largest representable depth, metres (20 indoor, 80 outdoor).
        max_depth_m: f32,
    },
}

impl Head {
    /// The head called `name` (`relative` or `metric`, case-insensitive); a metric head with
    /// maximum depth `max_depth_m` (metres, positive and finite; unused for `relative`).
    ///
    /// # Errors
    /// An unknown name; a metric head with a maximum depth that is not a positive number.
    pub fn from_name(name: &str, max_depth_m: f32) -> std::result::Result<Self, String> {
        match name.trim().to_ascii_lowercase().as_str() {
            "relative" => Ok(Self::Relative),
            "metric" if max_depth_m.is_finite() && max_depth_m > 0.0 => {
                Ok(Self::Metric { max_depth_m })
            }
            "metric" => Err(format!(
                "max depth {max_depth_m} must be a positive number of metres"
            )),
            _ => Err(format!(
                "unknown head '{name}' (expected one of: relative, metric)"
            )),
        }
    }

    /// The kind of map this head predicts.
    pub fn prediction_kind(&self) -> PredictionKind {
        match self {
            Self::Relative => PredictionKind::RelativeDisparity,
            Self::Metric { .. } => PredictionKind::MetricDepth,
        }
    }
}

/// Which network a backend runs: backbone, head and pre-processing size.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ModelSpec {
    /// Backbone.
    pub backbone: Backbone,
    /// Head.
    pub head: Head,
    /// Lower bound of the network input's short side, pixels (518 by default; multiple of 14).
    pub input_size: usize,
}

/// A monocular depth model: RGB in, a [`Prediction`] (with its kind) out, at the image's resolution.
///
/// Every model is [`Send`]: a robot program can load it on one thread and move it to a worker
/// thread (`Box<dyn DepthModel>`, as [`load`] returns, is `Send` too). Inference takes
/// `&mut self`, so the trait does not require [`Sync`]; both backends are nevertheless `Sync`
/// (candle's tensors are immutable and reference-counted, an ONNX Runtime session may be shared
/// across threads), which the crate checks at compile time.
pub trait DepthModel: Send {
    /// What the model is.
    fn spec(&self) -> ModelSpec;

    /// Where and how it runs (backend, device, precision), for provenance records.
    fn runtime(&self) -> String {
        "unspecified".into()
    }

    /// Runs the network on a pre-processed input `(3, H, W)` (ImageNet-normalised RGB, H and W
    /// multiples of 14) and returns the raw output `(H, W)` at network resolution.
    ///
    /// # Errors
    /// Shape errors and backend failures.
    fn forward_net(&mut self, input: &Array3<f32>) -> Result<Array2<f32>>;

    /// RGB image (8-bit) → prediction at the image's size: [`preprocess::preprocess`] →
    /// [`DepthModel::forward_net`] → [`preprocess::resize_bilinear_align_corners`].
    ///
    /// # Errors
    /// As [`DepthModel::forward_net`].
    fn predict(&mut self, rgb: &image::RgbImage) -> Result<Prediction> {
        let spec = self.spec();
        let input = preprocess::preprocess(rgb, spec.input_size)?;
        let net = self.forward_net(&input)?;
        let full = preprocess::resize_bilinear_align_corners(
            &net.view(),
            rgb.height() as usize,
            rgb.width() as usize,
        );
        Ok(Prediction::new(full, spec.head.prediction_kind()))
    }
}

/// Compile-time checks: the trait objects and both backends can cross threads.
#[allow(dead_code)]
const _: () = {
    const fn assert_send<T: Send + ?Sized>() {}
    const fn assert_send_sync<T: Send + Sync + ?Sized>() {}
    assert_send::<dyn DepthModel>();
    assert_send::<Box<dyn DepthModel>>();
    #[cfg(feature = "candle")]
    assert_send_sync::<candle::CandleDepthModel>();
    #[cfg(feature = "onnx")]
    assert_send_sync::<onnx::OnnxDepthModel>();
};
