//! Plumbing shared by the subcommands: prediction sources (files or a depth model), progress
//! bars and JSON output.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use moma_core::{Prediction, PredictionKind};
use moma_depth::{Backbone, DepthModel, DeviceRequest, Head, ModelSpec, Precision};

/// `--pred-kind` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum KindArg {
    /// Larger = farther (metric models, simulated `depth`).
    Depth,
    /// Larger = nearer (Depth Anything relative models: disparity).
    InverseDepth,
}

impl From<KindArg> for PredictionKind {
    fn from(k: KindArg) -> Self {
        match k {
            KindArg::Depth => PredictionKind::Depth,
            KindArg::InverseDepth => PredictionKind::InverseDepth,
        }
    }
}

/// `--model` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum BackboneArg {
    /// ViT-S (24.8 M parameters).
    Vits,
    /// ViT-B (97.5 M parameters).
    Vitb,
    /// ViT-L (335.3 M parameters).
    Vitl,
}

/// `--head` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum HeadArg {
    /// Relative depth head (outputs inverse depth).
    Relative,
    /// Metric depth head (outputs depth in metres, up to --max-depth).
    Metric,
}

/// `--backend` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum BackendArg {
    /// Pick from the weights' extension: .onnx → onnx, else candle.
    Auto,
    /// Pure-Rust candle backend (.safetensors weights).
    Candle,
    /// ONNX Runtime backend (.onnx models; needs the runtime library, see README).
    Onnx,
}

/// `--dtype` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum DtypeArg {
    /// 32-bit floats (reference precision).
    F32,
    /// Half precision (GPU).
    F16,
    /// bfloat16 (GPU only).
    Bf16,
}

/// Which Depth Anything V2 network to run, and from which weights.
#[derive(Debug, Clone, Args)]
pub struct ModelArgs {
    /// Weights: an official Depth Anything V2 checkpoint (.pth or .safetensors; candle) or an
    /// .onnx export (ONNX Runtime).
    #[arg(long, value_name = "FILE")]
    pub weights: Option<PathBuf>,
    /// A public checkpoint by name instead of --weights (sets --model/--head/--max-depth): vits,
    /// vitb, vitl, metric-hypersim-{vits,vitb,vitl}, metric-vkitti-{vits,vitb,vitl}. Found in the
    /// Hugging Face cache, else downloaded (builds with `--features hub`). ViT-B/L weights are
    /// CC-BY-NC-4.0.
    #[arg(long, value_name = "NAME", conflicts_with_all = ["weights", "model", "head", "max_depth"])]
    pub hub: Option<String>,
    /// Backbone size.
    #[arg(long, value_enum, default_value_t = BackboneArg::Vits)]
    pub model: BackboneArg,
    /// Output head: relative (inverse depth) or metric (depth in metres).
    #[arg(long, value_enum, default_value_t = HeadArg::Relative)]
    pub head: HeadArg,
    /// Largest depth of the metric head, metres (20 indoor, 80 outdoor).
    #[arg(long, default_value_t = 20.0, value_name = "METRES")]
    pub max_depth: f32,
    /// Network input lower bound, pixels (multiple of 14).
    #[arg(long, default_value_t = 518, value_name = "PX")]
    pub input_size: usize,
    /// Inference backend.
    #[arg(long, value_enum, default_value_t = BackendArg::Auto)]
    pub backend: BackendArg,
    /// Device for the candle backend: auto (first GPU of this build, else CPU), cpu, cuda[:N],
    /// metal[:N].
    #[arg(long, default_value = "auto", value_name = "DEVICE")]
    pub device: DeviceRequest,
    /// Arithmetic precision of the candle backend (f16/bf16 are for GPUs).
    #[arg(long, value_enum, default_value_t = DtypeArg::F32)]
    pub dtype: DtypeArg,
}

/// A loaded depth model and the weights file it came from.
pub struct LoadedModel {
    /// The model.
    pub model: Box<dyn DepthModel>,
    /// The weights file (after resolving `--hub`).
    pub weights: PathBuf,
}

impl ModelArgs {
    /// The network these arguments describe.
    pub fn spec(&self) -> ModelSpec {
        ModelSpec {
            backbone: match self.model {
                BackboneArg::Vits => Backbone::Vits,
                BackboneArg::Vitb => Backbone::Vitb,
                BackboneArg::Vitl => Backbone::Vitl,
            },
            head: match self.head {
                HeadArg::Relative => Head::Relative,
                HeadArg::Metric => Head::Metric {
                    max_depth_m: self.max_depth,
                },
            },
            input_size: self.input_size,
        }
    }

    /// Loads the model (`--weights` or `--hub` required).
    ///
    /// # Errors
    /// Missing `--weights`, unreadable weights, a backend or device this build lacks.
    pub fn load(&self) -> Result<LoadedModel> {
        if self.input_size == 0 || !self.input_size.is_multiple_of(14) {
            bail!(
                "--input-size {} must be a positive multiple of 14",
                self.input_size
            );
        }
        if !(self.max_depth.is_finite() && self.max_depth > 0.0) {
            bail!(
                "--max-depth {} must be a positive number of metres",
                self.max_depth
            );
        }
        let (weights, spec) = match (&self.weights, &self.hub) {
            (Some(w), _) => (w.clone(), self.spec()),
            (None, Some(name)) => {
                let checkpoint = moma_depth::hub::find(name)?;
                let path = moma_depth::hub::fetch(checkpoint)
                    .with_context(|| format!("getting checkpoint {}", checkpoint.name))?;
                let spec = ModelSpec {
                    input_size: self.input_size,
                    ..checkpoint.spec()
                };
                (path, spec)
            }
            (None, None) => bail!(
                "a depth model needs --weights FILE (.pth, .safetensors or .onnx) or --hub NAME"
            ),
        };
        let options = moma_depth::LoadOptions {
            backend: match self.backend {
                BackendArg::Auto if has_extension(&weights, "onnx") => moma_depth::Backend::Onnx,
                BackendArg::Auto | BackendArg::Candle => moma_depth::Backend::Candle,
                BackendArg::Onnx => moma_depth::Backend::Onnx,
            },
            device: self.device,
            precision: match self.dtype {
                DtypeArg::F32 => Precision::F32,
                DtypeArg::F16 => Precision::F16,
                DtypeArg::Bf16 => Precision::Bf16,
            },
        };
        let model = moma_depth::load_model_with(&weights, spec, &options)
            // Weight-file errors name the file themselves.
            .context("loading the depth model")?;
        Ok(LoadedModel { model, weights })
    }
}

/// Case-insensitive extension check.
pub fn has_extension(path: &Path, ext: &str) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case(ext))
}

/// Where predictions come from: files, or RGB images through a depth model.
#[derive(Debug, Clone, Args)]
pub struct SourceArgs {
    /// Prediction files (.npy float32, .pfm, or 16-bit .png holding raw values).
    #[arg(long, num_args = 1.., value_name = "FILE", required_unless_present = "rgb", conflicts_with = "rgb")]
    pub pred: Vec<PathBuf>,
    /// What the prediction files hold (a depth model's head decides it for --rgb).
    #[arg(long, value_enum, default_value_t = KindArg::Depth)]
    pub pred_kind: KindArg,
    /// RGB images to run through the depth model (--weights or --hub) instead of --pred files.
    #[arg(long, num_args = 1.., value_name = "IMG")]
    pub rgb: Vec<PathBuf>,
    #[command(flatten)]
    pub model: ModelArgs,
}

/// One prediction with where it came from.
pub struct SourcedPrediction {
    /// Output name for this frame: the input's file stem.
    pub name: String,
    /// The input file (prediction or RGB image).
    pub path: PathBuf,
    /// The prediction.
    pub prediction: Prediction,
    /// The RGB image, when the source was an RGB image.
    pub rgb: Option<image::RgbImage>,
}

/// An opened prediction source; [`Source::get`] produces the i-th prediction.
pub struct Source {
    inputs: Vec<PathBuf>,
    kind: PredictionKind,
    model: Option<Box<dyn DepthModel>>,
}

impl SourceArgs {
    /// Opens the source (loads the model once when `--rgb` is used).
    ///
    /// # Errors
    /// Model loading errors.
    pub fn open(&self) -> Result<Source> {
        if self.rgb.is_empty() {
            Ok(Source {
                inputs: self.pred.clone(),
                kind: self.pred_kind.into(),
                model: None,
            })
        } else {
            let model = self.model.load()?.model;
            Ok(Source {
                inputs: self.rgb.clone(),
                kind: model.spec().head.prediction_kind(),
                model: Some(model),
            })
        }
    }
}

impl Source {
    /// Number of inputs.
    pub fn len(&self) -> usize {
        self.inputs.len()
    }

    /// Kind of the predictions this source produces.
    pub fn kind(&self) -> PredictionKind {
        self.kind
    }

    /// Reads (or predicts) input `i`.
    ///
    /// # Errors
    /// Unreadable file, model failure; the message names the file.
    pub fn get(&mut self, i: usize) -> Result<SourcedPrediction> {
        let path = self.inputs[i].clone();
        let name = frame_name(&path);
        match &mut self.model {
            None => {
                let prediction = moma_io::read_prediction(&path, self.kind)?;
                Ok(SourcedPrediction {
                    name,
                    path,
                    prediction,
                    rgb: None,
                })
            }
            Some(model) => {
                let rgb = moma_io::read_rgb(&path)?;
                let prediction = model
                    .predict(&rgb)
                    .with_context(|| format!("depth model failed on {}", path.display()))?;
                Ok(SourcedPrediction {
                    name,
                    path,
                    prediction,
                    rgb: Some(rgb),
                })
            }
        }
    }
}

/// The output name of an input file: its stem, or for a moma-set frame (`frames/ID/rgb.png`) the frame id.
pub fn frame_name(path: &Path) -> String {
    let stem = path
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("frame")
        .to_string();
    if matches!(stem.as_str(), "rgb" | "depth" | "pred" | "prediction")
        && let Some(parent) = path
            .parent()
            .and_then(|p| p.file_name())
            .and_then(|s| s.to_str())
    {
        return parent.to_string();
    }
    stem
}

/// A progress bar on stderr; hidden when `hidden` (e.g. `--json`) or for a single item.
pub fn progress(len: usize, message: &'static str, hidden: bool) -> ProgressBar {
    if hidden || len <= 1 {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(len as u64);
    if let Ok(style) =
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} {elapsed_precise} eta {eta}")
    {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_message(message);
    bar
}

/// Prints `value` as pretty JSON on stdout.
///
/// # Errors
/// Serialisation failure.
pub fn print_json(value: &impl serde::Serialize) -> Result<()> {
    println!("{}", serde_json::to_string_pretty(value)?);
    Ok(())
}

/// Creates `dir` (and parents) with a clear error.
///
/// # Errors
/// The directory cannot be created.
pub fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir)
        .with_context(|| format!("cannot create output directory {}", dir.display()))
}

/// Paths joined by ", " for messages.
pub fn join_paths(paths: &[PathBuf]) -> String {
    paths
        .iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(", ")
}
