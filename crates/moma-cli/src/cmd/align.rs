//! `moma align`: apply a calibration to many frames.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use moma_core::realign::{AnchorTarget, CorrectionModel, RealignConfig};
use moma_core::{AlignOptions, Aligned, MetricDepth};
use moma_io::{Colormap, DepthRange, PlyFormat};
use serde::Serialize;

use super::common::{SourceArgs, SourcedPrediction, print_json, progress};

/// `--colormap` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ColormapArg {
    /// Google's Turbo.
    Turbo,
    /// Matplotlib's viridis.
    Viridis,
}

impl From<ColormapArg> for Colormap {
    fn from(c: ColormapArg) -> Self {
        match c {
            ColormapArg::Turbo => Colormap::Turbo,
            ColormapArg::Viridis => Colormap::Viridis,
        }
    }
}

/// `--realign` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum RealignArg {
    /// Per-frame re-alignment on static anchors: the calibration frame's unchanged background
    /// (`moma align`: a calibration made with --anchors; `moma eval`: the set's calibration frame).
    Anchors,
}

/// Settings of per-frame re-alignment on static anchors (`--realign anchors`), shared by
/// `moma align` and `moma eval`; defaults are the library's (`moma_core::realign::RealignConfig`).
#[derive(Debug, Clone, Args)]
pub struct RealignFlags {
    /// Re-alignment correction: prediction-affine (an affine map of the frame's normalised
    /// prediction that reproduces the calibration frame's prediction at the anchors, then the
    /// calibration's model), scale-shift or planar (corrections of the one-shot metres).
    #[arg(long, value_name = "FORM", default_value_t = RealignConfig::default().model, requires = "realign")]
    pub realign_form: CorrectionModel,
    /// Ridge λ of the re-alignment towards the identity, in anchor equivalents (>= 0).
    #[arg(long, value_name = "LAMBDA", default_value_t = RealignConfig::default().ridge, requires = "realign")]
    pub realign_ridge: f64,
    /// Most anchors used per frame (a seeded subsample; >= the minimum of 50).
    #[arg(long, value_name = "N", default_value_t = RealignConfig::default().max_anchors, requires = "realign")]
    pub realign_max_anchors: usize,
    /// What the re-alignment reproduces at the anchors: calibration-output (the calibration's
    /// own result on its frame) or ground-truth (scale-shift and planar only).
    #[arg(long, value_name = "TARGET", default_value_t = RealignConfig::default().target, requires = "realign")]
    pub realign_target: AnchorTarget,
}

impl RealignFlags {
    /// The library configuration these flags give, checked.
    ///
    /// # Errors
    /// A value out of range, named by its flag.
    pub fn config(&self) -> Result<RealignConfig> {
        let config = RealignConfig {
            model: self.realign_form,
            ridge: self.realign_ridge,
            max_anchors: self.realign_max_anchors,
            target: self.realign_target,
            ..Default::default()
        };
        config
            .validate()
            .context("--realign-ridge / --realign-max-anchors")?;
        if config.model == CorrectionModel::PredictionAffine
            && config.target != AnchorTarget::CalibrationOutput
        {
            bail!(
                "--realign-target {} needs --realign-form scale-shift or planar (prediction-affine \
                 reproduces the calibration frame's own prediction)",
                config.target
            );
        }
        Ok(config)
    }
}

/// Apply a calibration to predictions (or RGB images through a depth model): metric depth out.
///
/// Writes per input NAME (the file stem, or the frame id for moma-set paths):
///   NAME.depth.png  uint16 millimetres, 0 = no depth
///   NAME.depth.npy  float32 metres, NaN = no depth
///   NAME.color.png  with --colormap: colour-mapped depth (range in metres recorded in the PNG)
///   NAME.ply        with --ply: point cloud in metres, camera frame, coloured when RGB is known
///   aligned.json    where each depth file came from (SIMULATED or not; read by `moma metrics`;
///                   docs/formats.md), beside .aligned.json.lock, which serialises its writers
///
/// Examples:
///   moma align --calib calib.json --pred pred/*.npy --pred-kind relative-disparity -o aligned/ \
///       --colormap turbo
///   moma align --calib calib.json --rgb frames/*/rgb.png --weights vits.safetensors -o aligned/ \
///       --ply
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
pub struct AlignArgs {
    /// Calibration file from `moma calibrate`.
    #[arg(long, value_name = "FILE")]
    pub calib: PathBuf,
    #[command(flatten)]
    pub source: SourceArgs,
    /// Output directory (created if missing).
    #[arg(short, long, visible_alias = "out", value_name = "DIR")]
    pub output: PathBuf,
    /// Also write a point cloud (PLY) per frame; needs intrinsics (calibrated with --camera, or --camera here).
    #[arg(long)]
    pub ply: bool,
    /// Write the PLY as ASCII instead of binary little-endian.
    #[arg(long, requires = "ply")]
    pub ply_ascii: bool,
    /// RGB images to colour the point clouds with (one per input, same order) when the inputs
    /// are prediction files; not with --rgb inputs, whose own images colour them.
    #[arg(long, num_args = 1.., value_name = "IMG", requires = "ply", conflicts_with = "rgb")]
    pub ply_rgb: Vec<PathBuf>,
    /// camera.json to use for point clouds instead of the calibration's intrinsics.
    #[arg(long, value_name = "FILE", requires = "ply")]
    pub camera: Option<PathBuf>,
    /// Also write a colour-mapped PNG per frame (`--colormap` alone: turbo).
    #[arg(long, value_enum, num_args = 0..=1, default_missing_value = "turbo")]
    pub colormap: Option<ColormapArg>,
    /// Colour-map range in metres, e.g. `0.4,1.2` (default: 2nd–98th percentile per frame).
    #[arg(long, value_name = "MIN,MAX", value_parser = parse_range_m, requires = "colormap")]
    pub range_m: Option<(f32, f32)>,
    /// Check only: a workspace mask PNG that must equal the one embedded in the calibration file
    /// (which always normalises over its own workspace); a different mask, or one given for a
    /// calibration made without a workspace, is an error.
    #[arg(long, value_name = "PNG")]
    pub workspace: Option<PathBuf>,
    /// Print a JSON summary on stdout (and no progress bar).
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub realign: RealignArgs,
    /// Also write each frame's per-pixel σ of the depth error from the calibration's error
    /// model (metres, NaN = no depth) as NAME.sigma.npy, and its colour map NAME.sigma.png.
    #[arg(long)]
    pub sigma_map: bool,
}

/// Per-frame re-alignment on static anchors, as `moma align` and `moma grasp` take it.
#[derive(Debug, Clone, Args)]
pub struct RealignArgs {
    /// Re-align each frame (`grasp`: the frame) on static anchors (pixels unchanged since
    /// calibration, found in the frame's RGB): needs a calibration made with `moma calibrate
    /// --anchors`; reports per frame (anchors, held-out RMSE before/after, accepted or why not).
    #[arg(long, value_enum, value_name = "MODE")]
    pub realign: Option<RealignArg>,
    /// The RGB of each frame for --realign when the inputs are prediction files (`align`: one
    /// per input, same order; `grasp`: one); not with --rgb inputs, whose own images are used.
    #[arg(long, num_args = 1.., value_name = "IMG", requires = "realign", conflicts_with = "rgb")]
    pub realign_rgb: Vec<PathBuf>,
    #[command(flatten)]
    pub realign_flags: RealignFlags,
}

impl RealignArgs {
    /// Checks the flags against `n_inputs` inputs and the calibration (read from
    /// `calib_path`), and returns the re-alignment settings.
    ///
    /// # Errors
    /// --realign-rgb not one per input; --realign with a calibration without anchors; bad
    /// settings.
    pub fn check(
        &self,
        n_inputs: usize,
        calibration: &moma_core::Calibration,
        calib_path: &Path,
    ) -> Result<RealignConfig> {
        if !self.realign_rgb.is_empty() && self.realign_rgb.len() != n_inputs {
            bail!(
                "--realign-rgb needs one image per input ({} given for {} inputs)",
                self.realign_rgb.len(),
                n_inputs
            );
        }
        if self.realign.is_some() {
            calibration
                .anchor_store()
                .with_context(|| format!("--realign anchors with {}", calib_path.display()))?;
        }
        self.realign_flags.config()
    }

    /// The RGB to re-align input `i` (named `name`, with its own RGB `own` when it came from
    /// --rgb) on, `None` without --realign.
    ///
    /// # Errors
    /// No RGB for the input; an unreadable image or one of another size.
    pub fn rgb_for(
        &self,
        i: usize,
        name: &Path,
        own: Option<&image::RgbImage>,
        size: moma_core::ImageSize,
    ) -> Result<Option<image::RgbImage>> {
        let Some(RealignArg::Anchors) = self.realign else {
            return Ok(None);
        };
        Ok(Some(match self.realign_rgb.get(i) {
            Some(p) => moma_io::read_rgb_sized(p, size)?,
            None => own.cloned().with_context(|| {
                format!(
                    "--realign anchors needs the RGB of {}: give --realign-rgb IMG... \
                     (one per input) or align from --rgb",
                    name.display()
                )
            })?,
        }))
    }
}

/// What was written for one frame.
#[derive(Debug, Serialize)]
struct FrameSummary {
    name: String,
    input: PathBuf,
    outputs: Vec<PathBuf>,
    /// The calibration's alignment method and normalisation (`ssra`, `minmax`, ...).
    method: String,
    normalisation: String,
    valid_pixels: usize,
    /// Per-frame re-alignment report (with --realign).
    #[serde(skip_serializing_if = "Option::is_none")]
    realign: Option<moma_core::realign::RealignReport>,
    /// Normalisation + alignment time, milliseconds (excludes file I/O and the depth model).
    align_ms: f64,
    /// A min-max normalisation that hangs on a few isolated pixels of the prediction
    /// (`moma_core::normalise::isolated_extremes`), as printed on stderr.
    #[serde(skip_serializing_if = "Option::is_none")]
    normalisation_note: Option<String>,
    /// SIMULATED: the input prediction, or the predictions the calibration was fitted on, came
    /// from the simulator (not a depth model).
    simulated: bool,
}

pub fn run(args: &AlignArgs) -> Result<()> {
    super::common::check_unique_output_names(args.source.inputs())?;
    let calib = moma_io::read_calibration(&args.calib)?;
    let mut source = args
        .source
        .open(Some(calib.prediction_kind))
        .with_context(|| format!("predictions for {}", args.calib.display()))?;
    if !args.ply_rgb.is_empty() && args.ply_rgb.len() != source.len() {
        bail!(
            "--ply-rgb needs one image per input ({} given for {} inputs)",
            args.ply_rgb.len(),
            source.len()
        );
    }
    let realign_config = args
        .realign
        .check(source.len(), &calib.calibration, &args.calib)?;
    if args.sigma_map && calib.calibration.error_model.is_none() {
        bail!(
            "--sigma-map needs the calibration's error model, which {} does not hold (written \
             before error models existed, or its fit failed on the calibration frame: `moma \
             calibrate` warned of it)",
            args.calib.display()
        );
    }
    let size = calib.image_size;
    let intrinsics = match &args.camera {
        Some(p) => {
            let k = moma_io::read_camera(p)?;
            // checked before any frame is written: a camera of another size fails every frame
            size.expect_eq("camera", k.size()).with_context(|| {
                format!("{} vs calibration {}", p.display(), args.calib.display())
            })?;
            Some(k)
        }
        None => calib.intrinsics,
    };
    if args.ply && intrinsics.is_none() {
        bail!(
            "--ply needs camera intrinsics: calibrate with --camera, or pass --camera camera.json here"
        );
    }
    if let Some(p) = &args.workspace {
        let given = moma_core::Workspace::new(moma_io::read_mask_sized(p, size)?)
            .with_context(|| format!("workspace mask {}", p.display()))?;
        match calib.calibration.check_workspace(&given) {
            Ok(()) => {}
            Err(moma_core::pipeline::WorkspaceMismatch::Differs) => bail!(
                "workspace mismatch: {} differs from the workspace embedded in {} (the \
                 calibration aligns with its own workspace; drop --workspace)",
                p.display(),
                args.calib.display()
            ),
            Err(moma_core::pipeline::WorkspaceMismatch::NoneRecorded) => bail!(
                "workspace mismatch: {} was calibrated without a workspace, but --workspace {} \
                 was given",
                args.calib.display(),
                p.display()
            ),
        }
    }
    let range = match args.range_m {
        None => DepthRange::default(),
        Some((min_m, max_m)) => {
            if max_m > SUSPICIOUS_RANGE_M {
                eprintln!(
                    "note: --range-m ends at {max_m} m, far beyond an RGB-D sensor's reach: the \
                     values are metres (0.4,1.2), not millimetres"
                );
            }
            DepthRange::Fixed { min_m, max_m }
        }
    };
    if calib.created.simulated_predictions {
        eprintln!(
            "note: {} was fitted on SIMULATED predictions: the depth it gives is not a depth \
             model's",
            args.calib.display()
        );
    }
    let simulated = source.simulated || calib.created.simulated_predictions;
    // (created here, it goes again if the run fails before writing into it)
    let output_dir = super::common::create_output_dir(&args.output)?;
    // the folder's index records where each frame's depth came from (a SIMULATED one is scored
    // as such later, by `moma metrics`): before the frame's files are written (keeping the
    // label of files they replace) and once they are
    // (every file of the frame: its colour map, σ maps and point cloud say SIMULATED there too)
    let index_entries = |name: &str, input: &Path, with_ply: bool| -> Vec<moma_io::AlignedFile> {
        let entry = |file: String| moma_io::AlignedFile {
            file,
            simulated,
            written_by: "moma align".into(),
            calibration: Some(moma_io::recorded_path(&args.calib)),
            method: Some(calib.method.to_string()),
            input: Some(moma_io::recorded_path(input)),
        };
        let mut files = vec![
            entry(format!("{name}.depth.png")),
            entry(format!("{name}.depth.npy")),
        ];
        if args.sigma_map {
            files.push(entry(format!("{name}.sigma.npy")));
            files.push(entry(format!("{name}.sigma.png")));
        }
        if args.colormap.is_some() {
            files.push(entry(format!("{name}.color.png")));
        }
        if with_ply {
            files.push(entry(format!("{name}.ply")));
        }
        files
    };
    let index_context = || format!("the index of {}", args.output.display());

    let bar = progress(source.len(), "aligning", args.json);
    let frame = |i: usize, input: SourcedPrediction| -> Result<FrameSummary> {
        size.expect_eq("prediction", input.prediction.size())
            .with_context(|| {
                format!(
                    "{} vs calibration {}",
                    input.path.display(),
                    args.calib.display()
                )
            })?;
        let t = Instant::now();
        let realign_rgb = args
            .realign
            .rgb_for(i, &input.path, input.rgb.as_ref(), size)?;
        let realign_grey = realign_rgb
            .as_ref()
            .map(super::common::grey_of)
            .transpose()?;
        let options = AlignOptions {
            realign: realign_grey.as_ref().map(|g| (g, &realign_config)),
            sigma_map: args.sigma_map,
        };
        let Aligned {
            depth,
            realign,
            sigma_m,
            normalisation_note,
            ..
        } = calib
            .calibration
            .aligned(&input.prediction, &options)
            .with_context(|| format!("aligning {}", input.path.display()))?;
        let align_ms = t.elapsed().as_secs_f64() * 1e3;
        if let Some(note) = &normalisation_note {
            eprintln!("note: {}: {note}", input.path.display());
        }
        // every input of this frame's files is read and checked before the first is written:
        // a frame that fails leaves none of its files
        let cloud = match intrinsics.filter(|_| args.ply) {
            Some(k) => Some((
                k,
                match args.ply_rgb.get(i) {
                    Some(p) => Some(moma_io::read_rgb_sized(p, size)?),
                    None => input.rgb.clone(),
                },
            )),
            None => None,
        };

        let with_ply = cloud.is_some();
        moma_io::record_before_writing(
            &args.output,
            index_entries(&input.name, &input.path, with_ply),
        )
        .with_context(index_context)?;
        let mut outputs = Vec::new();
        let base = args.output.join(&input.name);
        let png = with_suffix(&base, "depth.png");
        let stats = moma_io::write_depth(&png, &depth)?;
        if stats.out_of_range > 0 {
            // the PNG holds 0.5 mm … 65.535 m; the .npy beside it keeps every depth
            eprintln!(
                "warning: {}: {} of {} pixels outside what a millimetre PNG holds (0.5 mm to \
                 65.535 m) written as 0 (no depth); the .npy keeps them",
                png.display(),
                stats.out_of_range,
                stats.pixels
            );
        }
        outputs.push(png);
        let npy = with_suffix(&base, "depth.npy");
        moma_io::write_depth(&npy, &depth)?;
        outputs.push(npy);
        if let Some(sigma) = sigma_m {
            let sigma = MetricDepth::new(sigma);
            let npy = with_suffix(&base, "sigma.npy");
            moma_io::write_depth(&npy, &sigma)?;
            let png = with_suffix(&base, "sigma.png");
            moma_io::write_sigma_colormap(
                &png,
                &sigma,
                moma_io::Colormap::Turbo,
                DepthRange::default(),
            )?;
            outputs.extend([npy, png]);
        }
        if let Some(cmap) = args.colormap {
            let path = with_suffix(&base, "color.png");
            moma_io::write_depth_colormap(&path, &depth, cmap.into(), range)?;
            outputs.push(path);
        }
        if let Some((k, rgb)) = cloud {
            let path = with_suffix(&base, "ply");
            write_cloud(&path, &depth, &k, rgb.as_ref(), args.ply_ascii)?;
            outputs.push(path);
        }
        moma_io::record_aligned_files(
            &args.output,
            index_entries(&input.name, &input.path, with_ply),
        )
        .with_context(index_context)?;
        bar.inc(1);
        Ok(FrameSummary {
            name: input.name,
            input: input.path,
            outputs,
            method: calib.method.to_string(),
            normalisation: calib.calibration.normalisation.method.to_string(),
            valid_pixels: depth.valid_count(),
            realign,
            align_ms,
            normalisation_note,
            simulated,
        })
    };
    let mut summaries = Vec::with_capacity(source.len());
    // in input order, whatever ran in parallel
    let mut done = |_: usize, s: FrameSummary| -> Result<()> {
        if let Some(report) = &s.realign
            && !args.json
        {
            bar.suspend(|| {
                println!(
                    "{}: {} anchors, {}{}",
                    s.name,
                    report.anchors,
                    if report.accepted { "" } else { "WARNING: " },
                    report.reason
                )
            });
        }
        summaries.push(s);
        Ok(())
    };
    if let Some(files) = source.files() {
        // files: decode, align and encode frames in parallel, a bounded batch at a time
        moma_io::batch::map_bounded(
            source.len(),
            moma_io::batch::default_in_flight(),
            |i| frame(i, files.read(i)?),
            &mut done,
        )?;
    } else {
        // a depth model: one frame at a time (the model uses every core itself)
        for i in 0..source.len() {
            let input = source.get(i)?;
            done(i, frame(i, input)?)?;
        }
    }
    bar.finish_and_clear();

    if args.json {
        print_json(&summaries)?;
    } else {
        let mut times: Vec<f64> = summaries.iter().map(|s| s.align_ms).collect();
        times.sort_by(f64::total_cmp);
        println!(
            "aligned {} {}frame(s) with {} (normalisation {}) into {} (median alignment {:.2} ms \
             per frame)",
            summaries.len(),
            if simulated { "SIMULATED " } else { "" },
            calib.method,
            calib.calibration.normalisation.method,
            args.output.display(),
            times[times.len() / 2]
        );
    }
    output_dir.keep();
    Ok(())
}

/// `base` + `.suffix`, keeping dots in the frame name.
fn with_suffix(base: &Path, suffix: &str) -> PathBuf {
    let mut s = base.as_os_str().to_owned();
    s.push(".");
    s.push(suffix);
    PathBuf::from(s)
}

/// Writes the valid pixels of `depth` as a PLY point cloud (metres, camera frame).
fn write_cloud(
    path: &Path,
    depth: &MetricDepth,
    intrinsics: &moma_core::Intrinsics,
    rgb: Option<&image::RgbImage>,
    ascii: bool,
) -> Result<()> {
    let format = if ascii {
        PlyFormat::Ascii
    } else {
        PlyFormat::BinaryLittleEndian
    };
    moma_io::write_depth_ply(path, depth, intrinsics, rgb, format)?;
    Ok(())
}

/// A colour-map range ending beyond this many metres was most likely typed in millimetres.
const SUSPICIOUS_RANGE_M: f32 = 50.0;

/// `MIN,MAX` in metres → (MIN, MAX): finite, 0 ≤ MIN < MAX. (A `value_delimiter` with
/// `num_args = 2` wanted two separate values and refused the documented `0.4,1.2`.)
fn parse_range_m(s: &str) -> std::result::Result<(f32, f32), String> {
    let bad = |why: &str| format!("{s:?}: {why}; expected MIN,MAX in metres, e.g. 0.4,1.2");
    let (lo, hi) = s.split_once(',').ok_or_else(|| bad("no comma"))?;
    let parse = |x: &str| x.trim().parse::<f32>().map_err(|_| bad("not a number"));
    let (lo, hi) = (parse(lo)?, parse(hi)?);
    if !(lo.is_finite() && hi.is_finite() && lo >= 0.0 && hi > lo) {
        return Err(bad("need 0 <= MIN < MAX, both finite"));
    }
    Ok((lo, hi))
}
