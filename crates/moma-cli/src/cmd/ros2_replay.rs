//! `moma ros2-replay`: a camera from files. Publishes a moma set's frames (or a folder of images)
//! as `image` + `camera_info` (+ `depth_sensor` where the set has depth, + `prediction` from a
//! folder of `.npy` maps), all topics of one frame with the same stamp, at a given rate.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime};

use anyhow::{Context, Result, bail};
use clap::Args;
use moma_core::Intrinsics;
use moma_ros2::convert;
use moma_ros2::dds;
use moma_ros2::msg::{self, CameraInfo, Header, Image, Time};

use super::ros2::DdsArgs;

/// Publish recorded frames as a ROS 2 camera: image (rgb8), camera_info, depth_sensor (16UC1
/// millimetres, the set's depth.png) and prediction (32FC1, from --pred), one stamp per frame.
/// Prints one line per published frame: `frame NAME stamp SEC.NANOSEC`.
///
/// Examples:
///   moma ros2-replay --set ../shared/data/gqcnn-primesense --rate 2 --loop
///   moma ros2-replay --set SET --pred preds/ --rate 5     (then: moma ros2 --input prediction …)
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
#[command(group(clap::ArgGroup::new("frames").required(true).args(["set", "images"])))]
pub struct Ros2ReplayArgs {
    /// A moma set: frames/*/rgb.png, depth.png and camera.json.
    #[arg(long, value_name = "DIR")]
    pub set: Option<PathBuf>,
    /// A folder of RGB images (.png, .jpg), published in name order.
    #[arg(long, value_name = "DIR")]
    pub images: Option<PathBuf>,
    /// camera.json for --images (camera_info is published only when intrinsics are known; a
    /// --set has its own).
    #[arg(long, value_name = "FILE", conflicts_with = "set")]
    pub camera: Option<PathBuf>,
    /// Predictions to publish on `prediction`: NAME.npy per frame, in this folder or in its
    /// sub-folder named after the set (`moma simulate` / `moma predict` output).
    #[arg(long, value_name = "DIR")]
    pub pred: Option<PathBuf>,
    /// Frames per second.
    #[arg(long, default_value_t = 5.0, value_name = "HZ")]
    pub rate: f64,
    /// Start over after the last frame (until killed).
    #[arg(long = "loop")]
    pub repeat: bool,
    /// Stop after publishing this many frames in all (with or without --loop).
    #[arg(long, value_name = "N")]
    pub max_frames: Option<u64>,
    /// Wait this long after starting before the first frame, seconds (discovery).
    #[arg(long, default_value_t = 1.0, value_name = "S")]
    pub warmup_s: f64,
    /// Frame id of the camera's optical frame.
    #[arg(long, default_value = "camera_optical_frame", value_name = "FRAME")]
    pub frame_id: String,
    /// Rename a topic: NAME:=TOPIC (image, camera_info, depth_sensor, prediction).
    #[arg(long, value_name = "NAME:=TOPIC")]
    pub remap: Vec<String>,
    #[command(flatten)]
    pub dds: DdsArgs,
}

/// One frame's files, checked up front and decoded when the frame is published (memory stays
/// one frame's, whatever the folder holds).
struct ReplayFrame {
    name: String,
    rgb: PathBuf,
    depth: Option<PathBuf>,
    prediction: Option<PathBuf>,
}

impl ReplayFrame {
    /// (image, depth_sensor, prediction) with `header`; the image checked against `camera`.
    fn messages(
        &self,
        camera: Option<&Intrinsics>,
        header: &Header,
    ) -> Result<(Image, Option<Image>, Option<Image>)> {
        let rgb = moma_io::read_rgb(&self.rgb)?;
        let size = moma_core::ImageSize::new(rgb.width() as usize, rgb.height() as usize);
        if let Some(k) = camera {
            k.size()
                .expect_eq("image", size)
                .with_context(|| format!("{} vs the camera", self.rgb.display()))?;
        }
        // depth and prediction of this frame describe its image pixel by pixel
        let same_size = |p: &Path, map_size: moma_core::ImageSize| -> Result<()> {
            if map_size != size {
                bail!(
                    "{} is {map_size}, but its image {} is {size}",
                    p.display(),
                    self.rgb.display()
                );
            }
            Ok(())
        };
        // The PNG's millimetres as they are: a depth sensor's 16UC1.
        let depth = self
            .depth
            .as_ref()
            .map(|p| -> Result<Image> {
                let mm = moma_io::read_png16(p)?;
                same_size(p, moma_core::ImageSize::of(&mm.view()))?;
                Ok(convert::mm_to_image(&mm, header.clone()))
            })
            .transpose()?;
        let prediction = self
            .prediction
            .as_ref()
            .map(|p| -> Result<Image> {
                let map = moma_io::read_npy_f32(p)?;
                same_size(p, moma_core::ImageSize::of(&map.view()))?;
                Ok(convert::f32_to_image(&map, header.clone()))
            })
            .transpose()?;
        Ok((
            convert::rgb_to_image(&rgb, header.clone()),
            depth,
            prediction,
        ))
    }
}

fn find_prediction(dir: &Path, set_name: Option<&str>, name: &str) -> Option<PathBuf> {
    let direct = dir.join(format!("{name}.npy"));
    if direct.is_file() {
        return Some(direct);
    }
    let nested = dir.join(set_name?).join(format!("{name}.npy"));
    nested.is_file().then_some(nested)
}

fn load_frames(args: &Ros2ReplayArgs) -> Result<(Vec<ReplayFrame>, Option<Intrinsics>)> {
    let mut frames = Vec::new();
    let camera;
    let mut set_name = None;
    let mut inputs: Vec<(String, PathBuf, Option<PathBuf>)> = Vec::new();
    if let Some(root) = &args.set {
        let set = moma_io::MomaSet::open(root)?;
        camera = Some(set.camera);
        set_name = Some(set.name());
        for f in &set.frames {
            inputs.push((f.id.clone(), f.rgb.clone(), Some(f.depth.clone())));
        }
    } else if let Some(dir) = &args.images {
        camera = args.camera.as_ref().map(moma_io::read_camera).transpose()?;
        let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
            .with_context(|| format!("reading {}", dir.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                ["png", "jpg", "jpeg"]
                    .iter()
                    .any(|x| super::common::has_extension(p, x))
            })
            .collect();
        files.sort();
        if files.is_empty() {
            bail!("{} holds no .png or .jpg image", dir.display());
        }
        for p in files {
            let name = p
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default();
            inputs.push((name, p, None));
        }
    } else {
        bail!("give --set DIR or --images DIR");
    }
    for (name, rgb, depth) in inputs {
        let prediction = match &args.pred {
            None => None,
            Some(dir) => Some(
                find_prediction(dir, set_name.as_deref(), &name).with_context(|| {
                    format!(
                        "no prediction for frame {name} in {} (NAME.npy or SET/NAME.npy)",
                        dir.display()
                    )
                })?,
            ),
        };
        frames.push(ReplayFrame {
            name,
            rgb,
            depth,
            prediction,
        });
    }
    Ok((frames, camera))
}

/// The wall-clock time as a ROS stamp.
pub fn now_stamp() -> Time {
    let d = SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .unwrap_or_default();
    Time {
        sec: i32::try_from(d.as_secs()).unwrap_or(i32::MAX),
        nanosec: d.subsec_nanos(),
    }
}

/// Longest wait `--rate` and `--warmup-s` may ask for, seconds (about 32 years).
const MAX_WAIT_S: f64 = 1.0e9;

pub fn run(args: &Ros2ReplayArgs) -> Result<()> {
    // both become a `Duration` added to an `Instant`: bounded by MAX_WAIT_S (1e30 s panicked
    // in the conversion, a period of 1e19 s in the addition)
    let seconds = |s: f64| {
        (s.is_finite() && (0.0..=MAX_WAIT_S).contains(&s)).then(|| Duration::from_secs_f64(s))
    };
    let period = (args.rate.is_finite() && args.rate > 0.0)
        .then(|| seconds(1.0 / args.rate))
        .flatten()
        .with_context(|| {
            format!(
                "--rate {} must be a positive number of frames per second (at least one frame \
                 in {MAX_WAIT_S} s)",
                args.rate
            )
        })?;
    let warmup = seconds(args.warmup_s).with_context(|| {
        format!(
            "--warmup-s {} must be a number of seconds from 0 to {MAX_WAIT_S}",
            args.warmup_s
        )
    })?;
    let (mut image, mut camera_info, mut depth_sensor, mut prediction) = (
        "image".to_string(),
        "camera_info".to_string(),
        "depth_sensor".to_string(),
        "prediction".to_string(),
    );
    let ros = args.dds.ros("moma_replay")?;
    super::ros2::resolve_topics(
        &args.remap,
        &ros,
        &mut [
            ("image", &mut image),
            ("camera_info", &mut camera_info),
            ("depth_sensor", &mut depth_sensor),
            ("prediction", &mut prediction),
        ],
    )?;
    let (frames, camera) = load_frames(args)?;
    let mut node = args.dds.node(&ros)?;
    let qos = dds::sensor_qos();
    let image_pub = dds::publisher::<Image>(&mut node, &image, msg::types::image(), &qos)?;
    let info_pub =
        dds::publisher::<CameraInfo>(&mut node, &camera_info, msg::types::camera_info(), &qos)?;
    let depth_pub = dds::publisher::<Image>(&mut node, &depth_sensor, msg::types::image(), &qos)?;
    let pred_pub = dds::publisher::<Image>(&mut node, &prediction, msg::types::image(), &qos)?;

    // a signal during the warm-up ends the replay at once (the frame loop's first wait sees it)
    super::common::sleep_until_or_stop(Instant::now() + warmup);
    let mut next = Instant::now();
    let mut published = 0u64;
    let mut failed = 0u64;
    'outer: loop {
        for f in &frames {
            if args.max_frames.is_some_and(|n| published >= n) {
                break 'outer;
            }
            // waits for the frame's time, leaving at once on SIGINT / SIGTERM / SIGHUP (the
            // participant then leaves the DDS domain)
            if !super::common::sleep_until_or_stop(next) {
                break 'outer;
            }
            next += period;
            let header = Header {
                stamp: now_stamp(),
                frame_id: args.frame_id.clone(),
            };
            // a frame that cannot be read is skipped with a message, as the node skips bad
            // input; a loop with no readable frame at all ends with the error
            let (image, depth, prediction) = match f.messages(camera.as_ref(), &header) {
                Ok(messages) => messages,
                Err(e) => {
                    eprintln!("moma ros2-replay: frame {} skipped: {e:#}", f.name);
                    failed += 1;
                    if failed >= frames.len() as u64 && published == 0 {
                        return Err(e.context("no frame of the replay could be read"));
                    }
                    continue;
                }
            };
            if let Some(k) = &camera {
                dds::publish(
                    &info_pub,
                    convert::intrinsics_to_camera_info(k, header.clone()),
                )?;
            }
            dds::publish(&image_pub, image)?;
            if let Some(d) = depth {
                dds::publish(&depth_pub, d)?;
            }
            // The prediction last: a node that waits for the image of the same stamp has it.
            if let Some(p) = prediction {
                dds::publish(&pred_pub, p)?;
            }
            println!(
                "frame {} stamp {}.{:09}",
                f.name, header.stamp.sec, header.stamp.nanosec
            );
            published += 1;
        }
        if !args.repeat {
            break;
        }
    }
    // Let the last samples leave before the participant goes.
    std::thread::sleep(Duration::from_millis(300));
    Ok(())
}
