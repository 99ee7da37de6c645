//! Plumbing shared by the subcommands: prediction sources (files or a depth model), progress
//! bars and JSON output.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicI32, Ordering};

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use moma_core::{Prediction, PredictionKind};
use moma_depth::{Backbone, DepthModel, DeviceRequest, Head, ModelSpec, Precision};

/// `--model` values: a released size, or a custom architecture from a JSON file.
#[derive(Debug, Clone, PartialEq)]
pub enum ModelArg {
    /// ViT-S (24.8 M parameters), ViT-B (97.5 M) or ViT-L (335.3 M).
    Preset(Backbone),
    /// A JSON configuration (`embed_dim`, `depth`, `num_heads`, `intermediate_layers`, `features`,
    /// `out_channels`, `head`, `max_depth`), e.g. the tiny test models.
    File(PathBuf),
}

impl std::str::FromStr for ModelArg {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        if has_extension(Path::new(s), "json") {
            return Ok(Self::File(PathBuf::from(s)));
        }
        s.parse::<Backbone>()
            .map(Self::Preset)
            .map_err(|e| format!("{e}, or a configuration PATH.json"))
    }
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
    /// bfloat16 (GPU; on the CPU the ViT encoder's products, the rest f32).
    Bf16,
    /// int8 linear layers in the ViT encoder, the rest f32 (CPU only, candle).
    Int8,
}

/// `--input-size`'s default: Depth Anything V2's own 518 px.
const DEFAULT_INPUT_SIZE_PX: usize = 518;

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
    /// Network: vits, vitb, vitl, or a custom configuration PATH.json (which fixes the head and
    /// max depth).
    #[arg(long, default_value = "vits", value_name = "vits|vitb|vitl|PATH.json")]
    pub model: ModelArg,
    /// Output head: relative (inverse depth) or metric (depth in metres) [default: relative].
    #[arg(long, value_enum)]
    pub head: Option<HeadArg>,
    /// Largest depth of the metric head, metres (20 indoor, 80 outdoor) [default: 20].
    #[arg(long, value_name = "METRES")]
    pub max_depth: Option<f32>,
    /// Network input lower bound, pixels (multiple of 14, at most 4200).
    #[arg(long, default_value_t = DEFAULT_INPUT_SIZE_PX, value_name = "PX")]
    pub input_size: usize,
    /// Inference backend.
    #[arg(long, value_enum, default_value_t = BackendArg::Auto)]
    pub backend: BackendArg,
    /// Device for the candle backend: auto (first GPU of this build, else CPU), cpu, cuda[:N],
    /// metal[:N].
    #[arg(long, default_value = "auto", value_name = "DEVICE")]
    pub device: DeviceRequest,
    /// Arithmetic precision of the candle backend (f16 is for GPUs, int8 for CPUs, bf16 for
    /// both).
    #[arg(long, value_enum, default_value_t = DtypeArg::F32)]
    pub dtype: DtypeArg,
    /// A LoRA adapter (`moma finetune` output) merged into the weights at load (candle backend;
    /// it must have been trained on these exact weights).
    #[arg(long, value_name = "ADAPTER")]
    pub lora: Option<PathBuf>,
}

impl ModelArgs {
    /// Refuses depth-model options given on the command line (those not at their defaults)
    /// where the inputs are `inputs` (e.g. "--pred files"), which no model reads: they would be
    /// ignored.
    ///
    /// # Errors
    /// Any such option, named.
    pub fn refuse_for(&self, inputs: &str) -> Result<()> {
        let given: Vec<&str> = [
            ("--weights", self.weights.is_some()),
            ("--hub", self.hub.is_some()),
            ("--model", self.model != ModelArg::Preset(Backbone::Vits)),
            ("--head", self.head.is_some()),
            ("--max-depth", self.max_depth.is_some()),
            ("--input-size", self.input_size != DEFAULT_INPUT_SIZE_PX),
            ("--backend", self.backend != BackendArg::Auto),
            ("--device", self.device != DeviceRequest::Auto),
            ("--dtype", self.dtype != DtypeArg::F32),
            ("--lora", self.lora.is_some()),
        ]
        .into_iter()
        .filter_map(|(flag, given)| given.then_some(flag))
        .collect();
        if !given.is_empty() {
            bail!(
                "{}: depth-model options, which apply only where a depth model runs (--rgb \
                 images, or --weights/--hub for a set; with {inputs} they would be ignored)",
                given.join(", ")
            );
        }
        Ok(())
    }
}

/// A loaded depth model and the weights file it came from.
pub struct LoadedModel {
    /// The model.
    pub model: Box<dyn DepthModel>,
    /// The weights file (after resolving `--hub`).
    pub weights: PathBuf,
}

impl LoadedModel {
    /// How tables, result files and prediction indexes name this model's predictions:
    /// `Depth Anything V2 ViT-S (relative head), weights FILE[, LoRA FILE]`.
    pub fn label(&self, lora: Option<&Path>) -> String {
        let spec = self.model.spec();
        let backbone = match spec.backbone {
            Backbone::Vits => "ViT-S",
            Backbone::Vitb => "ViT-B",
            Backbone::Vitl => "ViT-L",
            Backbone::Custom(_) => "(custom backbone)",
        };
        let head = match spec.head {
            moma_depth::Head::Relative => "relative head".to_string(),
            moma_depth::Head::Metric { max_depth_m } => {
                format!("metric head, max {max_depth_m} m")
            }
        };
        let lora = lora
            .map(|l| format!(", LoRA {}", l.display()))
            .unwrap_or_default();
        format!(
            "Depth Anything V2 {backbone} ({head}), weights {}{lora}",
            self.weights.display()
        )
    }
}

impl ModelArgs {
    /// The network these arguments describe. A JSON `--model` fixes the head and max depth:
    /// `--head`/`--max-depth` that disagree with it are an error.
    ///
    /// # Errors
    /// Bad `--input-size` or `--max-depth`, an unreadable configuration file, a disagreeing head.
    pub fn spec(&self) -> Result<ModelSpec> {
        moma_depth::preprocess::check_input_size(self.input_size)
            .map_err(|e| anyhow::anyhow!("--input-size: {e}"))?;
        if let Some(m) = self.max_depth
            && !(m.is_finite() && m > 0.0)
        {
            bail!("--max-depth {m} must be a positive number of metres");
        }
        match &self.model {
            ModelArg::Preset(backbone) => Ok(ModelSpec {
                backbone: *backbone,
                head: match self.head.unwrap_or(HeadArg::Relative) {
                    HeadArg::Relative => Head::Relative,
                    HeadArg::Metric => Head::Metric {
                        max_depth_m: self.max_depth.unwrap_or(20.0),
                    },
                },
                input_size: self.input_size,
            }),
            ModelArg::File(path) => {
                let file = moma_depth::ModelConfigFile::read(path)?;
                let spec = file.spec(self.input_size);
                let (file_head, file_max) = match spec.head {
                    Head::Relative => (HeadArg::Relative, None),
                    Head::Metric { max_depth_m } => (HeadArg::Metric, Some(max_depth_m)),
                };
                if let Some(h) = self.head
                    && h != file_head
                {
                    bail!(
                        "--head {} disagrees with the {} head of --model {}",
                        head_name(h),
                        head_name(file_head),
                        path.display()
                    );
                }
                if let Some(m) = self.max_depth
                    && Some(m) != file_max
                {
                    bail!(
                        "--max-depth {m} disagrees with --model {} ({})",
                        path.display(),
                        file_max.map_or("relative head, no max depth".to_string(), |f| format!(
                            "max_depth {f}"
                        ))
                    );
                }
                Ok(spec)
            }
        }
    }

    /// The weights file (`--weights`, or `--hub`'s checkpoint from the Hugging Face cache,
    /// downloaded if absent) and the network it holds.
    ///
    /// # Errors
    /// Neither `--weights` nor `--hub`, an unknown checkpoint, a failed download, a bad
    /// `--model`/`--head`/`--max-depth`/`--input-size`.
    pub fn weights_and_spec(&self) -> Result<(PathBuf, ModelSpec)> {
        Ok(match (&self.weights, &self.hub) {
            (Some(w), _) => (w.clone(), self.spec()?),
            (None, Some(name)) => {
                self.spec()?;
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
        })
    }

    /// Loads the model (`--weights` or `--hub` required).
    ///
    /// # Errors
    /// Missing `--weights`, unreadable weights, a backend or device this build lacks.
    pub fn load(&self) -> Result<LoadedModel> {
        let (weights, spec) = self.weights_and_spec()?;
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
                DtypeArg::Int8 => Precision::Int8,
            },
        };
        let model = moma_depth::load(&moma_depth::LoadSpec {
            weights: weights.clone(),
            model: spec,
            options,
            adapter: self.lora.clone(),
        })
        // Weight-file errors name the file themselves.
        .context("loading the depth model")?;
        Ok(LoadedModel { model, weights })
    }
}

fn head_name(h: HeadArg) -> &'static str {
    match h {
        HeadArg::Relative => "relative",
        HeadArg::Metric => "metric",
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
    /// What the prediction files hold: metric-depth | relative-depth | relative-disparity
    /// (relative Depth Anything heads output relative-disparity, metric heads metric-depth;
    /// docs/formats.md "Prediction kinds"). Never guessed: taken from predictions.json beside
    /// the files (written by `moma predict` / `moma simulate`) or the model's head with --rgb,
    /// which must agree, else the calibration file's; the calibration must accept it.
    #[arg(long, value_name = "KIND")]
    pub pred_kind: Option<PredictionKind>,
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
    /// Some input is SIMULATED (its `predictions.json` says so).
    pub simulated: bool,
}

impl SourceArgs {
    /// The input files: the RGB images with --rgb, else the prediction files.
    pub fn inputs(&self) -> &[PathBuf] {
        if self.rgb.is_empty() {
            &self.pred
        } else {
            &self.rgb
        }
    }

    /// Opens the source (loads the model once when `--rgb` is used). The prediction kind comes
    /// from `--pred-kind`, the `predictions.json` beside each prediction file, the model's head
    /// (`--rgb`) and `calibration_kind` (the calibration file's, in `align`); at least one must
    /// state it and all that do must agree.
    ///
    /// # Errors
    /// Unknown or contradicting kind, an unreadable index, model loading errors.
    pub fn open(&self, calibration_kind: Option<PredictionKind>) -> Result<Source> {
        if self.rgb.is_empty() {
            self.model
                .refuse_for("--pred files (their kind is --pred-kind)")?;
            let mut indexes = Vec::new();
            for file in &self.pred {
                let index = moma_io::read_prediction_index_for(file)?;
                // a map its folder's index does not list was not written by the run the index
                // describes: the index's kind says nothing about it (`moma eval` refuses it).
                // Given --pred-kind, the user vouches for the kind (copies beside a copied
                // index, as benches and tests make them); else it is refused.
                if let Some(i) = index.as_ref().filter(|i| i.disowns(file)) {
                    let why = format!(
                        "{} is not listed in {} ({} frames)",
                        file.display(),
                        i.path.display(),
                        i.frames.len()
                    );
                    match self.pred_kind {
                        Some(k) => eprintln!("note: {why}: read as --pred-kind {k} says"),
                        None => bail!(
                            "{why}: its kind is not known (a file left by another run?); give \
                             --pred-kind if you know what it holds"
                        ),
                    }
                }
                if let Some(index) = index
                    && !indexes
                        .iter()
                        .any(|i: &moma_io::PredictionIndex| i.path == index.path)
                {
                    indexes.push(index);
                }
            }
            let names: Vec<String> = indexes
                .iter()
                .map(|i| i.path.display().to_string())
                .collect();
            let mut sources: Vec<(&str, Option<PredictionKind>)> =
                vec![("--pred-kind", self.pred_kind)];
            sources.extend(
                names
                    .iter()
                    .zip(&indexes)
                    .map(|(n, i)| (n.as_str(), Some(i.kind))),
            );
            let kind = moma_io::resolve_prediction_kind(
                &sources,
                calibration_kind.map(|k| ("the calibration file", k)),
            )
            .map_err(anyhow::Error::msg)?;
            if let Some(sim) = indexes.iter().find(|i| i.simulated) {
                eprintln!(
                    "note: SIMULATED predictions ({}): not a depth model's output",
                    sim.path.display()
                );
            }
            Ok(Source {
                inputs: self.inputs().to_vec(),
                kind,
                model: None,
                simulated: indexes.iter().any(|i| i.simulated),
            })
        } else {
            let model = self.model.load()?.model;
            let kind = moma_io::resolve_prediction_kind(
                &[
                    (
                        "the depth model's head",
                        Some(model.spec().head.prediction_kind()),
                    ),
                    ("--pred-kind", self.pred_kind),
                ],
                calibration_kind.map(|k| ("the calibration file", k)),
            )
            .map_err(anyhow::Error::msg)?;
            Ok(Source {
                inputs: self.inputs().to_vec(),
                kind,
                model: Some(model),
                simulated: false,
            })
        }
    }
}

impl Source {
    /// Number of inputs.
    pub fn len(&self) -> usize {
        self.inputs.len()
    }

    /// The reader of the prediction files (`None` when the source runs a depth model: use
    /// [`Source::get`]); it reads any input from any thread.
    pub fn files(&self) -> Option<FileReader<'_>> {
        self.model.is_none().then_some(FileReader {
            inputs: &self.inputs,
            kind: self.kind,
        })
    }

    /// Reads (or predicts) input `i`.
    ///
    /// # Errors
    /// Unreadable file, model failure; the message names the file.
    pub fn get(&mut self, i: usize) -> Result<SourcedPrediction> {
        let path = self.inputs[i].clone();
        let Some(model) = self.model.as_mut() else {
            return FileReader {
                inputs: &self.inputs,
                kind: self.kind,
            }
            .read(i);
        };
        let rgb = moma_io::read_rgb(&path)?;
        let prediction = model
            .predict(&rgb)
            .with_context(|| format!("depth model failed on {}", path.display()))?;
        Ok(SourcedPrediction {
            name: frame_name(&path),
            path,
            prediction,
            rgb: Some(rgb),
        })
    }
}

/// Prediction files of a [`Source`], readable from any thread.
#[derive(Clone, Copy)]
pub struct FileReader<'a> {
    inputs: &'a [PathBuf],
    kind: PredictionKind,
}

impl FileReader<'_> {
    /// Reads prediction file `i`.
    ///
    /// # Errors
    /// Unreadable file; the message names it.
    pub fn read(&self, i: usize) -> Result<SourcedPrediction> {
        let path = self.inputs[i].clone();
        let prediction = moma_io::read_prediction(&path, self.kind)?;
        Ok(SourcedPrediction {
            name: frame_name(&path),
            path,
            prediction,
            rgb: None,
        })
    }
}

/// Reads a metric depth map for `flag`, refusing a relative model's raw output: a `.npy` that
/// the `predictions.json` beside it lists as a `relative-disparity` or `relative-depth`
/// prediction holds values with an unknown scale (and shift), not metres (`hint` says what to do
/// instead). A raw `metric-depth` prediction (a metric head's output, nominally metres) is read
/// with a note: uncalibrated.
pub fn read_metric_depth(path: &Path, flag: &str, hint: &str) -> Result<moma_core::MetricDepth> {
    if let Some(index) = moma_io::prediction_index_listing(path)? {
        let simulated = if index.simulated { "SIMULATED " } else { "" };
        if !index.kind.is_metric() {
            bail!(
                "{flag} {}: this is a raw {simulated}{} prediction listed in {}: no unit, not \
                 metres; {hint}",
                path.display(),
                index.kind,
                index.path.display()
            );
        }
        eprintln!(
            "note: {flag} {}: a raw {simulated}metric-depth prediction listed in {}, used as metres \
             without calibration (its scale is the model's own)",
            path.display(),
            index.path.display()
        );
    }
    Ok(moma_io::read_depth(path)?)
}

/// What the folder of a metric depth file says of where it came from.
pub enum DepthOrigin {
    /// SIMULATED, as the file at this path says: the `predictions.json` that lists a raw
    /// prediction as simulated, the folder's `aligned.json` for a depth that `moma align`,
    /// `grasp -o` or `demo` wrote from simulated predictions, or (`moma grasp --calib`) the
    /// calibration fitted on them.
    Simulated(PathBuf),
    /// Nothing says it is simulated.
    NotSimulated,
    /// Another tool's `aligned.json` stands beside it: nothing can be said (a note was printed).
    Unknown,
}

/// Where a metric depth file came from, as far as its folder says ([`DepthOrigin`]).
pub fn depth_origin(path: &Path) -> Result<DepthOrigin> {
    if let Some(i) = moma_io::prediction_index_listing(path)? {
        return Ok(if i.simulated {
            DepthOrigin::Simulated(i.path)
        } else {
            DepthOrigin::NotSimulated
        });
    }
    Ok(match moma_io::provenance_of(path)? {
        moma_io::Provenance::Listed { index, entry } if entry.simulated => {
            DepthOrigin::Simulated(index)
        }
        moma_io::Provenance::Listed { .. } | moma_io::Provenance::Unlisted => {
            DepthOrigin::NotSimulated
        }
        moma_io::Provenance::ForeignIndex(index) => {
            eprintln!(
                "note: {} is not moma's aligned-depth index: where {} came from is not known",
                index.display(),
                path.display()
            );
            DepthOrigin::Unknown
        }
    })
}

/// Fails when every set was skipped (`rows` is empty and `notes` say why): a table or a `--json`
/// array with no row would read as a run that measured nothing wrong.
pub fn check_some_rows<T>(rows: &[T], notes: &[moma_eval::protocol::EvalNote]) -> Result<()> {
    if rows.is_empty() && !notes.is_empty() {
        let why = notes
            .iter()
            .map(|n| format!("set '{}' ({}): {}", n.set, n.variant, n.note))
            .collect::<Vec<_>>()
            .join("; ");
        bail!("no set could be evaluated: {why}");
    }
    Ok(())
}

/// Refuses a list flag that names one value twice (it would give duplicate rows), as
/// `--calib-frames 1,1` is refused.
pub fn check_no_repeats<T: PartialEq + std::fmt::Display>(flag: &str, values: &[T]) -> Result<()> {
    for (i, v) in values.iter().enumerate() {
        if values[..i].contains(v) {
            bail!("{flag} names {v} twice");
        }
    }
    Ok(())
}

/// Refuses `--set` folders of the same name (a set is named by its folder): their rows could
/// not be told apart, and their per-set output and prediction folders would be one.
pub fn check_unique_set_names(sets: &[PathBuf]) -> Result<()> {
    let mut seen = std::collections::HashMap::new();
    for dir in sets {
        let name = moma_io::loaded_set_name(dir);
        if let Some(first) = seen.insert(name.clone(), dir) {
            bail!(
                "--set {} and --set {} are both named '{name}' (a set is named by its folder): \
                 their rows, outputs and prediction folders would be one; give each set a folder \
                 of its own name",
                first.display(),
                dir.display()
            );
        }
    }
    Ok(())
}

/// Refuses inputs whose outputs would overwrite each other: two paths with the same
/// [`frame_name`] (the second's files would silently replace the first's).
pub fn check_unique_output_names(inputs: &[PathBuf]) -> Result<()> {
    let mut seen = std::collections::HashMap::new();
    for p in inputs {
        if let Some(first) = seen.insert(frame_name(p), p) {
            bail!(
                "two inputs map to the same output name '{}' ({} and {}): rename one",
                frame_name(p),
                first.display(),
                p.display()
            );
        }
    }
    Ok(())
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
    if dir.exists() && !dir.is_dir() {
        bail!(
            "cannot write into {}: it is a file, not a directory (the output is a folder)",
            dir.display()
        );
    }
    std::fs::create_dir_all(dir)
        .with_context(|| format!("cannot create output directory {}", dir.display()))
}

/// An output folder a run created: removed again, if still empty, when the run fails (dropped
/// without [`OutputDir::keep`]), so that a run stopped by bad input leaves no empty folder
/// behind; one that existed before is left as it was.
#[must_use = "call keep() once the run has succeeded"]
pub struct OutputDir {
    path: PathBuf,
    created: bool,
}

impl OutputDir {
    /// The run succeeded: the folder stays.
    pub fn keep(mut self) {
        self.created = false;
    }
}

impl Drop for OutputDir {
    fn drop(&mut self) {
        if self.created {
            // removes an empty folder only: anything written stays
            let _ = std::fs::remove_dir(&self.path);
        }
    }
}

/// [`create_dir`], returning the guard that removes the folder again if the run fails before
/// writing into it.
///
/// # Errors
/// As [`create_dir`].
pub fn create_output_dir(dir: &Path) -> Result<OutputDir> {
    let created = !dir.exists();
    create_dir(dir)?;
    Ok(OutputDir {
        path: dir.to_path_buf(),
        created,
    })
}

/// Removes a result an earlier run left at `path` (none there is fine), before a run writes
/// the files that result would otherwise seem to describe: an index of predictions, a
/// `grasps.json` beside new outputs.
///
/// # Errors
/// The file exists and cannot be removed.
pub fn remove_earlier(path: &Path) -> Result<()> {
    // nothing there: nothing to remove (a read-only file system answers a removal of a file
    // that is not there with its own error, not "not found")
    if path.symlink_metadata().is_err() {
        return Ok(());
    }
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            Err(e).with_context(|| format!("removing the earlier {}", path.display()))
        }
        _ => Ok(()),
    }
}

/// Paths joined by ", " for messages.
pub fn join_paths(paths: &[PathBuf]) -> String {
    paths
        .iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(", ")
}

/// The grey that re-alignment compares ([`moma_io::grey_half`]) of a decoded RGB image.
///
/// # Errors
/// As [`rgb_view`].
pub fn grey_of(img: &image::RgbImage) -> Result<moma_core::realign::GreyHalf> {
    Ok(moma_io::grey_half(rgb_view(img)?)?)
}

/// An RGB image as an `(height, width, 3)` view.
///
/// # Errors
/// Never for an `RgbImage` in practice; a shape error is reported rather than unwrapped.
pub fn rgb_view(img: &image::RgbImage) -> Result<ndarray::ArrayView3<'_, u8>> {
    ndarray::ArrayView3::from_shape(
        (img.height() as usize, img.width() as usize, 3),
        img.as_raw().as_slice(),
    )
    .context("RGB image buffer")
}

/// The signal that asked a long-running loop (the ROS 2 node, the replay) to stop; 0: none.
static STOP_SIGNAL: AtomicI32 = AtomicI32::new(0);

/// Asks the running loop to stop (the first SIGINT, SIGTERM or SIGHUP of the ROS 2 node or
/// replay), saying so on stderr.
pub fn request_stop(signal: i32) {
    STOP_SIGNAL.store(signal, Ordering::SeqCst);
    eprintln!("moma: signal {signal} received: stopping (a second one ends the program at once)");
}

/// The signal that asked the loop to stop, if one did.
pub fn stop_requested() -> Option<i32> {
    match STOP_SIGNAL.load(Ordering::SeqCst) {
        0 => None,
        signal => Some(signal),
    }
}

/// Sleeps until `until` in naps of at most 20 ms, so that a stop ([`stop_requested`]) is seen
/// at once; `false` when one was asked for (before `until`, or already).
pub fn sleep_until_or_stop(until: std::time::Instant) -> bool {
    loop {
        if stop_requested().is_some() {
            return false;
        }
        let now = std::time::Instant::now();
        if until <= now {
            return true;
        }
        std::thread::sleep((until - now).min(std::time::Duration::from_millis(20)));
    }
}
