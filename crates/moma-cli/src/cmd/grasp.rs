//! `moma grasp`: grasps for a parallel jaw or a suction cup from one frame's metric depth, from a
//! calibrated prediction, or from an RGB image through the depth model and a calibration.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use image::{Rgb, RgbImage};
use moma_core::{Intrinsics, MetricDepth, PredictionKind};
use moma_grasp::{
    Extrinsics, Grasp, ParallelConfig, ParallelJaw, PlanOutcome, Scene, SceneConfig, SuctionConfig,
    SuctionCup, Vec3, plan_parallel, plan_suction,
};
use serde::Deserialize;

use super::common::{ModelArgs, SourceArgs, create_dir, print_json};

/// `--gripper` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum GripperArg {
    /// Parallel jaw (default geometry: Robotiq 2F-85).
    Parallel,
    /// Suction cup (default: 10 mm radius, 15 mm compliance).
    Suction,
}

/// Plan grasps on one frame: a parallel jaw or a suction cup, best first.
///
/// The depth comes from --depth (metric: uint16 mm PNG, float32 .npy in metres, PFM), or from a
/// calibration (`moma calibrate`) applied to --pred, or to --rgb run through the depth model.
/// Grasps are in the camera frame (x right, y down, z forward, metres):
///   parallel: {"kind":"parallel","score":s,"center_m":[x,y,z],"approach":[..],"closing":[..],"width_m":w}
///   suction:  {"kind":"suction","score":s,"point_m":[x,y,z],"approach":[..]}
/// `center_m` is the midpoint of the two planned contacts, `approach` the unit vector along which
/// the gripper moves (for suction: into the surface), `closing` the unit vector along which the
/// fingers close, `width_m` the opening before closing. With --extrinsics each grasp also carries
/// the same pose fields in the robot base frame under "base".
///
/// Files:
///   --extrinsics: JSON {"camera_to_base": [[r00,r01,r02,tx],[r10,r11,r12,ty],[r20,r21,r22,tz],[0,0,0,1]]}
///     (rows; p_base = R p_camera + t, metres; must be rigid: orthonormal R, det +1, last row 0 0 0 1)
///   --gripper-config: JSON with any of the gripper's fields, e.g. parallel
///     {"stroke_m":0.085,"finger_height_m":0.02,"finger_thickness_m":0.01,"finger_length_m":0.04,
///      "palm_depth_m":0.02,"contact_to_tip_m":0.01,"opening_clearance_m":0.01}
///     or suction {"radius_m":0.01,"compliance_m":0.015,"tool_length_m":0.1}
///   -o DIR writes grasps.json (the --json array), overlay.png (grasps drawn on the RGB image or the
///     colour-mapped depth; best = green, then yellow to red) and scene.ply (the scene points plus
///     finger/palm or cup boxes of the grasps; binary PLY, opens in MeshLab / Open3D).
///
/// Without a mask, an object is whatever stands more than 10 mm above the fitted support plane
/// and does not touch the image border (--keep-border-objects keeps such regions).
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
    /// What --pred holds: depth | inverse-depth (default: from predictions.json beside it and
    /// the calibration file, which must agree).
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
    /// Object mask (PNG, nonzero = object): grasps only on masked objects.
    #[arg(long, value_name = "PNG")]
    pub mask: Option<PathBuf>,
    /// Without --mask, also plan on regions that touch the image border (dropped by default:
    /// partly seen, and most often a bin wall or the band along the frame's edge where sensor
    /// depth curls away from the table).
    #[arg(long, conflicts_with = "mask")]
    pub keep_border_objects: bool,
    /// Camera→robot-base transform (JSON, see above): adds "base" poses.
    #[arg(long, value_name = "FILE")]
    pub extrinsics: Option<PathBuf>,
    /// Gripper type.
    #[arg(long, value_enum)]
    pub gripper: GripperArg,
    /// Gripper geometry (JSON, see above); defaults for the rest.
    #[arg(long, value_name = "FILE")]
    pub gripper_config: Option<PathBuf>,
    /// Number of grasps to return at most.
    #[arg(long, default_value_t = 10, value_name = "K")]
    pub top: usize,
    /// Seed of the planner's sampling (same inputs and seed → same grasps).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Print the grasps as one JSON array on stdout, best first.
    #[arg(long)]
    pub json: bool,
    /// Output directory for grasps.json, overlay.png and scene.ply (created if missing).
    #[arg(short, long, value_name = "DIR")]
    pub output: Option<PathBuf>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ExtrinsicsFile {
    camera_to_base: [[f64; 4]; 4],
}

fn read_json<T: for<'de> Deserialize<'de>>(path: &Path, what: &str) -> Result<T> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read {what} {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{what} {} is not valid", path.display()))
}

fn read_extrinsics(path: &Path) -> Result<Extrinsics> {
    let file: ExtrinsicsFile = read_json(path, "extrinsics file")?;
    Extrinsics::new(file.camera_to_base)
        .with_context(|| format!("extrinsics file {}", path.display()))
}

/// The gripper geometry (validated), from `--gripper-config` or the defaults.
enum GripperGeometry {
    Parallel(ParallelJaw),
    Suction(SuctionCup),
}

fn read_gripper(args: &GraspArgs) -> Result<GripperGeometry> {
    let what = "gripper config";
    let g = match (args.gripper, &args.gripper_config) {
        (GripperArg::Parallel, None) => GripperGeometry::Parallel(ParallelJaw::default()),
        (GripperArg::Suction, None) => GripperGeometry::Suction(SuctionCup::default()),
        (GripperArg::Parallel, Some(p)) => GripperGeometry::Parallel(read_json(p, what)?),
        (GripperArg::Suction, Some(p)) => GripperGeometry::Suction(read_json(p, what)?),
    };
    let checked = match &g {
        GripperGeometry::Parallel(j) => j.validate(),
        GripperGeometry::Suction(c) => c.validate(),
    };
    if let Err(e) = checked {
        let origin = args.gripper_config.as_ref().map_or_else(
            || "default gripper".to_string(),
            |p| p.display().to_string(),
        );
        return Err(anyhow::Error::new(e).context(format!("{what} {origin}")));
    }
    Ok(g)
}

/// The frame to plan on.
struct LoadedFrame {
    /// Metric depth.
    depth: MetricDepth,
    /// Where it came from, for messages.
    name: String,
    /// Its RGB image, when known.
    rgb: Option<RgbImage>,
    /// The calibration's intrinsics and file, with --calib.
    calib_intrinsics: Option<(Intrinsics, PathBuf)>,
    /// The depth comes from SIMULATED predictions (the input's or the calibration's).
    simulated: bool,
}

/// The frame's metric depth: read (--depth), or aligned with --calib.
fn load_depth(args: &GraspArgs) -> Result<LoadedFrame> {
    if let Some(path) = &args.depth {
        let depth = super::common::read_metric_depth(
            path,
            "--depth",
            "plan on it through its calibration instead (`--calib calib.json --pred FILE`)",
        )?;
        return Ok(LoadedFrame {
            depth,
            name: path.display().to_string(),
            rgb: None,
            calib_intrinsics: None,
            simulated: false,
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
    let depth = calib
        .calibration
        .align(&input.prediction)
        .with_context(|| format!("aligning {}", input.path.display()))?;
    Ok(LoadedFrame {
        depth,
        name: input.path.display().to_string(),
        rgb: input.rgb,
        calib_intrinsics: calib.intrinsics.map(|k| (k, calib_path.clone())),
        simulated: opened.simulated || calib.created.simulated_predictions,
    })
}

pub fn run(args: &GraspArgs) -> Result<()> {
    if args.top == 0 {
        bail!("--top must be at least 1");
    }
    let extrinsics = args
        .extrinsics
        .as_deref()
        .map(read_extrinsics)
        .transpose()?;
    let gripper = read_gripper(args)?;
    let LoadedFrame {
        depth,
        name: depth_name,
        rgb,
        calib_intrinsics,
        simulated,
    } = load_depth(args)?;
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
    if simulated {
        eprintln!(
            "note: the depth of {depth_name} comes from SIMULATED predictions: these grasps are \
             not planned on a depth model's output"
        );
    }
    let mask = args
        .mask
        .as_ref()
        .map(|p| moma_io::read_mask_sized(p, depth.size()))
        .transpose()?;
    let scene = Scene::build(
        &depth,
        &camera,
        mask.as_ref(),
        &SceneConfig {
            keep_border_objects: args.keep_border_objects,
            ..SceneConfig::default()
        },
    )
    .map_err(|e| {
        let about = match (&e, &args.mask) {
            (moma_grasp::GraspError::MaskNoValidDepth { .. }, Some(m)) => {
                format!("mask {} on the depth of {depth_name}", m.display())
            }
            (moma_grasp::GraspError::Intrinsics(_), _) => camera_name.clone(),
            _ => format!("depth of {depth_name}"),
        };
        anyhow::Error::new(e).context(about)
    })?;
    if scene.border_regions_dropped() > 0 {
        eprintln!(
            "note: {} region(s) above the support plane touch the image border and are not \
             planned on (partly seen; --keep-border-objects keeps them, --mask chooses objects)",
            scene.border_regions_dropped()
        );
    }
    let mut outcome = match &gripper {
        GripperGeometry::Parallel(jaw) => plan_parallel(
            &scene,
            jaw,
            &ParallelConfig {
                top_k: args.top,
                seed: args.seed,
                ..ParallelConfig::default()
            },
        )?,
        GripperGeometry::Suction(cup) => plan_suction(
            &scene,
            cup,
            &SuctionConfig {
                top_k: args.top,
                seed: args.seed,
                ..SuctionConfig::default()
            },
        )?,
    };
    if let Some(e) = &extrinsics {
        outcome.set_base(e);
    }
    if let Some(reason) = &outcome.no_grasp_reason {
        eprintln!("no grasp found on {depth_name}: {reason}");
    }
    if let Some(dir) = &args.output {
        let written = write_outputs(dir, &outcome, &gripper, &depth, &camera, rgb)?;
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
    println!(
        "{} grasp(s), best first (camera frame, metres):",
        outcome.grasps.len()
    );
    for (k, g) in outcome.grasps.iter().enumerate() {
        let f = |v: [f32; 3]| format!("[{:+.3}, {:+.3}, {:+.3}]", v[0], v[1], v[2]);
        match g {
            Grasp::Parallel(p) => println!(
                "  #{:<2} score {:.3}  centre {}  approach {}  closing {}  width {:.1} mm",
                k + 1,
                p.score,
                f(p.pose.center_m),
                f(p.pose.approach),
                f(p.pose.closing),
                p.pose.width_m * 1e3
            ),
            Grasp::Suction(s) => println!(
                "  #{:<2} score {:.3}  point {}  approach {}",
                k + 1,
                s.score,
                f(s.pose.point_m),
                f(s.pose.approach)
            ),
        }
    }
}

/// Colour of rank `k` of `n`: best green, then yellow to red.
fn rank_colour(k: usize, n: usize) -> [u8; 3] {
    if k == 0 {
        return [0, 230, 0];
    }
    let t = if n > 2 {
        (k - 1) as f32 / (n - 2) as f32
    } else {
        0.0
    };
    [255, (220.0 * (1.0 - t)) as u8, 0]
}

fn project(k: &Intrinsics, p: &Vec3) -> Option<(f32, f32)> {
    (p.z > 1e-6).then(|| {
        (
            (k.fx as f32) * p.x / p.z + k.cx as f32,
            (k.fy as f32) * p.y / p.z + k.cy as f32,
        )
    })
}

fn put(img: &mut RgbImage, x: i64, y: i64, c: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
        img.put_pixel(x as u32, y as u32, Rgb(c));
    }
}

fn line(img: &mut RgbImage, a: (f32, f32), b: (f32, f32), c: [u8; 3], thick: i64) {
    let n = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as usize).clamp(1, 4096);
    for i in 0..=n {
        let t = i as f32 / n as f32;
        let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
        for dy in -thick..=thick {
            for dx in -thick..=thick {
                put(img, x.round() as i64 + dx, y.round() as i64 + dy, c);
            }
        }
    }
}

fn segment(img: &mut RgbImage, k: &Intrinsics, a: &Vec3, b: &Vec3, c: [u8; 3], thick: i64) {
    if let (Some(pa), Some(pb)) = (project(k, a), project(k, b)) {
        line(img, pa, pb, c, thick);
    }
}

/// Draws the grasps, worst first so that the best is on top.
fn draw_overlay(
    img: &mut RgbImage,
    outcome: &PlanOutcome,
    k: &Intrinsics,
    geometry: &GripperGeometry,
) {
    let n = outcome.grasps.len();
    for (rank, g) in outcome.grasps.iter().enumerate().rev() {
        let c = rank_colour(rank, n);
        let thick = if rank == 0 { 1 } else { 0 };
        match (g, geometry) {
            (Grasp::Parallel(p), GripperGeometry::Parallel(jaw)) => {
                let (centre, a, b) = (
                    Vec3::from(p.pose.center_m),
                    Vec3::from(p.pose.approach),
                    Vec3::from(p.pose.closing),
                );
                let h = a.cross(&b) * (jaw.finger_height_m / 2.0);
                let half = p.pose.width_m / 2.0;
                let (f1, f2) = (centre - b * half, centre + b * half);
                segment(img, k, &f1, &f2, c, thick);
                for f in [f1, f2] {
                    segment(img, k, &(f - h), &(f + h), c, thick + 1);
                }
            }
            (Grasp::Suction(s), GripperGeometry::Suction(cup)) => {
                let (p, a) = (Vec3::from(s.pose.point_m), Vec3::from(s.pose.approach));
                let helper = if a.x.abs() < 0.9 {
                    Vec3::x()
                } else {
                    Vec3::y()
                };
                let e1 = a.cross(&helper).normalize();
                let e2 = a.cross(&e1);
                let ring = |i: usize| {
                    let t = std::f32::consts::TAU * i as f32 / 36.0;
                    p + (e1 * t.cos() + e2 * t.sin()) * cup.radius_m
                };
                for i in 0..36 {
                    segment(img, k, &ring(i), &ring(i + 1), c, thick);
                }
                segment(img, k, &p, &(p - a * 0.03), c, thick);
            }
            _ => {}
        }
    }
}

/// A box mesh: centre, three unit axes, half sizes (metres).
struct BoxMesh {
    centre: Vec3,
    axes: [Vec3; 3],
    half: [f32; 3],
    colour: [u8; 3],
}

fn gripper_boxes(outcome: &PlanOutcome, geometry: &GripperGeometry) -> Vec<BoxMesh> {
    let n = outcome.grasps.len();
    let mut boxes = Vec::new();
    for (rank, g) in outcome.grasps.iter().enumerate() {
        let colour = rank_colour(rank, n);
        match (g, geometry) {
            (Grasp::Parallel(p), GripperGeometry::Parallel(jaw)) => {
                let (c, a, b) = (
                    Vec3::from(p.pose.center_m),
                    Vec3::from(p.pose.approach),
                    Vec3::from(p.pose.closing),
                );
                let h = a.cross(&b);
                let (tip, len, palm) =
                    (jaw.contact_to_tip_m, jaw.finger_length_m, jaw.palm_depth_m);
                let half_w = p.pose.width_m / 2.0;
                let t = jaw.finger_thickness_m;
                let fx = tip - len / 2.0;
                for s in [-1.0f32, 1.0] {
                    boxes.push(BoxMesh {
                        centre: c + a * fx + b * (s * (half_w + t / 2.0)),
                        axes: [a, b, h],
                        half: [len / 2.0, t / 2.0, jaw.finger_height_m / 2.0],
                        colour,
                    });
                }
                boxes.push(BoxMesh {
                    centre: c + a * (tip - len - palm / 2.0),
                    axes: [a, b, h],
                    half: [palm / 2.0, half_w + t, jaw.finger_height_m / 2.0],
                    colour,
                });
            }
            (Grasp::Suction(s), GripperGeometry::Suction(cup)) => {
                let (p, a) = (Vec3::from(s.pose.point_m), Vec3::from(s.pose.approach));
                let helper = if a.x.abs() < 0.9 {
                    Vec3::x()
                } else {
                    Vec3::y()
                };
                let e1 = a.cross(&helper).normalize();
                let e2 = a.cross(&e1);
                boxes.push(BoxMesh {
                    centre: p - a * (cup.tool_length_m / 2.0),
                    axes: [a, e1, e2],
                    half: [cup.tool_length_m / 2.0, cup.radius_m, cup.radius_m],
                    colour,
                });
            }
            _ => {}
        }
    }
    boxes
}

/// Binary little-endian PLY: the valid scene points coloured from `colours`, then the boxes as
/// coloured triangle meshes.
fn write_scene_ply(
    path: &Path,
    depth: &MetricDepth,
    k: &Intrinsics,
    colours: &RgbImage,
    boxes: &[BoxMesh],
) -> Result<()> {
    let mut verts: Vec<([f32; 3], [u8; 3])> = Vec::new();
    for ((v, u), &z) in depth.depth_m.indexed_iter() {
        if moma_core::is_valid_depth(z) {
            let x = (u as f64 - k.cx) / k.fx * z as f64;
            let y = (v as f64 - k.cy) / k.fy * z as f64;
            verts.push((
                [x as f32, y as f32, z],
                colours.get_pixel(u as u32, v as u32).0,
            ));
        }
    }
    const QUADS: [[u32; 4]; 6] = [
        [0, 2, 6, 4],
        [1, 5, 7, 3],
        [0, 4, 5, 1],
        [2, 3, 7, 6],
        [0, 1, 3, 2],
        [4, 6, 7, 5],
    ];
    let mut faces: Vec<[u32; 3]> = Vec::new();
    for b in boxes {
        let base = verts.len() as u32;
        for i in 0..8u32 {
            let s = |bit: u32| if i & bit != 0 { 1.0f32 } else { -1.0 };
            let p = b.centre
                + b.axes[0] * (s(1) * b.half[0])
                + b.axes[1] * (s(2) * b.half[1])
                + b.axes[2] * (s(4) * b.half[2]);
            verts.push(([p.x, p.y, p.z], b.colour));
        }
        for q in QUADS {
            faces.push([base + q[0], base + q[1], base + q[2]]);
            faces.push([base + q[0], base + q[2], base + q[3]]);
        }
    }
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment moma grasp: scene points (camera frame, metres) and gripper boxes of the grasps\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        verts.len(),
        faces.len()
    );
    let mut bytes = Vec::with_capacity(header.len() + verts.len() * 15 + faces.len() * 13);
    bytes.extend_from_slice(header.as_bytes());
    for (p, c) in &verts {
        for x in p {
            bytes.extend_from_slice(&x.to_le_bytes());
        }
        bytes.extend_from_slice(c);
    }
    for f in &faces {
        bytes.push(3);
        for i in f {
            bytes.extend_from_slice(&(*i as i32).to_le_bytes());
        }
    }
    write_bytes(path, &bytes)
}

fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    moma_io::atomic_write(path, |w: &mut dyn Write| {
        w.write_all(bytes).map_err(|e| moma_io::IoError::Io {
            path: path.to_path_buf(),
            action: "write",
            source: e,
        })
    })?;
    Ok(())
}

fn write_outputs(
    dir: &Path,
    outcome: &PlanOutcome,
    geometry: &GripperGeometry,
    depth: &MetricDepth,
    k: &Intrinsics,
    rgb: Option<RgbImage>,
) -> Result<Vec<PathBuf>> {
    create_dir(dir)?;
    let json_path = dir.join("grasps.json");
    let mut json = serde_json::to_vec_pretty(&outcome.grasps)?;
    json.push(b'\n');
    write_bytes(&json_path, &json)?;
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
    let ply_path = dir.join("scene.ply");
    write_scene_ply(
        &ply_path,
        depth,
        k,
        &background,
        &gripper_boxes(outcome, geometry),
    )?;
    let mut overlay = background;
    draw_overlay(&mut overlay, outcome, k, geometry);
    let overlay_path = dir.join("overlay.png");
    moma_io::write_rgb(&overlay_path, &overlay)?;
    Ok(vec![json_path, overlay_path, ply_path])
}
