//! `moma calibrate`: fit an alignment on one RGB-D frame and write a calibration file.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use moma_core::align::robust::{DEFAULT_THRESHOLD_M, Robust, RobustKind};
use moma_core::align::{Method, lwlr};
use moma_core::normalise::{AlignSpace, Normalisation, NormalisationConfig};
use moma_core::pipeline::{CalibrationConfig, calibrate};
use moma_core::sampling::{SamplingConfig, SamplingStrategy};
use moma_io::{CalibrationFile, CreationInfo};

use super::common::{SourceArgs, print_json};

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
    /// Alignment method: ssra (the paper's), gssa, lwlr (BoostingDepth's grid solve),
    /// lwlr-exact, lwlr-bare, ssra-local / gssa-local (global fit + local correction, bandwidth
    /// and ridge by leave-one-out), auto (the best of those by leave-one-out), raw (metric
    /// predictions used as metres; needs --norm none).
    #[arg(long, default_value = "ssra", value_name = "METHOD")]
    pub method: Method,
    /// Normalisation of the prediction: minmax (paper), minmax-unit (authors' code), median,
    /// none. Default: minmax (--method raw needs --norm none).
    #[arg(long, value_name = "NORM")]
    pub norm: Option<Normalisation>,
    /// Alignment space: inverse (predictor disparity, target 1/z) or depth. Default: the
    /// prediction's own (inverse-depth predictions align in inverse space, depth in depth space).
    #[arg(long, value_name = "SPACE")]
    pub space: Option<AlignSpace>,
    /// Number of calibration samples n.
    #[arg(long, default_value_t = 100)]
    pub samples: usize,
    /// How samples are chosen: random (MOMA's protocol, seeded) or grid (BoostingDepth's).
    #[arg(long, default_value = "random", value_name = "SAMPLING")]
    pub sampling: SamplingStrategy,
    /// Seed of the random sampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// LWLR bandwidth in pixels (default: 50 px at 640 px width, scaled with the image width).
    #[arg(long, value_name = "PX")]
    pub bandwidth_px: Option<f64>,
    #[command(flatten)]
    pub robust: RobustArgs,
    /// Output calibration file (JSON).
    #[arg(short, long, value_name = "FILE")]
    pub output: PathBuf,
    /// Print the calibration summary as JSON on stdout.
    #[arg(long)]
    pub json: bool,
}

/// `--robust` and `--robust-threshold-m` of `moma calibrate`.
#[derive(Debug, Clone, Args)]
pub struct RobustArgs {
    /// Robust fit against wrong ground truth (sensor edges, glass): huber or tukey (iteratively
    /// reweighted least squares) or ransac (minimal samples seeded with --seed, then least
    /// squares on the inliers). For gssa, ssra, gssa-local and ssra-local. Default: plain least
    /// squares.
    #[arg(long, value_name = "KIND")]
    pub robust: Option<RobustKind>,
    /// Residual scale of the robust fit in metres, measured in depth whatever the alignment
    /// space: Huber's corner, Tukey's cut-off, RANSAC's inlier bound [default: 0.01].
    #[arg(long, value_name = "M", requires = "robust")]
    pub robust_threshold_m: Option<f64>,
}

impl RobustArgs {
    /// The robust fit asked for (RANSAC seeded with `seed`), checked.
    ///
    /// # Errors
    /// A threshold that is not a positive number of metres.
    pub fn robust(&self, seed: u64) -> Result<Option<Robust>> {
        let Some(kind) = self.robust else {
            return Ok(None);
        };
        let r = Robust::new(kind)
            .with_threshold_m(self.robust_threshold_m.unwrap_or(DEFAULT_THRESHOLD_M))
            .with_seed(seed);
        r.validate().context("--robust-threshold-m")?;
        Ok(Some(r))
    }
}

/// The method with the command line's LWLR bandwidth and SSRA intrinsics.
///
/// # Errors
/// A bandwidth that is not a positive number of pixels, or given for a method without one.
pub fn method_from(
    method: &Method,
    bandwidth_px: Option<f64>,
    intrinsics: Option<moma_core::Intrinsics>,
) -> Result<Method> {
    if let Some(b) = bandwidth_px
        && !(b.is_finite() && b > 0.0)
    {
        bail!("--bandwidth-px {b} must be a positive number of pixels");
    }
    Ok(match method.clone().with_intrinsics(intrinsics) {
        Method::Lwlr(cfg) => Method::Lwlr(lwlr::LwlrConfig {
            bandwidth_px: bandwidth_px.or(cfg.bandwidth_px),
            ..cfg
        }),
        other if bandwidth_px.is_some() => {
            bail!("--bandwidth-px applies to the LWLR methods only, not {other}")
        }
        other => other,
    })
}

/// The normalisation from `--norm` (default `minmax`, also for RAW, which then refuses it: a
/// user must say `--norm none` to use a prediction as metres) and `--space` (default: the
/// prediction's own; depth space for RAW).
pub fn normalisation_from(
    method: &Method,
    norm: Option<Normalisation>,
    space: Option<AlignSpace>,
    kind: moma_core::PredictionKind,
) -> NormalisationConfig {
    let default_norm = Normalisation::Minmax;
    let default_space = if *method == Method::Raw {
        AlignSpace::Depth
    } else {
        AlignSpace::native(kind)
    };
    NormalisationConfig {
        method: norm.unwrap_or(default_norm),
        space: space.unwrap_or(default_space),
    }
}

pub fn run(args: &CalibrateArgs) -> Result<()> {
    if args.source.pred.len() + args.source.rgb.len() != 1 {
        bail!("calibrate takes exactly one --pred FILE or one --rgb IMG (the calibration frame)");
    }
    let intrinsics = args.camera.as_ref().map(moma_io::read_camera).transpose()?;
    let mut source = args.source.open(None)?;
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

    let method = method_from(&args.method, args.bandwidth_px, intrinsics)?;
    let config = CalibrationConfig {
        normalisation: normalisation_from(&method, args.norm, args.space, pred.kind),
        method,
        sampling: SamplingConfig {
            strategy: args.sampling,
            n: args.samples,
            seed: args.seed,
        },
        robust: args.robust.robust(args.seed)?,
    };
    if let Some(r) = &config.robust {
        r.check_method(&config.method)
            .with_context(|| format!("--robust {} with --method {}", r.kind, config.method))?;
    }
    config.check(pred.kind).with_context(|| {
        format!(
            "--method {} with --norm {} on {} predictions ({}): --method raw needs --norm none \
             and a metric depth prediction",
            config.method,
            config.normalisation.method,
            pred.kind,
            input.path.display()
        )
    })?;
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
    if let Some(p) = &args.workspace {
        created = created.with_source("workspace (embedded)", p);
    }
    let file = CalibrationFile::new(calibration, intrinsics, created);
    moma_io::write_calibration(&args.output, &file)?;

    let report = &file.calibration.report;
    if args.json {
        let mut summary = serde_json::json!({
            "output": args.output,
            "method": report.method,
            "n_used": report.n_used,
            "rms_residual_m": report.rms_residual_m,
            "fit_time_s": report.fit_time_s,
            "model": file.calibration.model,
        });
        if let (Some(r), Some(obj)) = (&report.robust, summary.as_object_mut()) {
            obj.insert("robust".into(), serde_json::to_value(r)?);
        }
        print_json(&summary)?;
    } else {
        println!(
            "calibrated {} on {} samples: RMS residual {:.2} mm, fit {:.1} µs",
            report.method,
            report.n_used,
            report.rms_residual_m * 1e3,
            report.fit_time_s * 1e6
        );
        if let Some(r) = &report.robust {
            println!(
                "robust {} (threshold {:.1} mm): {} of {} samples are inliers (RMS {:.2} mm), \
                 {} iterations",
                r.kind,
                r.threshold_m * 1e3,
                r.inliers,
                report.n_used,
                r.inlier_rms_residual_m * 1e3,
                r.iterations
            );
        }
        println!(
            "parameters: {}",
            serde_json::to_string(&file.calibration.model)?
        );
        println!("wrote {}", args.output.display());
    }
    Ok(())
}
