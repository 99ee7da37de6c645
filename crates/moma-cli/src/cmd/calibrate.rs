//! `moma calibrate`: fit an alignment on one RGB-D frame (or several: few-shot) and write a
//! calibration file.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;
use moma_core::align::Method;
use moma_core::align::local::CvLoss;
use moma_core::align::robust::{Robust, RobustKind};
use moma_core::normalise::{AlignSpace, Normalisation};
use moma_core::pipeline::{CalibrationConfig, CalibrationFrame, calibrate};
use moma_core::policy::{MethodOptions, Protocol};
use moma_core::sampling::{SamplingConfig, SamplingStrategy};
use moma_io::{CalibrationFile, CreationInfo};

use super::common::{SourceArgs, print_json};
use super::grasp::GripperArg;

/// Fit an alignment from one frame's prediction and ground truth, or from several frames of the
/// same camera (few-shot: repeat --pred P --gt G; each frame is normalised on its own, --samples
/// are drawn per frame, one fit over all).
///
/// Examples:
///   moma calibrate --pred pred/0000.npy --pred-kind relative-disparity \
///       --gt set/frames/0000/depth.png --camera set/camera.json -o calib.json
///   moma calibrate --rgb set/frames/0000/rgb.png --weights depth_anything_v2_vits.safetensors \
///       --gt set/frames/0000/depth.png --camera set/camera.json --method ssra --samples 100 \
///       --seed 7 -o calib.json
///   moma calibrate --pred pred/0000.npy --gt set/frames/0000/depth.png \
///       --pred pred/0001.npy --gt set/frames/0001/depth.png --camera set/camera.json -o calib.json
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
pub struct CalibrateArgs {
    #[command(flatten)]
    pub source: SourceArgs,
    /// Ground-truth depth of the same frame: uint16 PNG (mm, 0 = none), .npy (m) or .pfm (m).
    /// Several frames: one --gt per --pred / --rgb, in the same order.
    #[arg(long, value_name = "FILE", required = true, num_args = 1..)]
    pub gt: Vec<PathBuf>,
    /// camera.json intrinsics (pixels); used for SSRA's canonical parameters and point clouds.
    #[arg(long, value_name = "FILE")]
    pub camera: Option<PathBuf>,
    /// Draw calibration samples only inside this mask (8-bit PNG, nonzero = inside). Several
    /// frames: one mask for all, or one per frame in the order of --gt. A mask that leaves much
    /// of the image beyond the samples' reach is warned about (`sample_reach` in --json): the
    /// alignment extrapolates there, and the error model gains a σ that grows with the distance
    /// to the samples (`sample_distance_gain`), still too narrow on objects far from them
    /// (docs/grasping.md, "σ away from the samples").
    #[arg(long, value_name = "PNG", num_args = 1..)]
    pub mask: Vec<PathBuf>,
    /// Normalise over this workspace mask instead of the whole map (same mask at run time).
    #[arg(long, value_name = "PNG")]
    pub workspace: Option<PathBuf>,
    /// Alignment method: ssra (the paper's), gssa, lwlr (BoostingDepth's grid solve),
    /// lwlr-exact, lwlr-bare, ssra-local / gssa-local (global fit + local correction, bandwidth
    /// and ridge by cross-validation, kept only when it beats the global fit by more than the
    /// rule's margin), auto (the simplest of gssa, ssra, gssa-local, ssra-local, lwlr within the
    /// margin of the best by that cross-validation; see --protocol), raw (metric predictions
    /// used as metres, normalisation none).
    #[arg(long, default_value = "ssra", value_name = "METHOD")]
    pub method: Method,
    /// Normalisation of the prediction: minmax (paper), minmax-unit (authors' code), median,
    /// none. Default: minmax-unit (the paper's added z_min, in the model's own output units,
    /// moves the whole map with a depth's nearest object or a disparity's scale drift;
    /// docs/evaluation.md); none for --method raw, which refuses any other.
    #[arg(long, value_name = "NORM")]
    pub norm: Option<Normalisation>,
    /// Alignment space: inverse (predictor disparity, target 1/z) or depth. Default: the
    /// prediction's own (relative-disparity predictions align in inverse space, the depth kinds in
    /// depth space).
    #[arg(long, value_name = "SPACE")]
    pub space: Option<AlignSpace>,
    /// Number of calibration samples n (per frame).
    #[arg(long, default_value_t = 100)]
    pub samples: usize,
    /// How samples are chosen: random (MOMA's protocol, seeded) or grid (BoostingDepth's).
    #[arg(long, default_value = "random", value_name = "SAMPLING")]
    pub sampling: SamplingStrategy,
    /// Seed of the random sampling (frame i > 0 of several uses a seed derived from it and i).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Draw samples more than this many pixels away from depth discontinuities of the ground
    /// truth (object boundaries: flying pixels, blurred predictions); 0: anywhere valid (MOMA).
    #[arg(long, default_value_t = 0, value_name = "PX")]
    pub edge_margin_px: u32,
    /// LWLR bandwidth in pixels (default: 50 px at 640 px width, scaled with the image width).
    #[arg(long, value_name = "PX")]
    pub bandwidth_px: Option<f64>,
    #[command(flatten)]
    pub cv: CvArgs,
    #[command(flatten)]
    pub robust: RobustArgs,
    /// Output calibration file (JSON).
    #[arg(short, long, visible_alias = "out", value_name = "FILE")]
    pub output: PathBuf,
    /// Print the calibration summary as JSON on stdout: output, method, frames, n_used,
    /// rms_residual_m, fit_time_s, predicted_error, model, normalisation {method, space},
    /// prediction_kind, simulated_predictions, sample_reach {p90_px, uniform_p90_px, partial}; robust and grasp_check when asked for.
    #[arg(long)]
    pub json: bool,
    /// Store the anchor store for per-frame re-alignment (`moma align --realign anchors`): the
    /// calibration frame's grey, ground truth, one-shot result and normalised prediction at half
    /// resolution (about 920 kB of base64 in the file at 640×480). Uses the --rgb image, or --anchors-rgb with --pred.
    #[arg(long)]
    pub anchors: bool,
    /// The calibration frame's RGB for --anchors when calibrating from --pred.
    #[arg(long, value_name = "IMG", requires = "anchors")]
    pub anchors_rgb: Option<PathBuf>,
    /// Grasp check on the calibration frame (the first), for these grippers (parallel,suction;
    /// default geometries): grasps planned on its aligned prediction with the calibration's
    /// error model, as `moma grasp --calib` plans them, executed on its ground truth by the
    /// proxy's rules (PROXY scores; the top 10 grasps without a mask: a gauge of the cell, not a
    /// forecast). Needs --camera.
    #[arg(
        long,
        value_name = "GRIPPERS",
        value_delimiter = ',',
        requires = "camera"
    )]
    pub grasp_check: Vec<GripperArg>,
}

/// What the calibration will align and how `auto` and the local corrections cross-validate
/// (shared by calibrate and eval).
#[derive(Debug, Clone, Args)]
pub struct CvArgs {
    /// What the calibration will align, which decides how auto, ssra-local and gssa-local
    /// cross-validate: fixed-camera (other frames of a fixed camera: each sample predicted
    /// without its neighbours, squared error in the fit's target units) or per-frame (the frame
    /// it was calibrated on, sparse-to-dense: plain leave-one-out, relative error, bandwidths
    /// down to ≈ 30 px).
    #[arg(long, default_value = "fixed-camera", value_name = "PROTOCOL")]
    pub protocol: Protocol,
    /// Cross-validation loss of auto, ssra-local and gssa-local, replacing the protocol's:
    /// target (squared error in the fit's target units: metres in depth space, 1/m in inverse
    /// space), abs (squared error in metres) or rel (|ẑ − z| / z).
    #[arg(long, value_name = "LOSS")]
    pub cv_loss: Option<CvLoss>,
    /// Selection rule of auto, ssra-local and gssa-local, replacing the protocol's: keep the
    /// simplest model within this many standard errors of the best's CV loss (1: the
    /// one-standard-error rule; 0: the lowest CV loss).
    #[arg(long, value_name = "K", allow_negative_numbers = true)]
    pub cv_margin_se: Option<f64>,
}

impl CvArgs {
    /// `method` with its settings ([`moma_core::policy::method`]).
    pub fn method(
        &self,
        method: Method,
        bandwidth_px: Option<f64>,
        intrinsics: Option<moma_core::Intrinsics>,
    ) -> Result<Method> {
        moma_core::policy::method(
            method,
            &MethodOptions {
                bandwidth_px,
                intrinsics,
                protocol: self.protocol,
                cv_loss: self.cv_loss,
                cv_margin_se: self.cv_margin_se,
            },
        )
        .context("the method's settings (--bandwidth-px, --cv-loss, --cv-margin-se)")
    }
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
    /// Residual scale of the robust fit: `auto` (the default: from the data, σ̂ a robust
    /// standard deviation of the residuals; Huber 1.345·σ̂, Tukey 4.685·σ̂, RANSAC 2.5·σ̂) or a
    /// fixed number of metres, measured in depth whatever the alignment space: Huber's corner,
    /// Tukey's cut-off, RANSAC's inlier bound.
    #[arg(long, value_name = "M|auto", requires = "robust")]
    pub robust_threshold_m: Option<ThresholdArg>,
}

/// `--robust-threshold-m`: `auto` (`None`) or a fixed number of metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThresholdArg(pub Option<f64>);

impl std::str::FromStr for ThresholdArg {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        if s.trim().eq_ignore_ascii_case("auto") {
            return Ok(Self(None));
        }
        s.trim()
            .parse::<f64>()
            .map(|m| Self(Some(m)))
            .map_err(|_| format!("'{s}' is neither 'auto' nor a number of metres"))
    }
}

impl ThresholdArg {
    /// `kind` with this threshold (`auto` when none was given).
    pub fn robust(arg: Option<Self>, kind: RobustKind) -> Robust {
        match arg.and_then(|t| t.0) {
            Some(m) => Robust::new(kind).with_threshold_m(m),
            None => Robust::new(kind),
        }
    }
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
        let r = ThresholdArg::robust(self.robust_threshold_m, kind).with_seed(seed);
        r.validate().context("--robust-threshold-m")?;
        Ok(Some(r))
    }
}

pub fn run(args: &CalibrateArgs) -> Result<()> {
    let n_inputs = args.source.pred.len() + args.source.rgb.len();
    if n_inputs != args.gt.len() {
        bail!(
            "calibrate takes one --gt per --pred / --rgb (the calibration frames, in order): got \
             {n_inputs} prediction input(s) and {} ground truth file(s)",
            args.gt.len()
        );
    }
    if args.mask.len() > 1 && args.mask.len() != args.gt.len() {
        bail!(
            "give one --mask for all frames or one per frame: got {} masks for {} frames",
            args.mask.len(),
            args.gt.len()
        );
    }
    let intrinsics = args.camera.as_ref().map(moma_io::read_camera).transpose()?;
    let mut source = args.source.open(None)?;
    let mut inputs = Vec::with_capacity(n_inputs);
    let mut gts = Vec::with_capacity(n_inputs);
    for (i, gt_path) in args.gt.iter().enumerate() {
        let input = source.get(i)?;
        let size = input.prediction.size();
        if let Some(first) = inputs.first() {
            let first: &super::common::SourcedPrediction = first;
            if size != first.prediction.size() {
                bail!(
                    "calibration frames must have the same size (one camera): {} is {size}, \
                     but {} is {}",
                    input.path.display(),
                    first.path.display(),
                    first.prediction.size()
                );
            }
        }
        // The I/O error names the ground-truth file; the context adds which prediction it is for.
        let gt = moma_io::read_depth_sized(gt_path, size).with_context(|| {
            format!(
                "reading the ground truth for prediction {}",
                input.path.display()
            )
        })?;
        gts.push(gt);
        inputs.push(input);
    }
    let first = &inputs[0];
    let size = first.prediction.size();
    let kind = first.prediction.kind;
    if let Some(k) = &intrinsics {
        k.size()
            .expect_eq("prediction (vs camera.json)", size)
            .with_context(|| {
                format!(
                    "{} does not match {}",
                    first.path.display(),
                    args.camera
                        .as_ref()
                        .map(|p| p.display().to_string())
                        .unwrap_or_default()
                )
            })?;
    }
    let sample_masks = args
        .mask
        .iter()
        .map(|p| moma_io::read_mask_sized(p, size))
        .collect::<Result<Vec<_>, _>>()?;
    let workspace = args
        .workspace
        .as_ref()
        .map(|p| moma_io::read_mask_sized(p, size))
        .transpose()?;

    let method = args
        .cv
        .method(args.method.clone(), args.bandwidth_px, intrinsics)?;
    if intrinsics.is_none()
        && matches!(
            method,
            Method::Ssra(_) | Method::SsraLocal(_) | Method::Auto(_)
        )
    {
        eprintln!(
            "note: no --camera: SSRA's canonical parameters (θ, φ, s) assume a nominal camera \
             (f = image width, principal point at the centre); the fit and its depth do not \
             depend on it, but point clouds and `grasp --calib` will need --camera"
        );
    }
    let config = CalibrationConfig {
        normalisation: moma_core::policy::normalisation(&method, args.norm, args.space, kind),
        method,
        sampling: SamplingConfig {
            strategy: args.sampling,
            n: args.samples,
            seed: args.seed,
            edge_margin_px: args.edge_margin_px,
        },
        robust: args.robust.robust(args.seed)?,
        workspace: None,
    }
    .with_workspace(workspace.as_ref())
    .with_context(|| {
        let path = args.workspace.as_deref().unwrap_or(Path::new(""));
        format!("--workspace {}", path.display())
    })?;
    if let Some(r) = &config.robust {
        r.check_method(&config.method)
            .with_context(|| format!("--robust {} with --method {}", r.kind, config.method))?;
    }
    config.check(kind).with_context(|| {
        let norm = match args.norm {
            Some(n) => format!("--norm {n}"),
            None => format!(
                "normalisation {} (the default)",
                config.normalisation.method
            ),
        };
        format!(
            "--method {} with {norm} on {} predictions ({}): --method raw takes a metric-depth \
             prediction, with normalisation none",
            config.method,
            kind,
            first.path.display()
        )
    })?;
    let frames: Vec<CalibrationFrame<'_>> = inputs
        .iter()
        .zip(&gts)
        .enumerate()
        .map(|(i, (input, gt))| {
            CalibrationFrame::new(&input.prediction, gt)
                .sampled_in(sample_masks.get(i).or(sample_masks.first()))
        })
        .collect();
    // the inputs, as every failure of the calibration names them
    let named_inputs = {
        let pairs: Vec<String> = inputs
            .iter()
            .zip(&args.gt)
            .map(|(input, gt)| {
                format!(
                    "prediction {}, ground truth {}",
                    input.path.display(),
                    gt.display()
                )
            })
            .collect();
        if pairs.len() == 1 {
            pairs[0].clone()
        } else {
            let listed: Vec<String> = pairs
                .iter()
                .enumerate()
                .map(|(i, p)| format!("frame {i}: {p}"))
                .collect();
            listed.join("; ")
        }
    };
    let calibration = calibrate(&frames, &config)
        .with_context(|| format!("calibration failed ({named_inputs})"))?;
    for note in &calibration.normalisation_notes {
        eprintln!("note: {note}");
    }

    // Anchors for per-frame re-alignment come from the first (calibration) frame.
    let calibration = if args.anchors {
        let rgb = match (&args.anchors_rgb, &first.rgb) {
            (Some(p), _) => moma_io::read_rgb_sized(p, size)?,
            (None, Some(img)) => img.clone(),
            (None, None) => bail!(
                "--anchors needs the calibration frame's RGB: calibrate from --rgb IMG, or give \
                 --anchors-rgb IMG with --pred"
            ),
        };
        let calibration = calibration
            .with_anchors(&super::common::grey_of(&rgb)?, &gts[0], &first.prediction)
            .with_context(|| format!("building the anchor store from {}", args.gt[0].display()))?;
        if let Some(w) = calibration
            .anchor_store()
            .ok()
            .and_then(|s| s.saturation_warning())
        {
            eprintln!("warning: {w}");
        }
        calibration
    } else {
        calibration
    };

    // One frame: the roles as before; frame i > 0 of several: "<role> (frame i)".
    let role = |r: &str, i: usize| {
        if i == 0 {
            r.to_string()
        } else {
            format!("{r} (frame {i})")
        }
    };
    let mut created = CreationInfo::now();
    created.simulated_predictions = source.simulated;
    for (i, (input, gt)) in inputs.iter().zip(&args.gt).enumerate() {
        let kind_role = if input.rgb.is_some() {
            "rgb"
        } else {
            "prediction"
        };
        created = created
            .with_source(role(kind_role, i), &input.path)
            .with_source(role("ground_truth", i), gt);
    }
    if let Some(p) = &args.camera {
        created = created.with_source("camera", p);
    }
    for (i, p) in args.mask.iter().enumerate() {
        created = created.with_source(role("sample_mask", i), p);
    }
    if let Some(w) = &args.source.model.weights
        && first.rgb.is_some()
    {
        created = created.with_source("weights", w);
    }
    if let Some(p) = &args.workspace {
        created = created.with_source("workspace (embedded)", p);
    }
    if let Some(p) = &args.anchors_rgb {
        created = created.with_source("anchors_rgb (embedded)", p);
    }
    let file = CalibrationFile::new(calibration, intrinsics, created);
    // before the file is written: a check that fails leaves no calibration behind (nor replaces
    // an earlier one)
    let checks = grasp_checks(&args.grasp_check, &file, &inputs[0], &gts[0], args)?;
    let predicted = file
        .calibration
        .predicted_error(args.cv.protocol)
        .with_context(|| {
            // its folds hold samples out: a fit that its method's minimum just allows cannot be
            // cross-validated
            let n = file.calibration.samples.samples.len();
            let need = config.method.min_samples() + 1;
            let why = if n < need {
                format!(
                    ": its folds fit on fewer than the {n} samples, and {} needs {} to fit: \
                     give at least {need} --samples",
                    config.method,
                    need - 1
                )
            } else {
                String::new()
            };
            format!(
                "cross-validating the calibration for its predicted error ({named_inputs}; \
                 nothing written){why}"
            )
        })?;
    moma_io::write_calibration(&args.output, &file)?;

    let reach = moma_core::sampling::sample_reach_over(
        &file.calibration.samples,
        &gts.iter().collect::<Vec<_>>(),
    );
    if let Some(w) = reach.and_then(|r| r.warning("--mask", file.calibration.error_model.as_ref()))
    {
        eprintln!("warning: {w}");
    }
    if file.calibration.error_model.is_none() {
        eprintln!("warning: {}", moma_core::pipeline::NO_ERROR_MODEL_WARNING);
    }
    let report = &file.calibration.report;
    let n_frames = inputs.len();
    if args.json {
        let mut summary = serde_json::json!({
            "output": args.output,
            "method": report.method,
            "frames": n_frames,
            "n_used": report.n_used,
            "rms_residual_m": report.rms_residual_m,
            "fit_time_s": report.fit_time_s,
            "predicted_error": predicted.map(|cv| serde_json::json!({
                "protocol": file.calibration.predicted_error_protocol(args.cv.protocol),
                "abs_rel": cv.abs_rel,
                "rms_m": cv.rms_m,
            })),
            "model": file.calibration.model,
            // the normalisation taken (its default depends on the kind) and the kind
            "normalisation": file.calibration.normalisation,
            "prediction_kind": file.calibration.prediction_kind,
            "simulated_predictions": source.simulated,
        });
        if let (Some(r), Some(obj)) = (reach, summary.as_object_mut()) {
            obj.insert(
                "sample_reach".into(),
                serde_json::json!({
                    "p90_px": r.p90_px,
                    "uniform_p90_px": r.uniform_p90_px,
                    "partial": r.is_partial(),
                }),
            );
        }
        if let (Some(r), Some(obj)) = (&report.robust, summary.as_object_mut()) {
            obj.insert("robust".into(), serde_json::to_value(r)?);
        }
        if let (false, Some(obj)) = (checks.is_empty(), summary.as_object_mut()) {
            obj.insert("grasp_check".into(), serde_json::to_value(&checks)?);
        }
        print_json(&summary)?;
    } else {
        let from = if n_frames == 1 {
            String::new()
        } else {
            format!(" from {n_frames} frames")
        };
        println!(
            "calibrated {} on {} samples{from}: RMS residual {:.2} mm, fit {:.1} µs",
            report.method,
            report.n_used,
            report.rms_residual_m * 1e3,
            report.fit_time_s * 1e6
        );
        if let Some(r) = &report.robust {
            let threshold = match &r.auto {
                None => format!("threshold {}", millimetres(r.threshold_m)),
                Some(a) => format!(
                    "threshold auto: {} × scale {:.2} mm = {:.1} mm, inlier bound {:.1} mm",
                    a.factor,
                    a.scale_m * 1e3,
                    r.threshold_m * 1e3,
                    a.inlier_bound_m * 1e3
                ),
            };
            let inlier_rms = if r.inliers == 0 {
                "none".to_string()
            } else {
                format!("{:.2} mm", r.inlier_rms_residual_m * 1e3)
            };
            println!(
                "robust {} ({threshold}): {} of {} samples are inliers (RMS {inlier_rms}), \
                 {} iterations",
                r.kind, r.inliers, report.n_used, r.iterations
            );
            // a fixed threshold below the data's scatter: the fit follows a minority of the
            // samples (Tukey, RANSAC) or down-weights all of them alike (Huber, then a least
            // absolute deviations fit); the auto rule estimates the scatter
            if r.auto.is_none() && 2 * r.inliers < report.n_used {
                eprintln!(
                    "warning: only {} of {} samples lie within the fixed robust threshold {}: \
                     it is below these data's scatter (RMS residual {:.2} mm), so the fit {}; \
                     use --robust-threshold-m auto or a threshold above the sensor's noise",
                    r.inliers,
                    report.n_used,
                    millimetres(r.threshold_m),
                    report.rms_residual_m * 1e3,
                    if r.kind == RobustKind::Huber {
                        "treats nearly every sample as an outlier and becomes a least absolute \
                         deviations fit (the median's, not the mean's)"
                    } else {
                        "follows a minority of the samples"
                    }
                );
            }
        }
        if let Some(cv) = predicted {
            println!(
                "predicted error ({} cross-validation on the samples): AbsRel {:.4}, RMS {:.1} mm",
                file.calibration.predicted_error_protocol(args.cv.protocol),
                cv.abs_rel,
                cv.rms_m * 1e3
            );
        }
        if let moma_core::align::AlignmentModel::Auto(m) = &file.calibration.model {
            for line in m.explain() {
                println!("{line}");
            }
        }
        let norm = file.calibration.normalisation;
        let space = norm.space;
        // the normalisation is said: its default depends on the prediction's kind
        println!(
            "parameters (normalisation {}{}, {space} space, target units {}): {}",
            norm.method,
            match (args.norm, &file.calibration.model) {
                (Some(_), _) => String::new(),
                (None, moma_core::align::AlignmentModel::Raw) => ", raw's only one".into(),
                (None, _) => format!(", the default for {kind}"),
            },
            space.target_unit(),
            abridged(serde_json::to_value(&file.calibration.model)?)
        );
        for line in grasp_check_lines(&checks, source.simulated) {
            println!("{line}");
        }
        println!("wrote {}", args.output.display());
    }
    Ok(())
}

/// The grasp check of the calibration frame for each of `grippers`
/// ([`moma_grasp::calibration_frame_check`]): `frame`'s prediction aligned by the calibration of
/// `file` (one-shot, as `moma grasp --calib` without --realign) and planned with its error
/// model, executed on `gt`.
///
/// # Errors
/// No --camera; a failed alignment or grasp check.
fn grasp_checks(
    grippers: &[GripperArg],
    file: &CalibrationFile,
    frame: &super::common::SourcedPrediction,
    gt: &moma_core::MetricDepth,
    args: &CalibrateArgs,
) -> Result<Vec<moma_grasp::GraspCheck>> {
    if grippers.is_empty() {
        return Ok(Vec::new());
    }
    let Some(intrinsics) = file.intrinsics else {
        bail!("--grasp-check needs --camera: grasps are planned in metres");
    };
    grippers
        .iter()
        .map(|&g| {
            let gripper = g.default_gripper();
            moma_grasp::calibration_frame_check(
                &file.calibration,
                &frame.prediction,
                gt,
                &intrinsics,
                None,
                gripper,
                args.seed,
            )
            .with_context(|| {
                format!(
                    "--grasp-check {} on {} and {}",
                    gripper.kind_name(),
                    frame.path.display(),
                    args.gt[0].display()
                )
            })
        })
        .collect()
}

/// The terminal lines of the grasp checks: what they are, then one line per gripper.
fn grasp_check_lines(checks: &[moma_grasp::GraspCheck], simulated: bool) -> Vec<String> {
    if checks.is_empty() {
        return Vec::new();
    }
    let label = if simulated {
        "SIMULATED predictions, PROXY scores"
    } else {
        "PROXY scores"
    };
    let mut lines = vec![format!(
        "grasp check on the calibration frame ({label}; its aligned prediction planned as `moma \
         grasp --calib` plans it, each grasp executed on its ground truth; a gauge of the \
         cell, not a forecast):"
    )];
    for c in checks {
        let gripper = &c.gripper;
        lines.push(if c.grasps == 0 {
            let why = c.no_grasp_reason.as_deref().unwrap_or("no reason given");
            format!("  {gripper}: no grasp ({why})")
        } else {
            let prob = c
                .mean_success_prob
                .map_or(String::new(), |p| format!(", mean success_prob {p:.2}"));
            let failures = if c.failures.is_empty() {
                String::new()
            } else {
                let f: Vec<String> = c.failures.iter().map(|(k, v)| format!("{k} {v}")).collect();
                format!(" (failed: {})", f.join(", "))
            };
            format!(
                "  {gripper}: {} of {} grasps hold{prob}{failures}",
                c.successes, c.grasps
            )
        });
        // what the check did not try: regions the planner leaves out (moma grasp's notes)
        lines.extend(c.notes.iter().map(|n| format!("    note: {n}")));
    }
    lines
}

/// Lists longer than this are summarised on the terminal ([`abridged`]).
const LIST_SHOWN_MAX: usize = 8;

/// `value` as one line of JSON for the terminal, with every list of more than
/// [`LIST_SHOWN_MAX`] entries replaced by a string that counts them: a local fit's samples (100
/// objects for LWLR) or node grids would fill the screen, and the calibration file holds them
/// in full.
fn abridged(value: serde_json::Value) -> String {
    fn walk(v: serde_json::Value) -> serde_json::Value {
        use serde_json::Value;
        match v {
            Value::Array(a) if a.len() > LIST_SHOWN_MAX => {
                Value::String(format!("[{} entries: in the calibration file]", a.len()))
            }
            Value::Array(a) => Value::Array(a.into_iter().map(walk).collect()),
            Value::Object(o) => Value::Object(o.into_iter().map(|(k, v)| (k, walk(v))).collect()),
            other => other,
        }
    }
    walk(value).to_string()
}

/// One RGB-D frame's calibration with `moma calibrate`'s defaults (random sampling, no robust
/// fit, no workspace, the prediction kind's own space and normalisation) and the anchor store
/// when `rgb` is given: what `moma ros2`'s live calibration fits.
///
/// # Errors
/// Settings the method refuses; a failed fit (too few valid samples, degenerate data); anchors
/// that cannot be built.
#[allow(clippy::too_many_arguments)]
pub fn fit_frame(
    prediction: &moma_core::Prediction,
    gt: &moma_core::MetricDepth,
    rgb: Option<&image::RgbImage>,
    intrinsics: Option<moma_core::Intrinsics>,
    method: Method,
    samples: usize,
    seed: u64,
    keep: Option<&moma_core::Calibration>,
) -> Result<moma_core::Calibration> {
    let method = CvArgs {
        protocol: Protocol::default(),
        cv_loss: None,
        cv_margin_se: None,
    }
    .method(method, None, intrinsics)?;
    let kind = prediction.kind;
    // the normalisation and its workspace of the calibration this one replaces, when it is of
    // the same kind (a live calibration keeps what the cell was set up with)
    // (RAW takes no normalisation: `none`, its own default; a RAW calibration's `none` is no
    // setting of the cell's to keep either)
    let kept = keep.filter(|c| {
        c.prediction_kind == kind
            && method != Method::Raw
            && !matches!(c.model, moma_core::align::AlignmentModel::Raw)
    });
    let config = CalibrationConfig {
        normalisation: match kept {
            Some(c) => c.normalisation,
            None => moma_core::policy::normalisation(&method, None, None, kind),
        },
        method,
        sampling: SamplingConfig {
            strategy: SamplingStrategy::Random,
            n: samples,
            seed,
            edge_margin_px: 0,
        },
        robust: None,
        workspace: kept.and_then(|c| c.workspace.clone()),
    };
    config
        .check(kind)
        .with_context(|| format!("--calib-method {} on {kind} predictions", config.method))?;
    let calibration = calibrate(&[CalibrationFrame::new(prediction, gt)], &config)
        .context("calibration failed")?;
    match rgb {
        Some(rgb) => calibration
            .with_anchors(&super::common::grey_of(rgb)?, gt, prediction)
            .context("building the anchor store"),
        None => Ok(calibration),
    }
}

/// A length in metres as millimetres with enough digits to be read (`0.01 mm`, `0.5 mm`, `12.0 mm`).
fn millimetres(m: f64) -> String {
    let mm = m * 1e3;
    if mm != 0.0 && mm.abs() < 0.1 {
        format!("{mm:.1e} mm")
    } else if mm.abs() < 1.0 {
        format!("{mm:.2} mm")
    } else {
        format!("{mm:.1} mm")
    }
}
