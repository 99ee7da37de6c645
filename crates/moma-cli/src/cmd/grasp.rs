//! `moma grasp`: grasps for a parallel jaw or a suction cup from one frame's metric depth, from a
//! calibrated prediction, or from an RGB image through the depth model and a calibration.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use image::RgbImage;
use moma_core::{Intrinsics, MetricDepth, PredictionKind};
use moma_grasp::{
    Extrinsics, Grasp, GraspRequest, Gripper, GripperKind, PlanOutcome, SceneConfig, plan_grasps,
};

use super::common::{DepthOrigin, ModelArgs, SourceArgs, create_dir, print_json};

/// `--gripper` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum GripperArg {
    /// Parallel jaw (default geometry: Robotiq 2F-85).
    Parallel,
    /// Suction cup (default: 10 mm radius, 15 mm compliance).
    Suction,
}

impl GripperArg {
    /// The gripper with its default geometry ([`GripperKind::default_gripper`]).
    pub fn default_gripper(self) -> Gripper {
        match self {
            GripperArg::Parallel => GripperKind::Parallel,
            GripperArg::Suction => GripperKind::Suction,
        }
        .default_gripper()
    }
}

/// Plan grasps on one frame: a parallel jaw or a suction cup, best first.
///
/// The depth comes from --depth (metric: uint16 mm PNG, float32 .npy in metres, PFM), or from a
/// calibration (`moma calibrate`) applied to --pred, or to --rgb run through the depth model.
/// Grasps are in the camera frame (x right, y down, z forward, metres):
///   parallel: {"kind":"parallel","score":s,"success_prob":p,"center_m":[x,y,z],
///              "approach":[..],"closing":[..],"width_m":w}
///   suction:  {"kind":"suction","score":s,"success_prob":p,"point_m":[x,y,z],"approach":[..]}
/// `success_prob` is (k + 1) / (N + 2) for the k of N depth maps drawn from the depth's error
/// model (the calibration's, or a uniform --sigma-m) on which the grasp succeeds by the proxy's
/// rules: in (0, 1); null without an error model (--depth without --sigma-m). With --realign
/// anchors the frame is re-aligned on static anchors first, exactly as `moma align --realign
/// anchors` does.
/// `center_m` is the midpoint of the two planned contacts, `approach` the unit vector along which
/// the gripper moves (for suction: into the surface), `closing` the unit vector along which the
/// fingers close, `width_m` the opening before closing. With --extrinsics each grasp also carries
/// the same pose fields in the robot base frame under "base".
///
/// Files:
///   --extrinsics: JSON {"camera_to_base":
///                         [[r00,r01,r02,tx],[r10,r11,r12,ty],[r20,r21,r22,tz],[0,0,0,1]]}
///     (rows; p_base = R p_camera + t, metres; must be rigid: orthonormal R, det +1,
///     last row 0 0 0 1)
///   --gripper-config: JSON with any of the gripper's fields, e.g. parallel
///     {"stroke_m":0.085,"finger_height_m":0.02,"finger_thickness_m":0.01,"finger_length_m":0.04,
///      "palm_depth_m":0.02,"contact_to_tip_m":0.01,"opening_clearance_m":0.01}
///     or suction {"radius_m":0.01,"compliance_m":0.015,"tool_length_m":0.1}
///   -o DIR writes grasps.json (the --json array), overlay.png (grasps drawn on the RGB image or the
///     colour-mapped depth; best = green, then yellow to red; below the image a caption: the
///     gripper, the depth's source, SIMULATED where it is, and each grasp's success_prob, score
///     and position), scene.ply (the scene points plus
///     finger/palm or cup boxes of the grasps; binary PLY, opens in MeshLab / Open3D) and
///     depth.npy (the frame's depth in metres, float32, as `moma align` writes it; its provenance
///     in aligned.json, read by `moma metrics`).
///
/// With an error model the planner works on its expected truth of the depth: the mean relief
/// and silhouette corrections the calibration measured (and, for suction, the depth model's
/// short-range bumps averaged out); docs/grasping.md.
///
/// Without a mask, an object is whatever stands more than 10 mm above the fitted support plane,
/// does not touch the image border (--keep-border-objects keeps such regions) and does not
/// enclose an opening of a container's size (a bin's walls: what lies inside is planned on,
/// and an object touching a wall where its top is flat and at least 15 mm below the rim), and
/// lies beside the support plane or such a container somewhere (a thing seen only against a far
/// wall or beside no depth is background).
/// A mask PNG of instance labels (one grey level or colour per object) keeps touching objects apart.
/// "No grasp found" is not an error: an empty list, and the reason on stderr.
///
/// Examples:
///   moma grasp --depth frame.depth.png --camera camera.json --gripper suction --json
///   moma grasp --calib calib.json --rgb rgb.png --weights vits.safetensors --camera camera.json \
///     --gripper parallel --extrinsics camera_to_base.json --top 5 -o grasps/
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
pub struct GraspArgs {
    /// Metric depth map of the frame.
    #[arg(long, value_name = "FILE", required_unless_present = "calib", conflicts_with_all = ["calib", "pred", "rgb"])]
    pub depth: Option<PathBuf>,
    /// Calibration from `moma calibrate`, applied to --pred or --rgb.
    #[arg(long, value_name = "FILE")]
    pub calib: Option<PathBuf>,
    /// A prediction file of the frame (.npy, .pfm, 16-bit .png), with --calib.
    #[arg(long, value_name = "FILE", requires = "calib", conflicts_with = "rgb")]
    pub pred: Option<PathBuf>,
    /// What --pred holds: metric-depth | relative-depth | relative-disparity (default: from
    /// predictions.json beside it, else the calibration file's; the calibration must accept it).
    #[arg(long, value_name = "KIND", requires = "pred")]
    pub pred_kind: Option<PredictionKind>,
    /// RGB image of the frame, run through the depth model (--weights or --hub), with --calib.
    #[arg(long, value_name = "IMG", requires = "calib")]
    pub rgb: Option<PathBuf>,
    #[command(flatten)]
    pub model: ModelArgs,
    /// Camera intrinsics (camera.json) of the frame. Optional with --calib when the calibration
    /// file records them (`moma calibrate --camera`).
    #[arg(long, value_name = "FILE")]
    pub camera: Option<PathBuf>,
    /// Object mask (PNG, nonzero = object): grasps only on masked objects. A label image (one
    /// grey level or colour per object) keeps objects that touch apart.
    #[arg(long, value_name = "PNG")]
    pub mask: Option<PathBuf>,
    /// Without --mask, also plan on regions that touch the image border (dropped by default:
    /// partly seen, and most often a bin wall or the band along the frame's edge where sensor
    /// depth curls away from the table).
    #[arg(long, conflicts_with = "mask")]
    pub keep_border_objects: bool,
    /// Without --mask, also plan on regions that enclose an opening of a container's size
    /// (dropped by default: a bin's or a tote's walls; what lies inside is planned on either
    /// way).
    #[arg(long, conflicts_with = "mask")]
    pub keep_containers: bool,
    /// Camera→robot-base transform (JSON {"camera_to_base": 4 × 4 rows}, as described above):
    /// adds "base" poses.
    #[arg(long, value_name = "FILE")]
    pub extrinsics: Option<PathBuf>,
    /// Gripper type.
    #[arg(long, value_enum)]
    pub gripper: GripperArg,
    #[command(flatten)]
    pub plan: PlanFlags,
    #[command(flatten)]
    pub realign: super::align::RealignArgs,
    /// A uniform σ of the depth's error, metres: with --depth (which has no calibration), or to
    /// override the calibration's error model. Gives every grasp a success probability. Drawn as
    /// one error field correlated over 5 % of the image width (32 pixels at 640×480, 64 at
    /// 1280×720: the same share of the view, so that a probability means the same at any
    /// resolution).
    #[arg(long, value_name = "S")]
    pub sigma_m: Option<f64>,
    /// Print the grasps as one JSON array on stdout, best first.
    #[arg(long)]
    pub json: bool,
    /// Output directory for grasps.json, overlay.png, scene.ply and depth.npy (created if missing).
    #[arg(short, long, visible_alias = "out", value_name = "DIR")]
    pub output: Option<PathBuf>,
    /// The colour image to draw overlay.png on and colour scene.ply with (the frame's RGB, the
    /// depth's size), e.g. the rgb.png beside a sensor's depth.png. Default: the RGB the
    /// prediction was made from (--rgb) or re-aligned on (--realign-rgb), else the
    /// colour-mapped depth.
    #[arg(long, value_name = "PNG", requires = "output")]
    pub overlay_rgb: Option<PathBuf>,
}

/// How grasps are planned and ranked: shared by `moma grasp` and `moma ros2`.
#[derive(Debug, Clone, Args)]
pub struct PlanFlags {
    /// Gripper geometry (JSON with any of the gripper's fields, as `moma grasp --help` describes
    /// it); defaults for the rest.
    #[arg(long, value_name = "FILE")]
    pub gripper_config: Option<PathBuf>,
    /// Number of grasps to return at most.
    #[arg(long, default_value_t = 10, value_name = "K")]
    pub top: usize,
    /// Seed of the planner's sampling (same inputs and seed → same grasps).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// How grasps are ranked: robust (by their share of successes on depth maps drawn from
    /// the error model; the default when there is one) or nominal (by the planner's score on
    /// the depth as if it were exact; success_prob is still reported where it can be).
    #[arg(long, value_name = "QUALITY", value_parser = super::grasp_eval::parse_quality)]
    pub grasp_quality: Option<moma_grasp::GraspQuality>,
    /// Depth maps drawn from the error model per frame (seeded by --seed).
    #[arg(long, value_name = "N", default_value_t = moma_grasp::DEFAULT_GRASP_DRAWS)]
    pub grasp_draws: usize,
    /// Robust ranking: shares of successful draws within this of the best count as tied, and the
    /// planner's score decides among them (in [0, 1]; default 0.2 for the parallel jaw, 0.5
    /// for suction).
    #[arg(long, value_name = "P")]
    pub grasp_tie_tolerance: Option<f32>,
    /// Return only grasps whose success_prob, (successes + 1) / (draws + 2), is at least P (in
    /// [0, 1]); when none is, the list is empty and the reason is printed.
    #[arg(long, value_name = "P")]
    pub min_success_prob: Option<f64>,
}

impl PlanFlags {
    /// The gripper geometry (validated), from `--gripper-config` or the defaults.
    ///
    /// # Errors
    /// An unreadable or invalid gripper file.
    pub fn gripper(&self, gripper: GripperArg) -> Result<Gripper> {
        let what = "gripper config";
        let g = match (gripper, &self.gripper_config) {
            (g, None) => g.default_gripper(),
            (GripperArg::Parallel, Some(p)) => Gripper::Parallel(moma_io::read_json(p, what)?),
            (GripperArg::Suction, Some(p)) => Gripper::Suction(moma_io::read_json(p, what)?),
        };
        if let Err(e) = g.validate() {
            let origin = self.gripper_config.as_ref().map_or_else(
                || "default gripper".to_string(),
                |p| p.display().to_string(),
            );
            return Err(anyhow::Error::new(e).context(format!("{what} {origin}")));
        }
        Ok(g)
    }

    /// Checks what needs no input.
    ///
    /// # Errors
    /// `--top 0`, `--grasp-draws 0`, `--min-success-prob` or `--grasp-tie-tolerance` outside
    /// [0, 1], each naming its flag.
    pub fn check(&self) -> Result<()> {
        if self.top == 0 {
            bail!("--top must be at least 1");
        }
        if self.grasp_draws == 0 {
            bail!("--grasp-draws must be at least 1");
        }
        if let Some(p) = self.min_success_prob
            && !(0.0..=1.0).contains(&p)
        {
            bail!("--min-success-prob {p} is outside [0, 1]");
        }
        if let Some(t) = self.grasp_tie_tolerance
            && !(0.0..=1.0).contains(&t)
        {
            bail!("--grasp-tie-tolerance {t} is outside [0, 1]");
        }
        Ok(())
    }

    /// The planning request for `gripper` with `error_model`, checked.
    ///
    /// # Errors
    /// `--top 0`, `--grasp-draws 0`, a probability outside [0, 1], robust ranking without an
    /// error model.
    pub fn request(
        &self,
        gripper: Gripper,
        error_model: Option<moma_core::DepthErrorModel>,
        scene: SceneConfig,
    ) -> Result<GraspRequest> {
        self.check()?;
        let mut request = GraspRequest::new(gripper).with_error_model(error_model);
        request.top_k = self.top;
        request.seed = self.seed;
        request.draws = self.grasp_draws;
        if let Some(t) = self.grasp_tie_tolerance {
            request.tie_tolerance = t;
        }
        request.min_success_prob = self.min_success_prob;
        request.scene = scene;
        if let Some(q) = self.grasp_quality {
            request.quality = q;
        }
        // what is left is a combination: robust ranking or a minimum probability without an
        // error model, or a calibration's error model out of range
        request.validate().map_err(|e| {
            anyhow::Error::new(e).context("--grasp-quality / --min-success-prob / --sigma-m")
        })?;
        Ok(request)
    }
}

/// A uniform σ beyond which `--sigma-m` was most likely meant in millimetres: a depth error of
/// 0.2 m is larger than any object a gripper takes.
const SUSPICIOUS_SIGMA_M: f64 = 0.2;

/// Reads and checks an extrinsics file (camera → robot base).
///
/// # Errors
/// An unreadable file or a transform that is not rigid.
pub fn read_extrinsics(path: &Path) -> Result<Extrinsics> {
    Extrinsics::new(moma_io::read_extrinsics(path)?)
        .with_context(|| format!("extrinsics file {}", path.display()))
}

/// The frame to plan on.
struct LoadedFrame {
    /// Metric depth.
    depth: MetricDepth,
    /// Its error model (the calibration's for this frame), if any.
    error_model: Option<moma_core::DepthErrorModel>,
    /// Where it came from, for messages.
    name: String,
    /// Its RGB image, when known.
    rgb: Option<RgbImage>,
    /// The calibration's intrinsics and file, with --calib.
    calib_intrinsics: Option<(Intrinsics, PathBuf)>,
    /// Whether the depth comes from SIMULATED predictions (the input's or the calibration's).
    simulated: DepthOrigin,
    /// Where the depth came from, in the overlay's caption: one or two lines.
    origin: Vec<String>,
}

/// A depth file's median depth (metres) when it is beyond [`FAR_FOR_GRASPING_M`], the sign of a
/// depth unit other than the millimetre it was read as; `None` otherwise.
fn far_median_m(depth: &MetricDepth) -> Option<f32> {
    moma_core::valid_median_m(depth.depth_m.view()).filter(|&m| m > FAR_FOR_GRASPING_M)
}

/// Median depth (metres) beyond which a frame to grasp from is no robot cell's: a depth file in
/// 0.1 mm units read as millimetres puts a table 0.7 m away at 7 m.
const FAR_FOR_GRASPING_M: f32 = 3.0;

/// The frame's metric depth: read (--depth), or aligned with --calib.
fn load_depth(args: &GraspArgs) -> Result<LoadedFrame> {
    if let Some(path) = &args.depth {
        let depth = super::common::read_metric_depth(
            path,
            "--depth",
            "plan on it through its calibration instead (`--calib calib.json --pred FILE`)",
        )?;
        if args.realign.realign.is_some() {
            bail!("--realign needs a calibration: use --calib with --pred or --rgb, not --depth");
        }
        args.model.refuse_for("--depth")?;
        if let Some(median) = far_median_m(&depth) {
            eprintln!(
                "note: the median depth of {} is {median:.2} m, beyond a robot arm's reach: if \
                 its values are not millimetres (a RealSense D405 writes 0.1 mm units), \
                 convert them to millimetres first; grasps are planned as read",
                path.display()
            );
        }
        let simulated = super::common::depth_origin(path)?;
        let origin = vec![match &simulated {
            DepthOrigin::Simulated(p) => format!(
                "SIMULATED predictions (as {} says), not a depth model's output",
                tail(p)
            ),
            DepthOrigin::NotSimulated => {
                "a depth file as given (no record of its origin says SIMULATED)".to_string()
            }
            DepthOrigin::Unknown => {
                "depth of unknown origin (another tool's aligned.json)".to_string()
            }
        }];
        return Ok(LoadedFrame {
            depth,
            error_model: None,
            name: path.display().to_string(),
            rgb: None,
            calib_intrinsics: None,
            simulated,
            origin,
        });
    }
    let Some(calib_path) = &args.calib else {
        bail!("give --depth FILE, or --calib FILE with --pred FILE or --rgb IMG");
    };
    if args.pred.is_none() && args.rgb.is_none() {
        bail!("--calib needs the frame: --pred FILE or --rgb IMG (with --weights or --hub)");
    }
    let calib = moma_io::read_calibration(calib_path)?;
    let source = SourceArgs {
        pred: args.pred.iter().cloned().collect(),
        pred_kind: args.pred_kind,
        rgb: args.rgb.iter().cloned().collect(),
        model: args.model.clone(),
    };
    let mut opened = source
        .open(Some(calib.prediction_kind))
        .with_context(|| format!("the frame for {}", calib_path.display()))?;
    let input = opened.get(0)?;
    calib
        .image_size
        .expect_eq("prediction", input.prediction.size())
        .with_context(|| {
            format!(
                "{} vs calibration {}",
                input.path.display(),
                calib_path.display()
            )
        })?;
    let realign_config = args.realign.check(1, &calib.calibration, calib_path)?;
    let realign_rgb = args
        .realign
        .rgb_for(0, &input.path, input.rgb.as_ref(), calib.image_size)?;
    let realign_grey = realign_rgb
        .as_ref()
        .map(super::common::grey_of)
        .transpose()?;
    let options = moma_core::AlignOptions {
        realign: realign_grey.as_ref().map(|g| (g, &realign_config)),
        sigma_map: false,
    };
    let aligned = calib
        .calibration
        .aligned(&input.prediction, &options)
        .with_context(|| format!("aligning {}", input.path.display()))?;
    if let Some(note) = &aligned.normalisation_note {
        eprintln!("note: {}: {note}", input.path.display());
    }
    if let Some(report) = &aligned.realign {
        eprintln!(
            "{}: re-aligned on {} anchors: {}{}",
            input.path.display(),
            report.anchors,
            if report.accepted { "" } else { "WARNING: " },
            report.reason
        );
    }
    let depth = aligned.depth;
    let simulated = opened.simulated || calib.created.simulated_predictions;
    let mut origin = vec![if simulated {
        format!(
            "SIMULATED predictions (as {} says), not a depth model's output",
            tail(calib_path)
        )
    } else if args.rgb.is_some() {
        format!(
            "the depth model's prediction of {} (not checked for trained weights)",
            tail(&input.path)
        )
    } else {
        format!("the prediction {}", tail(&input.path))
    }];
    origin.push(format!(
        "aligned by {} ({}){}",
        tail(calib_path),
        calib.method,
        match &aligned.realign {
            Some(r) if r.accepted => ", re-aligned on static anchors",
            Some(_) => ", re-alignment refused: one-shot depth",
            None => ", one-shot",
        }
    ));
    Ok(LoadedFrame {
        depth,
        error_model: aligned.error_model,
        name: input.path.display().to_string(),
        // the frame's RGB for the overlay: the model's input, or the one re-aligned on
        rgb: input.rgb.or(realign_rgb),
        calib_intrinsics: calib.intrinsics.map(|k| (k, calib_path.clone())),
        simulated: if simulated {
            DepthOrigin::Simulated(calib_path.clone())
        } else {
            DepthOrigin::NotSimulated
        },
        origin,
    })
}

pub fn run(args: &GraspArgs) -> Result<()> {
    args.plan.check()?;
    let extrinsics = args
        .extrinsics
        .as_deref()
        .map(read_extrinsics)
        .transpose()?;
    let gripper = args.plan.gripper(args.gripper)?;
    let LoadedFrame {
        depth,
        error_model,
        name: depth_name,
        rgb,
        calib_intrinsics,
        simulated,
        origin,
    } = load_depth(args)?;
    let rgb = match &args.overlay_rgb {
        Some(p) => Some(
            moma_io::read_rgb_sized(p, depth.size())
                .with_context(|| format!("--overlay-rgb for the depth of {depth_name}"))?,
        ),
        None => rgb,
    };
    let (camera, camera_name) = match (&args.camera, calib_intrinsics) {
        (Some(p), _) => (
            moma_io::read_camera(p)?,
            format!("camera file {}", p.display()),
        ),
        (None, Some((k, calib))) => (k, format!("the intrinsics of {}", calib.display())),
        (None, None) => bail!(
            "--camera camera.json is needed: {}",
            if args.calib.is_some() {
                "the calibration file records no intrinsics (calibrate with --camera)"
            } else {
                "a depth map carries no intrinsics"
            }
        ),
    };
    if camera.size() != depth.size() {
        bail!(
            "{camera_name} is for {} images but the depth of {depth_name} is {}",
            camera.size(),
            depth.size()
        );
    }
    if matches!(simulated, DepthOrigin::Simulated(_)) {
        eprintln!(
            "note: the depth of {depth_name} comes from SIMULATED predictions: these grasps are \
             not planned on a depth model's output"
        );
    }
    let mask = args
        .mask
        .as_ref()
        .map(|p| moma_io::read_object_mask_sized(p, depth.size()))
        .transpose()?;
    let error_model = match args.sigma_m {
        Some(sigma) => {
            if sigma > SUSPICIOUS_SIGMA_M {
                eprintln!(
                    "note: --sigma-m {sigma} is metres: an error of that size leaves no grasp a \
                     chance (millimetres? 10 mm is --sigma-m 0.01)"
                );
            }
            Some(
                moma_core::DepthErrorModel::uniform_for_width(sigma, depth.size().width)
                    .context("--sigma-m")?,
            )
        }
        None => error_model,
    };
    let request = args.plan.request(
        gripper,
        error_model,
        SceneConfig::keeping(args.keep_border_objects, args.keep_containers),
    )?;
    let (scene, mut outcome) =
        plan_grasps(&depth, &camera, mask.as_ref(), &request).map_err(|e| {
            let about = match (&e, &args.mask) {
                (moma_grasp::GraspError::MaskNoValidDepth { .. }, Some(m)) => {
                    format!("mask {} on the depth of {depth_name}", m.display())
                }
                (moma_grasp::GraspError::Intrinsics(_), _) => camera_name.clone(),
                _ => format!("depth of {depth_name}"),
            };
            anyhow::Error::new(e).context(about)
        })?;
    if let Some(note) = scene.border_note() {
        eprintln!("note: {note} (--keep-border-objects keeps them, --mask chooses objects)");
    }
    if let Some(note) = scene.container_note() {
        eprintln!("note: {note} (--mask; --keep-containers plans on them)");
    }
    if let Some(note) = scene.floating_note() {
        eprintln!("note: {note} (--mask chooses objects)");
    }
    if let Some(e) = &extrinsics {
        outcome.set_base(e);
    }
    match &outcome.no_grasp_reason {
        // "nothing stands above the support plane" would contradict the note above
        Some(moma_grasp::NoGraspReason::NoObject) if !scene.notes().is_empty() => {
            eprintln!(
                "no grasp found on {depth_name}: no object but the region(s) the notes above \
                 name (--keep-border-objects, --keep-containers plan on them)"
            );
        }
        Some(reason) => eprintln!("no grasp found on {depth_name}: {reason}"),
        None => {}
    }
    if let Some(dir) = &args.output {
        // what the overlay says it shows (its caption strip)
        let mut title = vec![format!(
            "moma grasp: {} grasps on the depth of {}",
            gripper.kind_name(),
            tail(Path::new(&depth_name))
        )];
        title.extend(origin.iter().cloned());
        title.push(moma_eval::render::success_prob_caption(
            match (&args.sigma_m, request.error_model.is_some()) {
                (Some(s), _) => Some(format!("a uniform σ of {:.1} mm", s * 1000.0)),
                (None, true) => Some("the calibration's error model".to_string()),
                (None, false) => None,
            }
            .as_deref(),
        ));
        // recorded where it is known (not beside another tool's aligned.json)
        let provenance = match simulated {
            DepthOrigin::Unknown => None,
            known => Some(moma_io::AlignedFile {
                file: "depth.npy".into(),
                simulated: matches!(known, DepthOrigin::Simulated(_)),
                written_by: "moma grasp".into(),
                calibration: args.calib.as_deref().map(moma_io::recorded_path),
                method: None,
                input: Some(moma_io::recorded_path(Path::new(&depth_name))),
            }),
        };
        let written = write_outputs(
            dir, &outcome, &gripper, &depth, &camera, rgb, provenance, &title,
        )?;
        if !args.json {
            for p in written {
                println!("wrote {}", p.display());
            }
        }
    }
    if args.json {
        print_json(&outcome.grasps)?;
    } else {
        print_summary(&outcome);
    }
    Ok(())
}

fn print_summary(outcome: &PlanOutcome) {
    if outcome.grasps.is_empty() {
        return;
    }
    let with_base = outcome.grasps.first().is_some_and(|g| match g {
        Grasp::Parallel(p) => p.base.is_some(),
        Grasp::Suction(s) => s.base.is_some(),
    });
    println!(
        "{} grasp(s), best first (camera frame{}, metres):",
        outcome.grasps.len(),
        if with_base {
            " and robot base frame"
        } else {
            ""
        }
    );
    for (k, g) in outcome.grasps.iter().enumerate() {
        let prob = |p: Option<f32>| p.map_or(String::new(), |p| format!("  success_prob {p:.2}"));
        let f = |v: [f32; 3]| format!("[{:+.3}, {:+.3}, {:+.3}]", v[0], v[1], v[2]);
        match g {
            Grasp::Parallel(p) => {
                println!(
                    "  #{:<2} score {:.3}{}  centre {}  approach {}  closing {}  width {:.1} mm",
                    k + 1,
                    p.score,
                    prob(p.success_prob),
                    f(p.pose.center_m),
                    f(p.pose.approach),
                    f(p.pose.closing),
                    p.pose.width_m * 1e3
                );
                if let Some(b) = &p.base {
                    println!(
                        "      base frame:  centre {}  approach {}  closing {}",
                        f(b.center_m),
                        f(b.approach),
                        f(b.closing)
                    );
                }
            }
            Grasp::Suction(s) => {
                println!(
                    "  #{:<2} score {:.3}{}  point {}  approach {}",
                    k + 1,
                    s.score,
                    prob(s.success_prob),
                    f(s.pose.point_m),
                    f(s.pose.approach)
                );
                if let Some(b) = &s.base {
                    println!(
                        "      base frame:  point {}  approach {}",
                        f(b.point_m),
                        f(b.approach)
                    );
                }
            }
        }
    }
}

/// The last two components of `path` (a caption's room is one line).
fn tail(path: &Path) -> String {
    let parts: Vec<_> = path.components().collect();
    let from = parts.len().saturating_sub(2);
    parts[from..]
        .iter()
        .collect::<PathBuf>()
        .display()
        .to_string()
}

/// Writes grasps.json (the `--json` array), scene.ply (scene points and gripper boxes),
/// overlay.png (grasps drawn on the RGB image, or on the colour-mapped depth) and depth.npy (the
/// frame's metric depth, as `moma align` writes it, with its `provenance` in aligned.json when
/// it is known) into `dir`; the overlay's caption strip says `title`.
#[allow(clippy::too_many_arguments)] // the run's outputs, each a different thing
fn write_outputs(
    dir: &Path,
    outcome: &PlanOutcome,
    gripper: &Gripper,
    depth: &MetricDepth,
    k: &Intrinsics,
    rgb: Option<RgbImage>,
    provenance: Option<moma_io::AlignedFile>,
    title: &[String],
) -> Result<Vec<PathBuf>> {
    create_dir(dir)?;
    // an earlier run's result goes first: should a write below fail, DIR must not hold that
    // grasps.json beside this run's depth (grasps.json, written last, vouches for the rest)
    let json_path = dir.join("grasps.json");
    super::common::remove_earlier(&json_path)?;
    let background = match rgb {
        Some(img) => img,
        None => {
            moma_io::colourise_depth(
                depth,
                moma_io::Colormap::Turbo,
                moma_io::DepthRange::default(),
            )
            .context("colour-mapping the depth for the overlay")?
            .0
        }
    };
    // the frame's depth as `moma align` writes it (before the planner's expected truth), its
    // provenance recorded first (DIR/aligned.json)
    let depth_path = dir.join("depth.npy");
    let index_context = || format!("the index of {}", dir.display());
    if let Some(p) = &provenance {
        moma_io::record_before_writing(dir, vec![p.clone()]).with_context(index_context)?;
    }
    moma_io::write_depth(&depth_path, depth)?;
    if let Some(p) = provenance {
        moma_io::record_aligned_files(dir, vec![p]).with_context(index_context)?;
    }
    let ply_path = dir.join("scene.ply");
    moma_io::write_scene_ply(
        &ply_path,
        depth,
        k,
        &background,
        &moma_grasp::render::gripper_boxes(outcome, gripper),
        "moma grasp: scene points (camera frame, metres) and gripper boxes of the grasps",
    )?;
    let overlay_path = dir.join("overlay.png");
    moma_eval::render::write_grasp_overlay(&overlay_path, background, k, outcome, gripper, title)?;
    // the result last (each file is written atomically): a grasps.json in DIR means every
    // other output of the run is there too
    moma_io::write_json(&json_path, &outcome.grasps)?;
    Ok(vec![json_path, overlay_path, ply_path, depth_path])
}
