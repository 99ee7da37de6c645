//! `moma predict`: run Depth Anything V2 on RGB images and write the raw predictions.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use moma_io::Colormap;
use serde::Serialize;

use super::common::{ModelArgs, create_dir, frame_name, print_json, progress};

/// Run Depth Anything V2 on RGB images; write raw predictions (not metres — calibrate them).
///
/// Writes per image NAME (file stem, or frame id for moma-set paths):
///   NAME.npy        float32 H×W prediction at the image's size (kind in predictions.json)
///   NAME.color.png  colour-mapped prediction for people (2nd–98th percentile range)
/// and OUTDIR/predictions.json recording the model, head, prediction kind and inputs.
///
/// Examples:
///   moma predict --weights depth_anything_v2_vits.pth --model vits set/frames/*/rgb.png -o pred/
///   moma predict --weights depth_anything_v2_vits.onnx --backend onnx img.png -o pred/
///   moma predict --weights depth_anything_v2_metric_hypersim_vits.pth --head metric \
///       --max-depth 20 img.png -o pred/
///   moma predict --hub metric-hypersim-vits --device cuda --dtype f16 img.png -o pred/
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
pub struct PredictArgs {
    #[command(flatten)]
    pub model: ModelArgs,
    /// RGB images (PNG or JPEG).
    #[arg(required = true, value_name = "IMG")]
    pub images: Vec<PathBuf>,
    /// Output directory (created if missing).
    #[arg(short, long, visible_alias = "out", value_name = "DIR")]
    pub output: PathBuf,
    /// Print a JSON summary on stdout (and no progress bar).
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Serialize)]
struct PredictionsIndex<'a> {
    /// Always "moma-predictions".
    format: &'static str,
    /// [`moma_io::PREDICTIONS_VERSION`].
    version: u32,
    /// `metric-depth` (metric head) or `relative-disparity` (relative head).
    prediction_kind: moma_core::PredictionKind,
    /// Always false: a depth model's output (labels, as `moma simulate`'s index has them).
    simulated: bool,
    /// The predictions' label ([`super::common::LoadedModel::label`]).
    source: String,
    model: moma_depth::ModelSpec,
    weights: &'a std::path::Path,
    /// The LoRA adapter merged into the weights (`--lora`), absent without one: predictions of
    /// a fine-tuned model say so.
    #[serde(skip_serializing_if = "Option::is_none")]
    lora: Option<&'a std::path::Path>,
    /// Backend, device and precision (`DepthModel::runtime`).
    runtime: String,
    frames: Vec<FrameRecord>,
}

#[derive(Debug, Serialize)]
struct FrameRecord {
    name: String,
    input: PathBuf,
    output: PathBuf,
    /// Depth-model time (pre-processing, network, post-processing), milliseconds.
    predict_ms: f64,
}

pub fn run(args: &PredictArgs) -> Result<()> {
    super::common::check_unique_output_names(&args.images)?;
    let loaded = args.model.load()?;
    let label = loaded.label(args.model.lora.as_deref());
    let super::common::LoadedModel { mut model, weights } = loaded;
    let kind = model.spec().head.prediction_kind();
    create_dir(&args.output)?;
    // an index left by an earlier run would describe the files this one writes (perhaps of
    // another kind) if this run stopped before writing its own: no index until the end
    let index_path = args.output.join("predictions.json");
    super::common::remove_earlier(&index_path)?;
    let bar = progress(args.images.len(), "predicting", args.json);
    let mut frames = Vec::new();
    for path in &args.images {
        let rgb = moma_io::read_rgb(path)?;
        let t = Instant::now();
        let pred = model
            .predict(&rgb)
            .with_context(|| format!("depth model failed on {}", path.display()))?;
        let predict_ms = t.elapsed().as_secs_f64() * 1e3;
        let name = frame_name(path);
        let out = args.output.join(format!("{name}.npy"));
        moma_io::write_prediction(&out, &pred)?;
        let png = args.output.join(format!("{name}.color.png"));
        write_prediction_colormap(&png, &pred, Colormap::Turbo)?;
        frames.push(FrameRecord {
            name,
            input: path.clone(),
            output: out,
            predict_ms,
        });
        bar.inc(1);
    }
    bar.finish_and_clear();
    let index = PredictionsIndex {
        format: moma_io::PREDICTIONS_FORMAT,
        version: moma_io::PREDICTIONS_VERSION,
        prediction_kind: kind,
        simulated: false,
        source: label,
        model: model.spec(),
        weights: &weights,
        lora: args.model.lora.as_deref(),
        runtime: model.runtime(),
        frames,
    };
    write_json(&index_path, &index)?;
    if args.json {
        print_json(&index)?;
    } else {
        let mut t: Vec<f64> = index.frames.iter().map(|f| f.predict_ms).collect();
        t.sort_by(f64::total_cmp);
        println!(
            "wrote {} {} prediction(s) to {} (median {:.0} ms per image); calibrate them with `moma calibrate --pred-kind {}`",
            index.frames.len(),
            kind,
            args.output.display(),
            t[t.len() / 2],
            kind
        );
    }
    Ok(())
}

/// Colour-maps a raw prediction (unitless) over its 2nd–98th percentile for people.
fn write_prediction_colormap(
    path: &std::path::Path,
    pred: &moma_core::Prediction,
    colormap: Colormap,
) -> Result<()> {
    let mut finite: Vec<f32> = pred
        .values
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    if finite.is_empty() {
        bail!("prediction for {} holds no finite value", path.display());
    }
    finite.sort_unstable_by(f32::total_cmp);
    let at = |q: f32| finite[((finite.len() - 1) as f32 * q).round() as usize];
    let (lo, hi) = (at(0.02), at(0.98));
    let img = moma_io::colourise(
        pred.values.view(),
        colormap,
        lo,
        hi.max(lo + f32::EPSILON),
        f32::is_finite,
    );
    moma_io::write_rgb(path, &img)?;
    Ok(())
}

/// Writes `value` as pretty JSON, atomically.
fn write_json(path: &std::path::Path, value: &impl Serialize) -> Result<()> {
    let text = serde_json::to_string_pretty(value)?;
    moma_io::atomic_write(path, |w| {
        std::io::Write::write_all(w, text.as_bytes()).map_err(|source| moma_io::IoError::Io {
            path: path.to_path_buf(),
            action: "write",
            source,
        })
    })?;
    Ok(())
}
