//! The candle backend: Depth Anything V2 (DINOv2 ViT-S/B/L + DPT head) in pure Rust, faithful to
//! the official PyTorch code (`DepthAnything/Depth-Anything-V2`, commit a561b84; docs/method.md §5).
//!
//! ```no_run
//! use moma_depth::candle::{CandleDepthModel, DepthAnythingConfig, open_device};
//! use moma_depth::{DepthModel, DeviceRequest, Head};
//!
//! let device = open_device(DeviceRequest::Auto)?;
//! let config = DepthAnythingConfig::vit_small(Head::Relative);
//! let weights = "depth_anything_v2_vits.safetensors";
//! let mut model = CandleDepthModel::load(weights, config, &device, candle_core::DType::F32, None)?;
//! let rgb = image::open("frame.png").unwrap().to_rgb8();
//! let prediction = model.predict(&rgb)?; // inverse depth at the image's size
//! # Ok::<(), moma_depth::DepthError>(())
//! ```
//!
//! Not used: candle-transformers' `depth_anything_v2` (square inputs only, nearest-neighbour
//! upsampling and position-embedding interpolation, LayerNorm eps 1e-5, no metric head).

mod bf16;
pub mod dinov2;
pub mod dpt;
mod heap;
mod int8;
mod ops;
pub mod train;
mod winograd;

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use ndarray::{Array2, Array3};
use serde::{Deserialize, Serialize};

use crate::preprocess::{DEFAULT_INPUT_SIZE, PATCH_SIZE};
use crate::{Backbone, DepthError, DepthModel, DeviceRequest, Head, ModelSpec, Precision, Result};

pub use dinov2::DinoV2;
pub use dpt::DptHead;

/// Side of the stored square position-embedding grid: 518 / 14 = 37 (`img_size=518` in
/// `dinov2.py::DINOv2`).
pub const POS_GRID: usize = 37;

/// LayerNorm epsilon of every DINOv2 norm (`partial(nn.LayerNorm, eps=1e-6)` in `vision_transformer.py`).
pub const LAYER_NORM_EPS: f64 = 1e-6;

/// Architecture of one Depth Anything V2 network. Presets: [`DepthAnythingConfig::vit_small`],
/// [`DepthAnythingConfig::vit_base`], [`DepthAnythingConfig::vit_large`]; any other size (e.g. the
/// tiny parity models) by filling the fields.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DepthAnythingConfig {
    /// The named backbone size this configuration is (custom sizes report the nearest one).
    pub backbone: Backbone,
    /// Token width of the ViT.
    pub embed_dim: usize,
    /// Number of transformer blocks.
    pub depth: usize,
    /// Attention heads per block (`embed_dim` must be a multiple).
    pub num_heads: usize,
    /// Hidden width of each block's MLP (4 × `embed_dim` in DINOv2).
    pub mlp_hidden_dim: usize,
    /// 0-based blocks whose normalised outputs feed the DPT head (`intermediate_layer_idx`).
    pub intermediate_layers: [usize; 4],
    /// Channels of the DPT fusion path (`features`).
    pub features: usize,
    /// Channels of the four DPT projections (`out_channels`).
    pub out_channels: [usize; 4],
    /// Relative (ReLU, inverse depth) or metric (Sigmoid × max depth, metres) head.
    pub head: Head,
    /// Lower bound of the network input's sides, pixels (518 for the released models).
    pub input_size: usize,
    /// Side of the stored square position-embedding grid (37).
    pub pos_grid: usize,
    /// LayerNorm epsilon (1e-6).
    pub layer_norm_eps: f64,
}

impl DepthAnythingConfig {
    fn preset(
        backbone: Backbone,
        (embed_dim, depth, num_heads): (usize, usize, usize),
        intermediate_layers: [usize; 4],
        features: usize,
        out_channels: [usize; 4],
        head: Head,
    ) -> Self {
        Self {
            backbone,
            embed_dim,
            depth,
            num_heads,
            mlp_hidden_dim: 4 * embed_dim,
            intermediate_layers,
            features,
            out_channels,
            head,
            input_size: DEFAULT_INPUT_SIZE,
            pos_grid: POS_GRID,
            layer_norm_eps: LAYER_NORM_EPS,
        }
    }

    /// ViT-S: embed 384, 12 blocks, 6 heads, layers [2, 5, 8, 11], features 64, out [48, 96, 192, 384].
    pub fn vit_small(head: Head) -> Self {
        Self::preset(
            Backbone::Vits,
            (384, 12, 6),
            [2, 5, 8, 11],
            64,
            [48, 96, 192, 384],
            head,
        )
    }

    /// ViT-B: embed 768, 12 blocks, 12 heads, layers [2, 5, 8, 11], features 128, out [96, 192, 384, 768].
    pub fn vit_base(head: Head) -> Self {
        Self::preset(
            Backbone::Vitb,
            (768, 12, 12),
            [2, 5, 8, 11],
            128,
            [96, 192, 384, 768],
            head,
        )
    }

    /// ViT-L: embed 1024, 24 blocks, 16 heads, layers [4, 11, 17, 23], features 256,
    /// out [256, 512, 1024, 1024].
    pub fn vit_large(head: Head) -> Self {
        Self::preset(
            Backbone::Vitl,
            (1024, 24, 16),
            [4, 11, 17, 23],
            256,
            [256, 512, 1024, 1024],
            head,
        )
    }

    /// A custom size ([`crate::ModelConfigFile`]); MLP hidden width 4 × `embed_dim`.
    pub fn custom(arch: crate::CustomArch, head: Head) -> Self {
        Self::preset(
            Backbone::Custom(arch),
            (arch.embed_dim, arch.depth, arch.num_heads),
            arch.intermediate_layers,
            arch.features,
            arch.out_channels,
            head,
        )
    }

    /// The preset of a [`ModelSpec`] (with its head and input size).
    pub fn from_spec(spec: &ModelSpec) -> Self {
        let mut c = match spec.backbone {
            Backbone::Vits => Self::vit_small(spec.head),
            Backbone::Vitb => Self::vit_base(spec.head),
            Backbone::Vitl => Self::vit_large(spec.head),
            Backbone::Custom(a) => Self::custom(a, spec.head),
        };
        c.input_size = spec.input_size;
        c
    }

    /// The [`ModelSpec`] of this configuration.
    pub fn spec(&self) -> ModelSpec {
        ModelSpec {
            backbone: self.backbone,
            head: self.head,
            input_size: self.input_size,
        }
    }

    fn validate(&self) -> Result<()> {
        let bad = |m: String| {
            Err(DepthError::Shape(format!(
                "invalid DepthAnythingConfig: {m}"
            )))
        };
        if self.num_heads == 0 || !self.embed_dim.is_multiple_of(self.num_heads) {
            return bad(format!(
                "embed_dim {} not a multiple of num_heads {}",
                self.embed_dim, self.num_heads
            ));
        }
        if let Some(l) = self.intermediate_layers.iter().find(|&&l| l >= self.depth) {
            return bad(format!("intermediate layer {l} >= depth {}", self.depth));
        }
        if self.features < 2 || self.pos_grid == 0 {
            return bad("features < 2 or empty position grid".into());
        }
        Ok(())
    }

    /// Every tensor an official checkpoint of this architecture holds, with its shape:
    /// `(name, shape, required)`; `pretrained.mask_token` (training only) is optional.
    pub fn expected_tensors(&self) -> Vec<(String, Vec<usize>, bool)> {
        let d = self.embed_dim;
        let p = PATCH_SIZE;
        let g = self.pos_grid;
        let mut t: Vec<(String, Vec<usize>, bool)> = vec![];
        let mut add = |name: String, shape: Vec<usize>| t.push((name, shape, true));
        add("pretrained.cls_token".into(), vec![1, 1, d]);
        add("pretrained.pos_embed".into(), vec![1, 1 + g * g, d]);
        add(
            "pretrained.patch_embed.proj.weight".into(),
            vec![d, 3, p, p],
        );
        add("pretrained.patch_embed.proj.bias".into(), vec![d]);
        for i in 0..self.depth {
            let b = format!("pretrained.blocks.{i}");
            for n in ["norm1", "norm2"] {
                add(format!("{b}.{n}.weight"), vec![d]);
                add(format!("{b}.{n}.bias"), vec![d]);
            }
            add(format!("{b}.attn.qkv.weight"), vec![3 * d, d]);
            add(format!("{b}.attn.qkv.bias"), vec![3 * d]);
            add(format!("{b}.attn.proj.weight"), vec![d, d]);
            add(format!("{b}.attn.proj.bias"), vec![d]);
            add(format!("{b}.ls1.gamma"), vec![d]);
            add(format!("{b}.ls2.gamma"), vec![d]);
            add(format!("{b}.mlp.fc1.weight"), vec![self.mlp_hidden_dim, d]);
            add(format!("{b}.mlp.fc1.bias"), vec![self.mlp_hidden_dim]);
            add(format!("{b}.mlp.fc2.weight"), vec![d, self.mlp_hidden_dim]);
            add(format!("{b}.mlp.fc2.bias"), vec![d]);
        }
        add("pretrained.norm.weight".into(), vec![d]);
        add("pretrained.norm.bias".into(), vec![d]);
        let oc = self.out_channels;
        let f = self.features;
        let h = "depth_head";
        for (i, &c) in oc.iter().enumerate() {
            add(format!("{h}.projects.{i}.weight"), vec![c, d, 1, 1]);
            add(format!("{h}.projects.{i}.bias"), vec![c]);
            add(
                format!("{h}.scratch.layer{}_rn.weight", i + 1),
                vec![f, c, 3, 3],
            );
        }
        add(
            format!("{h}.resize_layers.0.weight"),
            vec![oc[0], oc[0], 4, 4],
        );
        add(format!("{h}.resize_layers.0.bias"), vec![oc[0]]);
        add(
            format!("{h}.resize_layers.1.weight"),
            vec![oc[1], oc[1], 2, 2],
        );
        add(format!("{h}.resize_layers.1.bias"), vec![oc[1]]);
        add(
            format!("{h}.resize_layers.3.weight"),
            vec![oc[3], oc[3], 3, 3],
        );
        add(format!("{h}.resize_layers.3.bias"), vec![oc[3]]);
        for r in 1..=4 {
            let b = format!("{h}.scratch.refinenet{r}");
            for u in ["resConfUnit1", "resConfUnit2"] {
                for cv in ["conv1", "conv2"] {
                    add(format!("{b}.{u}.{cv}.weight"), vec![f, f, 3, 3]);
                    add(format!("{b}.{u}.{cv}.bias"), vec![f]);
                }
            }
            add(format!("{b}.out_conv.weight"), vec![f, f, 1, 1]);
            add(format!("{b}.out_conv.bias"), vec![f]);
        }
        add(
            format!("{h}.scratch.output_conv1.weight"),
            vec![f / 2, f, 3, 3],
        );
        add(format!("{h}.scratch.output_conv1.bias"), vec![f / 2]);
        add(
            format!("{h}.scratch.output_conv2.0.weight"),
            vec![32, f / 2, 3, 3],
        );
        add(format!("{h}.scratch.output_conv2.0.bias"), vec![32]);
        add(
            format!("{h}.scratch.output_conv2.2.weight"),
            vec![1, 32, 1, 1],
        );
        add(format!("{h}.scratch.output_conv2.2.bias"), vec![1]);
        t.push(("pretrained.mask_token".into(), vec![1, d], false));
        t
    }

    /// Compares a checkpoint's tensors `(name → shape)` with [`Self::expected_tensors`]; `Err` holds a
    /// readable list of missing keys, unexpected keys and shape mismatches.
    pub fn check_tensors(
        &self,
        found: &BTreeMap<String, Vec<usize>>,
    ) -> std::result::Result<(), String> {
        let expected = self.expected_tensors();
        let mut missing = vec![];
        let mut mismatched = vec![];
        for (name, shape, required) in &expected {
            match found.get(name) {
                None if *required => missing.push(name.clone()),
                None => {}
                Some(s) if s != shape => {
                    mismatched.push(format!("{name}: expected {shape:?}, found {s:?}"))
                }
                Some(_) => {}
            }
        }
        let known: BTreeSet<&str> = expected.iter().map(|(n, _, _)| n.as_str()).collect();
        let unexpected: Vec<&String> = found
            .keys()
            .filter(|k| !known.contains(k.as_str()))
            .collect();
        if missing.is_empty() && unexpected.is_empty() && mismatched.is_empty() {
            return Ok(());
        }
        fn list<T: std::fmt::Display>(what: &str, items: &[T]) -> String {
            const SHOWN: usize = 20;
            if items.is_empty() {
                return String::new();
            }
            let mut s = format!("{} {what}: ", items.len());
            s += &items
                .iter()
                .take(SHOWN)
                .map(|i| i.to_string())
                .collect::<Vec<_>>()
                .join(", ");
            if items.len() > SHOWN {
                s += &format!(", ... ({} more)", items.len() - SHOWN);
            }
            s + "; "
        }
        let mut reason = format!(
            "checkpoint does not match Depth Anything V2 {:?} (embed {}, depth {}): ",
            self.backbone, self.embed_dim, self.depth
        );
        reason += &list("missing keys", &missing);
        reason += &list("unexpected keys", &unexpected);
        reason += &list("shape mismatches", &mismatched);
        Err(reason.trim_end_matches("; ").to_string())
    }
}

/// Opens the device `request` names. [`DeviceRequest::Auto`] is the first GPU this build supports
/// and the machine has (CUDA, then Metal), else the CPU.
///
/// # Errors
/// [`DepthError::Unavailable`] when this build lacks the feature or the device cannot be opened
/// (never for `Auto`).
pub fn open_device(request: DeviceRequest) -> Result<Device> {
    if request == DeviceRequest::Auto {
        // candle's `*_is_available` say what the build supports, not what the machine has: a
        // GPU build on a machine without the GPU (or its driver) runs on the CPU
        if cfg!(feature = "cuda")
            && candle_core::utils::cuda_is_available()
            && let Ok(device) = Device::new_cuda(0)
        {
            return Ok(device);
        }
        if cfg!(feature = "metal")
            && candle_core::utils::metal_is_available()
            && let Ok(device) = Device::new_metal(0)
        {
            return Ok(device);
        }
        return Ok(Device::Cpu);
    }
    match request {
        DeviceRequest::Auto | DeviceRequest::Cpu => Ok(Device::Cpu),
        DeviceRequest::Cuda(i) if cfg!(feature = "cuda") => Device::new_cuda(i)
            .map_err(|e| DepthError::Unavailable(format!("CUDA device {i}: {e}"))),
        DeviceRequest::Metal(i) if cfg!(feature = "metal") => Device::new_metal(i)
            .map_err(|e| DepthError::Unavailable(format!("Metal device {i}: {e}"))),
        DeviceRequest::Cuda(_) => Err(DepthError::Unavailable(
            "built without the `cuda` feature".into(),
        )),
        DeviceRequest::Metal(_) => Err(DepthError::Unavailable(
            "built without the `metal` feature".into(),
        )),
    }
}

fn backend(e: candle_core::Error) -> DepthError {
    DepthError::Candle {
        context: "running the network".into(),
        source: e,
    }
}

/// candle's error `e` while reading the weight file `path`.
fn weights_source(path: &Path) -> impl FnOnce(candle_core::Error) -> DepthError + '_ {
    move |source| DepthError::Candle {
        context: format!("cannot load weights from {}", path.display()),
        source,
    }
}

/// Depth Anything V2 on candle; implements [`DepthModel`]. Computes in the dtype it was loaded with
/// (`f32` by default; the CPU kernels of this crate are `f32`, other dtypes and devices use candle's
/// own ops) whatever the storage dtype of the checkpoint (f32, f16 or bf16).
#[derive(Debug)]
pub struct CandleDepthModel {
    config: DepthAnythingConfig,
    encoder: DinoV2,
    head: DptHead,
    device: Device,
    dtype: DType,
    /// The precision of the encoder's packed CPU layers ([`Self::pack_cpu`]), `None` when
    /// unpacked: named in [`DepthModel::runtime`], so that `predictions.json` records it.
    packed: Option<Precision>,
}

/// Whether this CPU has the instructions of `precision`'s packed kernel, and their name
/// (int8: AVX512-VNNI, bf16: AVX512-BF16; other precisions have no packed kernel).
fn cpu_instructions(precision: Precision) -> (bool, &'static str) {
    match precision {
        Precision::Int8 => (int8::has_vnni(), "AVX512-VNNI"),
        Precision::Bf16 => (bf16::has_bf16(), "AVX512-BF16"),
        Precision::F32 | Precision::F16 => (true, ""),
    }
}

/// The two checkpoint containers the official weights come in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum WeightsFormat {
    /// `.safetensors` (memory-mapped).
    Safetensors,
    /// PyTorch `torch.save` zip archive (`.pth`, `.pt`), as the official releases are.
    PyTorchZip,
}

impl WeightsFormat {
    /// From the first bytes of the file (a zip archive starts with `PK\x03\x04`), so a renamed file
    /// still loads; a legacy (pre-1.6, non-zip) PyTorch pickle is named as such.
    fn sniff(path: &Path) -> std::result::Result<Self, String> {
        use std::io::Read;
        let mut magic = [0u8; 8];
        let mut f = std::fs::File::open(path).map_err(|e| e.to_string())?;
        let n = f.read(&mut magic).map_err(|e| e.to_string())?;
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        if n >= 4 && magic[..4] == *b"PK\x03\x04" {
            Ok(Self::PyTorchZip)
        } else if n >= 2 && magic[0] == 0x80 && matches!(ext.as_deref(), Some("pth" | "pt" | "bin"))
        {
            Err("legacy (pre-1.6, non-zip) PyTorch pickle; re-save it with a current torch.save or convert it to .safetensors".into())
        } else {
            Ok(Self::Safetensors)
        }
    }
}

/// An opened checkpoint: its tensors `name → shape`, the names of non-float tensors, and the
/// variable backend that reads them.
struct OpenedCheckpoint {
    shapes: BTreeMap<String, Vec<usize>>,
    non_float: Vec<String>,
    backend: Box<dyn candle_nn::var_builder::SimpleBackend>,
}

impl OpenedCheckpoint {
    /// Lists `(name, shape, dtype)` of every tensor (`dtype` is `Err(name of the stored type)` when
    /// candle has no such dtype).
    fn new(
        tensors: impl Iterator<Item = (String, Vec<usize>, std::result::Result<DType, String>)>,
        backend: Box<dyn candle_nn::var_builder::SimpleBackend>,
    ) -> Self {
        let mut shapes = BTreeMap::new();
        let mut non_float = vec![];
        for (name, shape, dtype) in tensors {
            match dtype {
                Ok(DType::F32 | DType::F16 | DType::BF16 | DType::F64) => {}
                Ok(other) => non_float.push(format!("{name}: {other:?}")),
                Err(other) => non_float.push(format!("{name}: {other}")),
            }
            shapes.insert(name, shape);
        }
        Self {
            shapes,
            non_float,
            backend,
        }
    }

    /// A `.safetensors` checkpoint (memory-mapped).
    fn safetensors(path: &Path) -> Result<Self> {
        // SAFETY: the file is mapped read-only; as everywhere with mmap, it must not be truncated
        // while mapped. The mapping lives only during loading (weights are copied into tensors).
        let st = unsafe { candle_core::safetensors::MmapedSafetensors::new(path) }
            .map_err(weights_source(path))?;
        let listing: Vec<_> = st
            .tensors()
            .into_iter()
            .map(|(name, view)| {
                let dtype =
                    DType::try_from(view.dtype()).map_err(|_| format!("{:?}", view.dtype()));
                (name, view.shape().to_vec(), dtype)
            })
            .collect();
        Ok(Self::new(listing.into_iter(), Box::new(st)))
    }

    /// A PyTorch zip checkpoint: a plain state dict (the official releases), or one nested under
    /// `state_dict` or `model`.
    fn pytorch(path: &Path) -> Result<Self> {
        use candle_core::pickle::PthTensors;
        let mut pth = PthTensors::new(path, None).map_err(weights_source(path))?;
        for key in ["state_dict", "model"] {
            if !pth.tensor_infos().is_empty() {
                break;
            }
            if let Ok(nested) = PthTensors::new(path, Some(key)) {
                pth = nested;
            }
        }
        if pth.tensor_infos().is_empty() {
            return Err(DepthError::Weights {
                path: path.display().to_string(),
                reason: "no tensors found in the PyTorch archive (expected a state dict)".into(),
            });
        }
        let listing: Vec<_> = pth
            .tensor_infos()
            .iter()
            .map(|(name, info)| (name.clone(), info.layout.dims().to_vec(), Ok(info.dtype)))
            .collect();
        Ok(Self::new(listing.into_iter(), Box::new(pth)))
    }
}

/// Opens a checkpoint with the official key names (`.safetensors` memory-mapped, or a PyTorch
/// `.pth` zip archive) as a [`VarBuilder`] reading in `dtype` on `device`, after checking every
/// tensor name and shape against `config`.
///
/// # Errors
/// [`DepthError::Weights`] naming the file (unreadable, mismatching keys or shapes, non-float
/// tensors); [`DepthError::Shape`] for an inconsistent `config`.
pub fn open_checkpoint(
    path: &Path,
    config: &DepthAnythingConfig,
    device: &Device,
    dtype: DType,
) -> Result<VarBuilder<'static>> {
    let werr = |reason: String| DepthError::Weights {
        path: path.display().to_string(),
        reason,
    };
    config.validate()?;
    let opened = match WeightsFormat::sniff(path).map_err(werr)? {
        WeightsFormat::Safetensors => {
            crate::weights_limits::check_safetensors_file(path)?;
            OpenedCheckpoint::safetensors(path)
        }
        WeightsFormat::PyTorchZip => {
            crate::weights_limits::check_weights_file_size(path)?;
            OpenedCheckpoint::pytorch(path)
        }
    }?;
    config.check_tensors(&opened.shapes).map_err(werr)?;
    if !opened.non_float.is_empty() {
        return Err(werr(format!(
            "non-float tensors: {}",
            opened.non_float.join(", ")
        )));
    }
    Ok(VarBuilder::from_backend(
        opened.backend,
        dtype,
        device.clone(),
    ))
}

#[doc(hidden)]
pub use ops::ConvPath;

/// A stride-1, padding-1 3×3 convolution of `x` `(1, c_in, h, w)` with `weight`
/// `(c_out, c_in, 3, 3)` and `bias` `(c_out)` by one CPU path: for benchmarks of the DPT head's
/// convolutions (`examples/cpu_kernels.rs`), not a stable API.
///
/// # Errors
/// Shapes that do not match; a path that has no stride-1 form.
#[doc(hidden)]
pub fn conv3x3_by(x: &Tensor, weight: &Tensor, bias: &Tensor, path: ConvPath) -> Result<Tensor> {
    ops::conv3x3_path(x, weight, Some(bias), 1, ops::ConvFusion::default(), path).map_err(
        |source| DepthError::Candle {
            context: "conv3x3".into(),
            source,
        },
    )
}

/// One linear layer packed for the CPU kernels of `--dtype int8|bf16`, outside a model: for
/// benchmarks against other kernels (`examples/cpu_kernels.rs`), not a stable API.
#[doc(hidden)]
pub struct PackedLayer(Box<dyn ops::PackedLinear>);

impl PackedLayer {
    /// `weight_t` (`k × n`, row-major) and `bias` (`n`) in int8 (per-channel weights).
    ///
    /// # Errors
    /// Sizes that do not match; weights that are not finite.
    pub fn int8(weight_t: &[f32], k: usize, n: usize, bias: &[f32]) -> Result<Self> {
        Ok(Self(Box::new(
            <int8::QuantLinear as ops::PackedLinear>::pack(weight_t, k, n, bias).map_err(
                |source| DepthError::Candle {
                    context: "int8 layer".into(),
                    source,
                },
            )?,
        )))
    }

    /// The same in bf16.
    ///
    /// # Errors
    /// As [`Self::int8`].
    pub fn bf16(weight_t: &[f32], k: usize, n: usize, bias: &[f32]) -> Result<Self> {
        Ok(Self(Box::new(
            <bf16::Bf16Linear as ops::PackedLinear>::pack(weight_t, k, n, bias).map_err(
                |source| DepthError::Candle {
                    context: "bf16 layer".into(),
                    source,
                },
            )?,
        )))
    }

    /// `x·W + b` for `x` (`m × k`, row-major), on the rayon pool.
    pub fn forward(&self, x: &[f32], m: usize) -> Vec<f32> {
        self.0.forward(x, m, None)
    }
}

/// The candle dtype of `precision` on `device`. On the CPU, int8 and bf16 load f32 weights that
/// [`CandleDepthModel::pack_cpu`] then packs for their kernels.
///
/// # Errors
/// [`DepthError::Unavailable`] for int8 on a GPU.
pub fn precision_dtype(precision: Precision, device: &Device) -> Result<DType> {
    match precision {
        Precision::F32 => Ok(DType::F32),
        Precision::F16 => Ok(DType::F16),
        Precision::Bf16 | Precision::Int8 if device.is_cpu() => Ok(DType::F32),
        Precision::Int8 => Err(DepthError::Unavailable(
            "int8 is a CPU precision (AVX512-VNNI kernels); on a GPU use f16 or bf16".into(),
        )),
        Precision::Bf16 => Ok(DType::BF16),
    }
}

impl CandleDepthModel {
    /// Loads a checkpoint with the official key names (`pretrained.*`, `depth_head.*`) from a
    /// `.safetensors` file (memory-mapped) or a PyTorch `.pth` zip archive (the official release
    /// format), any float storage dtype, computing in `dtype` (see [`precision_dtype`]), with the
    /// LoRA adapter file `adapter` merged into the weights when given ([`train::merge_adapter`]).
    /// Applications call [`crate::load`]; this is the candle backend's constructor, for a custom
    /// `config`.
    ///
    /// # Errors
    /// [`DepthError::Weights`] when the file cannot be read or its tensors do not match `config`
    /// (the message lists missing and unexpected keys and shape mismatches), or for an
    /// unreadable adapter or one made for other base weights or another model size (naming the
    /// adapter); [`DepthError::Shape`] for an inconsistent `config`.
    pub fn load(
        path: impl AsRef<Path>,
        config: DepthAnythingConfig,
        device: &Device,
        dtype: DType,
        adapter: Option<&Path>,
    ) -> Result<Self> {
        let path = path.as_ref();
        // the adapter first: a missing or broken one is named before the (larger) weights load
        let Some((adapter, a)) = adapter
            .map(|p| train::Adapter::load(p).map(|a| (p, a)))
            .transpose()?
        else {
            let base = open_checkpoint(path, &config, device, dtype)?;
            return Self::from_var_builder(config, base).map_err(|e| match e {
                DepthError::Candle { source, .. } => weights_source(path)(source),
                other => other,
            });
        };
        let base = open_checkpoint(path, &config, device, dtype)?;
        let vb = train::merge_adapter(base, &config, &a, adapter)?;
        Self::from_var_builder(config, vb)
    }

    /// Builds the network from any [`VarBuilder`] whose root holds `pretrained.*` and
    /// `depth_head.*` (e.g. `VarBuilder::zeros` for shape tests, a `VarMap` for fine-tuning).
    ///
    /// # Errors
    /// Missing or mis-shaped variables ([`DepthError::Candle`]).
    pub fn from_var_builder(config: DepthAnythingConfig, vb: VarBuilder) -> Result<Self> {
        config.validate()?;
        let device = vb.device().clone();
        let dtype = vb.dtype();
        if device.is_cpu() {
            heap::keep_freed_memory();
        }
        let building = |source| DepthError::Candle {
            context: "building the network from its variables".into(),
            source,
        };
        let encoder = DinoV2::new(&config, vb.pp("pretrained")).map_err(building)?;
        let head = DptHead::new(&config, vb.pp("depth_head")).map_err(building)?;
        Ok(Self {
            config,
            encoder,
            head,
            device,
            dtype,
            packed: None,
        })
    }

    /// [`Self::load`] in `precision` on `device`: the candle dtype of [`precision_dtype`], and
    /// for int8 and bf16 on the CPU the f32 model then [`Self::pack_cpu`]. The one constructor
    /// of `moma_depth::load` and of the Python package.
    ///
    /// # Errors
    /// As [`precision_dtype`], [`Self::load`] and [`Self::pack_cpu`].
    pub fn load_with_precision(
        path: impl AsRef<Path>,
        config: DepthAnythingConfig,
        device: &Device,
        precision: Precision,
        adapter: Option<&Path>,
    ) -> Result<Self> {
        let dtype = precision_dtype(precision, device)?;
        let mut model = Self::load(path, config, device, dtype, adapter)?;
        if device.is_cpu() && matches!(precision, Precision::Int8 | Precision::Bf16) {
            model.pack_cpu(precision)?;
        }
        Ok(model)
    }

    /// Packs the encoder's linear layers (qkv, proj, MLP) and attention products for a CPU
    /// kernel in `precision` (`--dtype int8|bf16` on the CPU): int8 with per-output-channel
    /// weight scales and per-token activation scales at run time (AVX512-VNNI), or bf16 with
    /// `f32` sums (AVX512-BF16). On a CPU without those instructions a portable kernel gives
    /// the same results, slower, and this says so once on stderr. The packed layers' f32
    /// weights are freed; `f32` leaves an unpacked model as it is and refuses a packed one
    /// (load it again).
    ///
    /// # Errors
    /// [`DepthError::Unavailable`] unless the model is f32 on the CPU; f16.
    pub fn pack_cpu(&mut self, precision: Precision) -> Result<()> {
        use dinov2::PackedPrecision;
        if !(self.device.is_cpu() && self.dtype == DType::F32) {
            return Err(DepthError::Unavailable(format!(
                "int8 and bf16 CPU layers are made from f32 weights on the CPU (this model is {:?} on {:?})",
                self.dtype,
                self.device.location()
            )));
        }
        let packed = match precision {
            Precision::F32 => PackedPrecision::F32,
            Precision::Int8 => PackedPrecision::Int8,
            Precision::Bf16 => PackedPrecision::Bf16,
            Precision::F16 => {
                return Err(DepthError::Unavailable(
                    "f16 has no CPU kernel (use f32, bf16 or int8 on the CPU)".into(),
                ));
            }
        };
        let (fast, instructions) = cpu_instructions(precision);
        if !fast {
            static SAID: std::sync::Once = std::sync::Once::new();
            SAID.call_once(|| {
                eprintln!(
                    "note: this CPU has no {instructions}: --dtype {precision:?} runs a portable \
                     kernel (same results, slower than f32)"
                );
            });
        }
        self.encoder
            .pack(packed)
            .map_err(|source| DepthError::Candle {
                context: format!("packing the encoder's linear layers for {precision:?}"),
                source,
            })?;
        if precision != Precision::F32 {
            self.packed = Some(precision);
        }
        Ok(())
    }

    /// The precision of the encoder's packed CPU layers, `None` when unpacked.
    pub fn packed_precision(&self) -> Option<Precision> {
        self.packed
    }

    /// The architecture.
    pub fn config(&self) -> &DepthAnythingConfig {
        &self.config
    }

    /// The device the weights live on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The dtype the network computes in.
    pub fn dtype(&self) -> DType {
        self.dtype
    }

    /// The network on a tensor `(1, 3, H, W)` (H, W multiples of 14, ImageNet-normalised RGB) on
    /// [`Self::device`], any float dtype; returns `(1, H, W)` in [`Self::dtype`]: inverse depth
    /// (relative head) or metres (metric head).
    ///
    /// # Errors
    /// Shape errors.
    pub fn forward(&mut self, x: &Tensor) -> candle_core::Result<Tensor> {
        let x = &x.to_dtype(self.dtype)?;
        let (_, _, h, w) = x.dims4()?;
        let (rows, cols) = (h / PATCH_SIZE, w / PATCH_SIZE);
        let layers = self.config.intermediate_layers;
        let features = self.encoder.intermediate_layers(x, &layers)?;
        let out = self.head.forward(&features, rows, cols)?;
        out.squeeze(1)
    }
}

impl DepthModel for CandleDepthModel {
    fn spec(&self) -> ModelSpec {
        self.config.spec()
    }

    fn runtime(&self) -> String {
        let base = format!("candle, {:?}, {:?}", self.device.location(), self.dtype);
        let (name, precision) = match self.packed {
            Some(p @ Precision::Int8) => ("int8", p),
            Some(p @ Precision::Bf16) => ("bf16", p),
            _ => return base,
        };
        let (fast, instructions) = cpu_instructions(precision);
        let kernel = if fast {
            instructions
        } else {
            "portable kernel"
        };
        format!("{base}, encoder linear layers and attention in {name} ({kernel})")
    }

    fn forward_net(&mut self, input: &Array3<f32>) -> Result<Array2<f32>> {
        let (c, h, w) = input.dim();
        if c != 3 || h == 0 || w == 0 || h % PATCH_SIZE != 0 || w % PATCH_SIZE != 0 {
            return Err(DepthError::Shape(format!(
                "network input must be (3, H, W) with H, W positive multiples of {PATCH_SIZE}, got ({c}, {h}, {w})"
            )));
        }
        let data: Vec<f32> = input.iter().copied().collect();
        let x = Tensor::from_vec(data, (1, 3, h, w), &self.device).map_err(backend)?;
        let y = self.forward(&x).map_err(backend)?;
        let values: Vec<f32> = y
            .flatten_all()
            .and_then(|t| t.to_dtype(DType::F32))
            .and_then(|t| t.to_vec1())
            .map_err(backend)?;
        Array2::from_shape_vec((h, w), values).map_err(|e| DepthError::Shape(e.to_string()))
    }
}

/// A tiny architecture for unit tests (embed 32, 2 blocks, 8 DPT features).
#[cfg(test)]
pub(crate) fn tiny_test_config(head: Head) -> DepthAnythingConfig {
    DepthAnythingConfig {
        embed_dim: 32,
        depth: 2,
        num_heads: 2,
        mlp_hidden_dim: 64,
        intermediate_layers: [0, 1, 1, 1],
        features: 8,
        out_channels: [4, 8, 8, 16],
        ..DepthAnythingConfig::vit_small(head)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny(head: Head) -> DepthAnythingConfig {
        tiny_test_config(head)
    }

    #[test]
    fn zero_weights_give_the_right_shapes() {
        // Any (H, W) multiple of 14, non-square: 28×42 -> patch grid 2×3.
        for head in [Head::Relative, Head::Metric { max_depth_m: 20.0 }] {
            let vb = VarBuilder::zeros(DType::F32, &Device::Cpu);
            let mut m = CandleDepthModel::from_var_builder(tiny(head), vb).unwrap();
            let out = m.forward_net(&Array3::zeros((3, 28, 42))).unwrap();
            assert_eq!(out.dim(), (28, 42));
            // Zero weights: relative head ReLU(0) = 0, metric head sigmoid(0)·20 = 10.
            let want = if head == Head::Relative { 0.0 } else { 10.0 };
            assert!(out.iter().all(|&v| v == want));
        }
        let vb = VarBuilder::zeros(DType::F32, &Device::Cpu);
        let mut m = CandleDepthModel::from_var_builder(tiny(Head::Relative), vb).unwrap();
        assert!(matches!(
            m.forward_net(&Array3::zeros((3, 28, 40))),
            Err(DepthError::Shape(_))
        ));
    }

    #[test]
    fn presets_list_the_official_key_set() {
        let c = DepthAnythingConfig::vit_small(Head::Relative);
        let t = c.expected_tensors();
        // 4 + 12·14 + 2 (encoder) + 12 + 6 + 4·10 + 6 (head) + mask_token = the 239 tensors of an
        // official ViT-S checkpoint (and of `vits-rel.safetensors`).
        assert_eq!(t.len(), 239);
        let found: BTreeMap<String, Vec<usize>> = t
            .iter()
            .filter(|(_, _, req)| *req)
            .map(|(n, s, _)| (n.clone(), s.clone()))
            .collect();
        assert!(c.check_tensors(&found).is_ok());
        assert_eq!(DepthAnythingConfig::from_spec(&c.spec()), c);
        let bad = DepthAnythingConfig { num_heads: 5, ..c };
        assert!(bad.validate().is_err());
    }
}
