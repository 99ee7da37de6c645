//! `moma calibrate`: fit an alignment on one RGB-D frame and write a calibration file.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use moma_core::align::{Method, lwlr, ssra};
use moma_core::normalise::{Normalisation, NormalisationConfig};
use moma_core::pipeline::{CalibrationConfig, calibrate};
use moma_core::sampling::{SamplingConfig, SamplingStrategy};
use moma_io::{CalibrationFile, CreationInfo};

use super::common::{SourceArgs, print_json};

/// `--method` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum MethodArg {
    /// Scale-shift-rotation (the paper's method; closed-form linear fit).
    Ssra,
    /// Global scale and shift.
    Gssa,
    /// Locally weighted linear regression, BoostingDepth's implementation (32-px grid + bilinear).
    Lwlr,
    /// Locally weighted linear regression, exact per-pixel solve.
    LwlrExact,
    /// No alignment: the prediction is used as metres (metric models only).
    Raw,
}

/// `--norm` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum NormArg {
    /// Paper's formula (z − min)/(max − min) + min.
    Minmax,
    /// Authors' code: (z − min)/(max − min).
    MinmaxUnit,
    /// (z − median)/mean|z − median|.
    Median,
    /// No normalisation.
    None,
}

impl From<NormArg> for Normalisation {
    fn from(n: NormArg) -> Self {
        match n {
            NormArg::Minmax => Normalisation::Minmax,
            NormArg::MinmaxUnit => Normalisation::MinmaxUnit,
            NormArg::Median => Normalisation::Median,
            NormArg::None => Normalisation::None,
        }
    }
}

/// `--sampling` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SamplingArg {
    /// Uniform over valid ground-truth pixels (MOMA's protocol), seeded.
    Random,
    /// √n × √n grid nodes snapped to the nearest valid pixel (BoostingDepth's).
    Grid,
}

/// Fit an alignment from one frame's prediction and ground truth.
///
/// Examples:
///   moma calibrate --pred pred/0000.npy --pred-kind inverse-depth --gt set/frames/0000/depth.png \
///       --camera set/camera.json -o calib.json
///   moma calibrate --rgb set/frames/0000/rgb.png --weights depth_anything_v2_vits.safetensors \
///       --gt set/frames/0000/depth.png --camera set/camera.json --method ssra --samples 100 --seed 7 -o calib.json
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
pub struct CalibrateArgs {
    #[command(flatten)]
    pub source: SourceArgs,
    /// Ground-truth depth of the same frame: uint16 PNG (mm, 0 = none), .npy (m) or .pfm (m).
    #[arg(long, value_name = "FILE")]
    pub gt: PathBuf,
    /// camera.json intrinsics (pixels); used for SSRA's canonical parameters and point clouds.
    #[arg(long, value_name = "FILE")]
    pub camera: Option<PathBuf>,
    /// Draw calibration samples only inside this mask (8-bit PNG, nonzero = inside).
    #[arg(long, value_name = "PNG")]
    pub mask: Option<PathBuf>,
    /// Normalise over this workspace mask instead of the whole map (same mask at run time).
    #[arg(long, value_name = "PNG")]
    pub workspace: Option<PathBuf>,
    /// Alignment method.
    #[arg(long, value_enum, default_value_t = MethodArg::Ssra)]
    pub method: MethodArg,
    /// Normalisation of the prediction.
    #[arg(long, value_enum, default_value_t = NormArg::Minmax)]
    pub norm: NormArg,
    /// For inverse-depth predictions: align in inverse space instead of converting to 1/d.
    #[arg(long)]
    pub inverse_space: bool,
    /// Number of calibration samples n.
    #[arg(long, default_value_t = 100)]
    pub samples: usize,
    /// How samples are chosen.
    #[arg(long, value_enum, default_value_t = SamplingArg::Random)]
    pub sampling: SamplingArg,
    /// Seed of the random sampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// LWLR bandwidth in pixels (default: 50 px at 640 px width, scaled with the image width).
    #[arg(long, value_name = "PX")]
    pub bandwidth_px: Option<f64>,
    /// Output calibration file (JSON).
    #[arg(short, long, value_name = "FILE")]
    pub output: PathBuf,
    /// Print the calibration summary as JSON on stdout.
    #[arg(long)]
    pub json: bool,
}

/// Builds the alignment method from the command-line choices.
pub fn method_from(
    method: MethodArg,
    bandwidth_px: Option<f64>,
    intrinsics: Option<moma_core::Intrinsics>,
) -> Result<Method> {
    if let Some(b) = bandwidth_px
        && !(b.is_finite() && b > 0.0)
    {
        bail!("--bandwidth-px {b} must be a positive number of pixels");
    }
    Ok(match method {
        MethodArg::Ssra => Method::Ssra(ssra::SsraConfig { intrinsics }),
        MethodArg::Gssa => Method::Gssa,
        MethodArg::Raw => Method::Raw,
        MethodArg::Lwlr => Method::Lwlr(lwlr::LwlrConfig {
            bandwidth_px,
            ..lwlr::LwlrConfig::faithful()
        }),
        MethodArg::LwlrExact => Method::Lwlr(lwlr::LwlrConfig {
            bandwidth_px,
            ..lwlr::LwlrConfig::exact()
        }),
    })
}

pub fn run(args: &CalibrateArgs) -> Result<()> {
    if args.source.pred.len() + args.source.rgb.len() != 1 {
        bail!("calibrate takes exactly one --pred FILE or one --rgb IMG (the calibration frame)");
    }
    let intrinsics = args.camera.as_ref().map(moma_io::read_camera).transpose()?;
    let mut source = args.source.open()?;
    let input = source.get(0)?;
    let pred = input.prediction;
    let size = pred.size();

    // The I/O error names the ground-truth file; the context adds which prediction it is for.
    let gt = moma_io::read_depth_sized(&args.gt, size).with_context(|| {
        format!(
            "reading the ground truth for prediction {}",
            input.path.display()
        )
    })?;
    if let Some(k) = &intrinsics {
        k.size()
            .expect_eq("prediction (vs camera.json)", size)
            .with_context(|| {
                format!(
                    "{} does not match {}",
                    input.path.display(),
                    args.camera
                        .as_ref()
                        .map(|p| p.display().to_string())
                        .unwrap_or_default()
                )
            })?;
    }
    let sample_mask = args
        .mask
        .as_ref()
        .map(|p| moma_io::read_mask_sized(p, size))
        .transpose()?;
    let workspace = args
        .workspace
        .as_ref()
        .map(|p| moma_io::read_mask_sized(p, size))
        .transpose()?;

    let config = CalibrationConfig {
        method: method_from(args.method, args.bandwidth_px, intrinsics)?,
        normalisation: NormalisationConfig {
            method: args.norm.into(),
            inverse_space: args.inverse_space,
        },
        sampling: SamplingConfig {
            strategy: match args.sampling {
                SamplingArg::Random => SamplingStrategy::Random,
                SamplingArg::Grid => SamplingStrategy::Grid,
            },
            n: args.samples,
            seed: args.seed,
        },
    };
    let calibration = calibrate(
        &pred,
        &gt,
        &config,
        workspace.as_ref(),
        sample_mask.as_ref(),
    )
    .with_context(|| {
        format!(
            "calibration failed (prediction {}, ground truth {})",
            input.path.display(),
            args.gt.display()
        )
    })?;

    let mut created = CreationInfo::now()
        .with_source(
            if input.rgb.is_some() {
                "rgb"
            } else {
                "prediction"
            },
            &input.path,
        )
        .with_source("ground_truth", &args.gt);
    if let Some(p) = &args.camera {
        created = created.with_source("camera", p);
    }
    if let Some(p) = &args.mask {
        created = created.with_source("sample_mask", p);
    }
    if let Some(w) = &args.source.model.weights
        && input.rgb.is_some()
    {
        created = created.with_source("weights", w);
    }
    let workspace_path = args.workspace.as_ref().map(|p| {
        std::path::absolute(p)
            .unwrap_or_else(|_| p.clone())
            .display()
            .to_string()
    });
    let file = CalibrationFile::new(calibration, intrinsics, workspace_path, created);
    moma_io::write_calibration(&args.output, &file)?;

    let report = &file.calibration.report;
    if args.json {
        print_json(&serde_json::json!({
            "output": args.output,
            "method": report.method,
            "n_used": report.n_used,
            "rms_residual_m": report.rms_residual_m,
            "fit_time_s": report.fit_time_s,
            "model": file.calibration.model,
        }))?;
    } else {
        println!(
            "calibrated {} on {} samples: RMS residual {:.2} mm, fit {:.1} µs",
            report.method,
            report.n_used,
            report.rms_residual_m * 1e3,
            report.fit_time_s * 1e6
        );
        println!(
            "parameters: {}",
            serde_json::to_string(&file.calibration.model)?
        );
        println!("wrote {}", args.output.display());
    }
    Ok(())
}
