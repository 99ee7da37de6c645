//! `moma ros2`: the node. RGB (or a depth model's raw output) in; metric depth, an organised
//! point cloud, grasps and diagnostics out; live calibration from an RGB-D frame through the
//! `calibrate` service. docs/ros2.md describes the topics, QoS and frames.
//!
//! One thread: it drains every subscription, keeps the newest frame (counting the ones it drops,
//! so that a slow model never builds a queue), aligns it through the same library call as
//! `moma align` (`Calibration::aligned`), and publishes. Bad frames are skipped with a
//! diagnostic naming the reason; the node never stops on input.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use moma_core::align::Method;
use moma_core::realign::RealignConfig;
use moma_core::{AlignOptions, Intrinsics, MetricDepth, Prediction};
use moma_grasp::{Extrinsics, GraspRequest, SceneConfig};
use moma_io::{CalibrationFile, CreationInfo};
use moma_ros2::convert;
use moma_ros2::dds::{self, Network};
use moma_ros2::msg::{
    self, CameraInfo, DiagnosticArray, DiagnosticStatus, Header, Image, KeyValue, PointCloud2,
    PoseArray, StringMsg, Time, TriggerResponse,
};
use ros2_client::{Publisher, Subscription};
use rustdds::mio1::{Events, Interest, Poll, Token};

use super::align::{RealignArg, RealignFlags};
use super::common::ModelArgs;
use super::grasp::{GripperArg, PlanFlags};

/// `--input` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum InputArg {
    /// RGB on `image`, through the depth model (--weights / --hub).
    Image,
    /// A depth model's raw output on `prediction` (32FC1; its kind is the calibration's), for a
    /// model that runs elsewhere, and for tests without weights.
    Prediction,
}

/// Topic and service names (each remappable with `--remap NAME:=TOPIC`).
#[derive(Debug, Clone)]
pub struct Topics {
    /// Input RGB.
    pub image: String,
    /// Input intrinsics.
    pub camera_info: String,
    /// Input raw prediction (`--input prediction`).
    pub prediction: String,
    /// The depth sensor, for live calibration.
    pub depth_sensor: String,
    /// Output metric depth.
    pub depth: String,
    /// Output point cloud.
    pub points: String,
    /// Output grasp poses.
    pub grasps: String,
    /// Output grasps as `moma grasp --json`.
    pub grasps_json: String,
    /// Output diagnostics.
    pub diagnostics: String,
    /// The live-calibration service.
    pub calibrate: String,
}

impl Default for Topics {
    fn default() -> Self {
        Self {
            image: "image".into(),
            camera_info: "camera_info".into(),
            prediction: "prediction".into(),
            depth_sensor: "depth_sensor".into(),
            depth: "depth".into(),
            points: "points".into(),
            grasps: "grasps".into(),
            grasps_json: "grasps_json".into(),
            // absolute, as diagnostic_updater publishes it: a namespaced node's statuses still
            // reach diagnostic_aggregator
            diagnostics: "/diagnostics".into(),
            calibrate: "calibrate".into(),
        }
    }
}

impl Topics {
    /// The default names with `remaps` (`--remap NAME:=TOPIC`) and `ros`'s rules applied,
    /// resolved in its namespace ([`resolve_topics`]).
    ///
    /// # Errors
    /// As [`resolve_topics`].
    pub fn with_remaps(remaps: &[String], ros: &RosArgs) -> Result<Self> {
        let mut t = Self::default();
        resolve_topics(
            remaps,
            ros,
            &mut [
                ("image", &mut t.image),
                ("camera_info", &mut t.camera_info),
                ("prediction", &mut t.prediction),
                ("depth_sensor", &mut t.depth_sensor),
                ("depth", &mut t.depth),
                ("points", &mut t.points),
                ("grasps", &mut t.grasps),
                ("grasps_json", &mut t.grasps_json),
                ("diagnostics", &mut t.diagnostics),
                ("calibrate", &mut t.calibrate),
            ],
        )?;
        Ok(t)
    }
}

/// `--remap` (`strict`: a name that is not a slot is an error) or `--ros-args -r` (such a
/// name is ignored, as ROS ignores a rule that matches nothing), then the namespace of
/// `--ros-args -r __ns:=` for every relative name: what `moma ros2` and the replay open.
///
/// # Errors
/// A remap without `:=`; with `--remap`, a name that is not a slot; a name ROS refuses.
pub fn resolve_topics(
    remaps: &[String],
    ros: &RosArgs,
    slots: &mut [(&str, &mut String)],
) -> Result<()> {
    remap_slots(remaps, slots, true)?;
    remap_slots(&ros.remaps, slots, false)?;
    for (_, slot) in slots.iter_mut() {
        **slot = in_namespace(slot, &ros.namespace);
    }
    Ok(())
}

fn remap_slots(remaps: &[String], slots: &mut [(&str, &mut String)], strict: bool) -> Result<()> {
    let flag = if strict { "--remap" } else { "--ros-args -r" };
    // ROS applies the first rule that matches a name; --remap, given once per name, the last
    let mut done: Vec<String> = Vec::new();
    for r in remaps {
        let Some((from, to)) = r.split_once(":=") else {
            bail!("{flag} {r:?}: expected NAME:=TOPIC, e.g. image:=/camera/color/image_raw");
        };
        let names: Vec<&str> = slots.iter().map(|(n, _)| *n).collect();
        let from = from.trim();
        if !strict && done.iter().any(|d| d == from) {
            continue;
        }
        let Some((_, slot)) = slots.iter_mut().find(|(n, _)| *n == from) else {
            if !strict {
                continue;
            }
            bail!(
                "--remap {r:?}: no topic or service {from:?} ({})",
                names.join(", ")
            );
        };
        let to = to.trim();
        // checked here, before DDS starts, whether or not the run opens that topic
        dds::topic_name(to).with_context(|| format!("{flag} {r:?}"))?;
        **slot = to.to_string();
        done.push(from.to_string());
    }
    Ok(())
}

/// How often the same camera_info problem is reported again.
const CAMERA_INFO_WARN_EVERY: Duration = Duration::from_secs(5);

/// The node's default name (`--ros-args -r __node:=NAME` renames it).
const NODE_NAME: &str = "moma";

/// DDS settings shared by `moma ros2` and `moma ros2-replay`.
#[derive(Debug, Clone, Args)]
pub struct DdsArgs {
    /// ROS 2 domain id [default: $ROS_DOMAIN_ID, else 0].
    #[arg(long, value_name = "ID")]
    pub domain_id: Option<u16>,
    /// Keep all DDS traffic on the loopback interface (127.0.0.1) [default: on when
    /// $ROS_LOCALHOST_ONLY is 1].
    #[arg(long)]
    pub localhost_only: bool,
    /// ROS 2 arguments, last on the line, as `launch_ros` appends them: `-r FROM:=TO` remaps a
    /// topic (as --remap; a name the node does not have is ignored, as ROS ignores it),
    /// `-r __node:=NAME` and `-r __ns:=/NS` name the node and its namespace (relative topic
    /// names are resolved in it); parameters (`-p`, `--params-file`), `--log-level` and
    /// `--enclave` are ignored with a note.
    #[arg(
        long = "ros-args",
        num_args = 0..,
        allow_hyphen_values = true,
        value_terminator = "--",
        value_name = "ARG"
    )]
    pub ros_args: Option<Vec<String>>,
}

/// What `--ros-args` says ([`DdsArgs::ros`]).
#[derive(Debug, Clone, PartialEq)]
pub struct RosArgs {
    /// Topic remaps `FROM:=TO` for this node (node-specific ones matched to its final name).
    pub remaps: Vec<String>,
    /// The node's name: `__node:=NAME`, else the default.
    pub node: String,
    /// The node's namespace, absolute, without a trailing `/` but for the root `/`.
    pub namespace: String,
}

impl RosArgs {
    /// The node's full name (`/left/cell_a`).
    pub fn full_name(&self) -> String {
        in_namespace(&self.node, &self.namespace)
    }
}

/// Reads ROS 2 command-line arguments (what follows `--ros-args`); `node` is the node's
/// default name. As rcl reads them: `__node` / `__name` and `__ns` first, then the topic
/// rules, a node-specific one (`NODE:FROM:=TO`) kept when NODE is the node's final name; the
/// first rule for a name wins.
///
/// # Errors
/// A flag that needs a value without one, an unknown flag, a node name or namespace ROS
/// refuses.
pub fn parse_ros_args(args: &[String], node: &str) -> Result<RosArgs> {
    let mut rules: Vec<(Option<String>, String, String)> = Vec::new();
    let mut ignored = Vec::new();
    let mut it = args.iter();
    while let Some(a) = it.next() {
        let mut value = |flag: &str| {
            it.next()
                .cloned()
                .with_context(|| format!("--ros-args {flag} needs a value"))
        };
        match a.as_str() {
            "--ros-args" => {}
            "-r" | "--remap" => {
                let rule = value(a)?;
                let Some((from, to)) = rule.split_once(":=") else {
                    bail!("--ros-args -r {rule:?}: expected FROM:=TO");
                };
                let (for_node, from) = match from.split_once(':') {
                    Some((n, f)) => (Some(n.to_string()), f.to_string()),
                    None => (None, from.to_string()),
                };
                rules.push((for_node, from, to.to_string()));
            }
            "-p" | "--param" | "--params-file" | "--log-level" | "-e" | "--enclave"
            | "--log-config-file" | "--log-file-name" => {
                ignored.push(format!("{a} {}", value(a)?));
            }
            "--disable-rosout-logs"
            | "--disable-stdout-logs"
            | "--enable-rosout-logs"
            | "--enable-stdout-logs"
            | "--disable-external-lib-logs" => ignored.push(a.clone()),
            other => bail!(
                "--ros-args: {other:?} is not a ROS 2 argument moma reads (-r FROM:=TO, \
                 -r __node:=NAME, -r __ns:=/NS; parameters, logging and --enclave are ignored; \
                 moma's own options go before --ros-args, or after a --)"
            ),
        }
    }
    let applies =
        |for_node: &Option<String>, name: &str| for_node.as_deref().is_none_or(|n| n == name);
    // the node's name and namespace first (a node-specific rule names the default name)
    let mut out = RosArgs {
        remaps: Vec::new(),
        node: node.to_string(),
        namespace: "/".to_string(),
    };
    let (mut named, mut placed) = (false, false);
    for (for_node, from, to) in &rules {
        if !applies(for_node, node) {
            continue;
        }
        match from.as_str() {
            "__node" | "__name" if !named => {
                out.node = to.clone();
                named = true;
            }
            "__ns" if !placed => {
                out.namespace = to.clone();
                placed = true;
            }
            _ => {}
        }
    }
    out.namespace = check_namespace(&out.namespace)?;
    check_node_name(&out.node)?;
    // then the topic rules of this node (its final name)
    for (for_node, from, to) in &rules {
        if !from.starts_with("__") && applies(for_node, &out.node) {
            out.remaps.push(format!("{from}:={to}"));
        }
    }
    if !ignored.is_empty() {
        eprintln!(
            "note: --ros-args {} ignored: moma takes its settings from its own options (moma \
             ros2 --help)",
            ignored.join(" ")
        );
    }
    Ok(out)
}

/// A namespace as ROS takes it: absolute, `/` the root, a trailing `/` dropped.
fn check_namespace(ns: &str) -> Result<String> {
    if !ns.starts_with('/') {
        bail!("--ros-args -r __ns:={ns}: a namespace is absolute (e.g. /left)");
    }
    let trimmed = ns.trim_end_matches('/');
    if trimmed.is_empty() {
        return Ok("/".to_string());
    }
    dds::topic_name(trimmed).with_context(|| format!("--ros-args -r __ns:={ns}"))?;
    Ok(trimmed.to_string())
}

/// A node name as ROS takes it: one part of letters, digits and `_`, not starting with a digit.
fn check_node_name(name: &str) -> Result<()> {
    let ok = !name.is_empty()
        && !name.starts_with(|c: char| c.is_ascii_digit())
        && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
    if !ok {
        bail!(
            "--ros-args -r __node:={name}: a node name is letters, digits and '_', not starting \
             with a digit"
        );
    }
    Ok(())
}

/// `name` resolved in `namespace`: an absolute name as it is, a relative one under the
/// namespace (`/left` and `depth`: `/left/depth`).
pub fn in_namespace(name: &str, namespace: &str) -> String {
    if name.starts_with('/') {
        name.to_string()
    } else {
        format!("{}/{name}", namespace.trim_end_matches('/'))
    }
}

#[cfg(test)]
mod ros_args_tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<RosArgs> {
        let args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
        parse_ros_args(&args, "moma")
    }

    #[test]
    fn names_and_namespaces_resolve_as_ros_resolves_them() {
        assert_eq!(in_namespace("depth", "/"), "/depth");
        assert_eq!(in_namespace("depth", "/left"), "/left/depth");
        assert_eq!(in_namespace("/diagnostics", "/left"), "/diagnostics");
        // launch_ros gives `__ns:=/` for a launch file's empty namespace
        let root = parse(&["-r", "__ns:=/", "-r", "__node:=cell_a"]).unwrap();
        assert_eq!(
            (root.namespace.as_str(), root.full_name()),
            ("/", "/cell_a".into())
        );
        let left = parse(&["-r", "__ns:=/left/"]).unwrap();
        assert_eq!(left.full_name(), "/left/moma");
        assert_eq!(left.namespace, "/left");
        let e = parse(&["-r", "__ns:=left"]).unwrap_err().to_string();
        assert!(e.contains("a namespace is absolute"), "{e}");
        let e = parse(&["-r", "__node:=cell-a"]).unwrap_err().to_string();
        assert!(e.contains("a node name is letters"), "{e}");
    }

    #[test]
    fn node_specific_rules_follow_the_final_name_and_the_first_rule_wins() {
        let r = parse(&[
            "-r",
            "__node:=cell_a",
            "-r",
            "cell_a:image:=/cam",
            "-r",
            "moma:depth:=/not_for_cell_a",
            "-r",
            "points:=/first",
            "-r",
            "points:=/second",
        ])
        .unwrap();
        assert_eq!(r.node, "cell_a");
        assert_eq!(
            r.remaps,
            ["image:=/cam", "points:=/first", "points:=/second"]
        );
        let mut points = "points".to_string();
        remap_slots(&r.remaps, &mut [("points", &mut points)], false).unwrap();
        assert_eq!(points, "/first");
        // logging is ignored, an unknown flag is not
        assert!(parse(&["--log-level", "info", "--log-file-name", "x"]).is_ok());
        let e = parse(&["--bogus"]).unwrap_err().to_string();
        assert!(e.contains("\"--bogus\" is not a ROS 2 argument"), "{e}");
    }
}

impl DdsArgs {
    /// The `--ros-args` of the node whose default name is `node` (none given: nothing).
    ///
    /// # Errors
    /// As [`parse_ros_args`].
    pub fn ros(&self, node: &str) -> Result<RosArgs> {
        parse_ros_args(self.ros_args.as_deref().unwrap_or_default(), node)
    }

    /// The node `ros` names ([`DdsArgs::ros`]), with these settings.
    ///
    /// # Errors
    /// A domain id out of range in the environment; DDS could not start.
    pub fn node(&self, ros: &RosArgs) -> Result<ros2_client::Node> {
        let domain = match self.domain_id {
            Some(d) => d,
            None => match std::env::var("ROS_DOMAIN_ID") {
                Ok(s) if !s.trim().is_empty() => s
                    .trim()
                    .parse::<u16>()
                    .with_context(|| format!("ROS_DOMAIN_ID={s:?} is not a domain id (0–232)"))?,
                _ => 0,
            },
        };
        if domain > 232 {
            bail!("domain id {domain} is out of range (0–232)");
        }
        let localhost = self.localhost_only
            || std::env::var("ROS_LOCALHOST_ONLY").is_ok_and(|v| v.trim() == "1");
        let network = if localhost {
            Network::Loopback
        } else {
            Network::All
        };
        dds::node(&ros.node, &ros.namespace, domain, network).with_context(|| {
            format!(
                "starting the ROS 2 node {} on domain {domain}",
                ros.full_name()
            )
        })
    }
}

/// Run moma as a ROS 2 node: RGB (or raw predictions) in; metric depth, point cloud, grasps and
/// diagnostics out. No ROS installation is needed (DDS in Rust); any ROS 2 system on the network
/// sees the topics.
///
/// Topics (remap with --remap NAME:=TOPIC): subscribes image, camera_info, prediction
/// (--input prediction), depth_sensor (live calibration); publishes depth (32FC1 metres),
/// points (PointCloud2), grasps (PoseArray) and grasps_json (String, with --gripper),
/// diagnostics; service calibrate (std_srvs/srv/Trigger).
///
/// Examples:
///   moma ros2 --calib calib.json --weights depth_anything_v2_vits.safetensors --gripper suction
///   moma ros2 --calib calib.json --input prediction --realign anchors \
///       --remap image:=/camera/color/image_raw
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
pub struct Ros2Args {
    /// Calibration file from `moma calibrate` (or written by this node's live calibration).
    #[arg(long, value_name = "FILE")]
    pub calib: PathBuf,
    /// Where the live calibration writes its file (atomically) [default: --calib itself].
    #[arg(long, value_name = "FILE")]
    pub calib_out: Option<PathBuf>,
    /// What the node aligns.
    #[arg(long, value_enum, default_value_t = InputArg::Image)]
    pub input: InputArg,
    #[command(flatten)]
    pub model: ModelArgs,
    /// camera.json intrinsics, instead of the calibration's or camera_info's.
    #[arg(long, value_name = "FILE")]
    pub camera: Option<PathBuf>,
    /// Colour the point cloud with the frame's RGB (a packed `rgb` field).
    #[arg(long)]
    pub points_rgb: bool,
    /// Plan grasps for this gripper on every frame (topics grasps and grasps_json).
    #[arg(long, value_enum)]
    pub gripper: Option<GripperArg>,
    #[command(flatten)]
    pub plan: PlanFlags,
    /// Objects to grasp (PNG, nonzero = object; the same mask for every frame: where objects of a
    /// fixed cell may be). A label image (one grey level or colour per object) keeps objects
    /// that touch apart.
    #[arg(long, value_name = "PNG", requires = "gripper")]
    pub mask: Option<PathBuf>,
    /// Camera → robot base transform: grasps are published in the base frame.
    #[arg(long, value_name = "FILE", requires = "gripper")]
    pub extrinsics: Option<PathBuf>,
    /// Frame id of the base frame for grasps with --extrinsics.
    #[arg(long, default_value = "base_link", value_name = "FRAME")]
    pub base_frame: String,
    /// Per-frame re-alignment on static anchors (a calibration made with --anchors): the
    /// frame's RGB (image, or the image of the same stamp with --input prediction).
    #[arg(long, value_enum, value_name = "MODE")]
    pub realign: Option<RealignArg>,
    #[command(flatten)]
    pub realign_flags: RealignFlags,
    /// Live calibration: the method [default: the loaded calibration's].
    #[arg(long, value_name = "METHOD")]
    pub calib_method: Option<Method>,
    /// Live calibration: number of samples [default: 100, `moma calibrate`'s].
    #[arg(long, value_name = "N")]
    pub calib_samples: Option<usize>,
    /// Live calibration: seed of the sampling.
    #[arg(long, default_value_t = 0)]
    pub calib_seed: u64,
    /// Live calibration: how long a request waits for a depth_sensor frame (with its image,
    /// and its prediction with --input prediction) before it fails, seconds.
    #[arg(long, default_value_t = 5.0, value_name = "S")]
    pub calib_timeout_s: f64,
    /// Live calibration: a depth_sensor frame pairs with the image nearest in time within this
    /// many seconds (drivers that stamp depth and colour apart: depthai, Orbbec); 0 pairs only
    /// identical stamps. The prediction (--input prediction) carries the image's stamp.
    #[arg(long, default_value_t = 0.02, value_name = "S")]
    pub calib_sync_slop_s: f64,
    /// With --input prediction: how long a frame waits for the image of the same stamp when
    /// it needs one (--realign, --points-rgb), seconds.
    #[arg(long, default_value_t = 0.5, value_name = "S")]
    pub sync_timeout_s: f64,
    /// Rename a topic or the service: NAME:=TOPIC (repeatable), e.g. image:=/camera/color/image_raw.
    #[arg(long, value_name = "NAME:=TOPIC")]
    pub remap: Vec<String>,
    #[command(flatten)]
    pub dds: DdsArgs,
    /// Stop after this many processed frames (tests, benchmarks); default: run until killed.
    #[arg(long, value_name = "N")]
    pub max_frames: Option<u64>,
    /// Stop after this many seconds (tests); default: run until killed.
    #[arg(long, value_name = "S")]
    pub max_seconds: Option<f64>,
}

impl Ros2Args {
    /// Whether a frame's RGB is used besides the model's input (re-alignment, coloured points).
    fn uses_rgb(&self) -> bool {
        self.realign.is_some() || self.points_rgb
    }
}

/// How many recent messages per input the node keeps to pair topics by stamp.
const PAIR_BUFFER: usize = 8;

/// Per-frame publishers.
struct Outputs {
    depth: Publisher<Image>,
    points: Publisher<PointCloud2>,
    grasps: Publisher<PoseArray>,
    grasps_json: Publisher<StringMsg>,
    diagnostics: Publisher<DiagnosticArray>,
}

/// A frame waiting to be processed.
struct Pending {
    msg: Image,
    received: Instant,
}

/// A calibration request waiting for its RGB-D pair.
struct CalibRequest {
    id: ros2_client::RmwRequestId,
    since: Instant,
}

/// The node's state between frames.
struct NodeState {
    args: Ros2Args,
    calib: CalibrationFile,
    calib_out: PathBuf,
    model: Option<Box<dyn moma_depth::DepthModel>>,
    realign: Option<RealignConfig>,
    camera_override: Option<Intrinsics>,
    camera_info: Option<Intrinsics>,
    /// A `camera_info` with distortion was warned about (once: it comes at camera rate).
    distortion_warned: bool,
    /// The camera_info problems reported, and when (each at most every
    /// [`CAMERA_INFO_WARN_EVERY`]: a driver repeats one at camera rate; and a best-effort status
    /// may be lost, so once is not enough).
    camera_info_warned: Vec<(String, Instant)>,
    /// An input with an empty `frame_id` was warned about (once).
    empty_frame_id_warned: bool,
    grasp: Option<(GraspRequest, Option<Extrinsics>, Option<moma_core::Mask>)>,
    images: VecDeque<Image>,
    predictions: VecDeque<Image>,
    depth_sensor: VecDeque<Image>,
    processed: u64,
    dropped: u64,
    skipped: u64,
}

fn push_bounded(buf: &mut VecDeque<Image>, msg: Image) {
    if buf.len() == PAIR_BUFFER {
        buf.pop_front();
    }
    buf.push_back(msg);
}

fn find_stamp(buf: &VecDeque<Image>, stamp: Time) -> Option<&Image> {
    buf.iter().rev().find(|m| m.header.stamp == stamp)
}

/// `b − a`, nanoseconds.
fn stamp_diff_ns(a: Time, b: Time) -> i64 {
    let ns = |t: Time| i64::from(t.sec) * 1_000_000_000 + i64::from(t.nanosec);
    ns(b) - ns(a)
}

/// The message of `buf` nearest in time to `stamp` within `slop_s` seconds (the newest of
/// equally near ones); with `slop_s` 0 the one of the same stamp.
fn nearest_stamp(buf: &VecDeque<Image>, stamp: Time, slop_s: f64) -> Option<&Image> {
    let slop_ns = (slop_s * 1e9).round() as i64;
    buf.iter()
        .rev()
        .map(|m| (stamp_diff_ns(stamp, m.header.stamp).abs(), m))
        .filter(|(d, _)| *d <= slop_ns)
        .min_by_key(|(d, _)| *d)
        .map(|(_, m)| m)
}

fn kv(key: &str, value: impl ToString) -> KeyValue {
    KeyValue {
        key: key.to_string(),
        value: value.to_string(),
    }
}

/// Takes every sample waiting on `sub`; a sample that does not decode is reported by `bad`.
fn drain<M: 'static + serde::de::DeserializeOwned>(
    sub: &Subscription<M>,
    mut bad: impl FnMut(String),
) -> Vec<M> {
    let mut out = Vec::new();
    loop {
        match sub.take() {
            Ok(Some((m, _))) => out.push(m),
            Ok(None) => break,
            Err(e) => bad(format!("{e:?}")),
        }
    }
    out
}

/// Keeps freed large buffers in the heap for reuse: without it glibc maps every buffer of more
/// than 128 kB afresh, and a frame's messages (1.2 MB depth, 3.7 MB cloud, their CDR copies)
/// page-fault on every frame. 32 MiB is glibc's largest mmap threshold on 64-bit
/// (`HEAP_MAX_SIZE / 2`): a larger value is refused (mallopt returns 0), and the trim threshold
/// alone would switch off glibc's own raising of the mmap threshold, leaving every large buffer
/// mapped afresh.
fn keep_large_buffers() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator thresholds; called before the node's threads start.
    unsafe {
        if libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20) == 1 {
            libc::mallopt(libc::M_TRIM_THRESHOLD, 256 << 20);
        }
    }
}

pub fn run(args: &Ros2Args) -> Result<()> {
    keep_large_buffers();
    let ros = args.dds.ros(NODE_NAME)?;
    let topics = Topics::with_remaps(&args.remap, &ros)?;
    for (flag, v) in [
        ("--calib-timeout-s", args.calib_timeout_s),
        ("--sync-timeout-s", args.sync_timeout_s),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            bail!("{flag} {v} must be a number of seconds >= 0");
        }
    }
    let slop = args.calib_sync_slop_s;
    if !(slop.is_finite() && (0.0..=1.0).contains(&slop)) {
        bail!("--calib-sync-slop-s {slop} must be a number of seconds in [0, 1]");
    }
    let calib = moma_io::read_calibration(&args.calib)?;
    let realign = match args.realign {
        Some(RealignArg::Anchors) => {
            calib
                .calibration
                .anchor_store()
                .with_context(|| format!("--realign anchors with {}", args.calib.display()))?;
            Some(args.realign_flags.config()?)
        }
        None => None,
    };
    let model = match args.input {
        InputArg::Image => {
            let loaded = args.model.load().context(
                "--input image runs the depth model: give --weights or --hub (or use --input \
                 prediction)",
            )?;
            Some(loaded.model)
        }
        InputArg::Prediction => {
            if args.model.weights.is_some() || args.model.hub.is_some() {
                bail!("--input prediction takes no model: drop --weights / --hub");
            }
            None
        }
    };
    let camera_override = args.camera.as_ref().map(moma_io::read_camera).transpose()?;
    if let Some(k) = &camera_override {
        calib
            .image_size
            .expect_eq("camera.json", k.size())
            .with_context(|| {
                format!(
                    "--camera vs calibration {} (one camera)",
                    args.calib.display()
                )
            })?;
    }
    let grasp = match args.gripper {
        None => None,
        Some(g) => {
            let gripper = args.plan.gripper(g)?;
            let request = args.plan.request(
                gripper,
                calib.calibration.frame_error_model(None),
                SceneConfig::default(),
            )?;
            let extrinsics = args
                .extrinsics
                .as_deref()
                .map(super::grasp::read_extrinsics)
                .transpose()?;
            let mask = args
                .mask
                .as_ref()
                .map(|p| moma_io::read_object_mask_sized(p, calib.image_size))
                .transpose()?;
            Some((request, extrinsics, mask))
        }
    };
    if calib.created.simulated_predictions {
        eprintln!(
            "note: {} was fitted on SIMULATED predictions: the depth it gives is not a depth \
             model's",
            args.calib.display()
        );
    }

    let mut node = args.dds.node(&ros)?;
    let node_label = ros.full_name();
    let sensor = dds::sensor_qos();
    let reader = dds::sensor_reader_qos();
    // The image is read on every frame with --input image, --realign or --points-rgb; else (and
    // the depth sensor always) only while a calibration waits for its pair: a camera's 0.6–1 MB
    // frames that the node would drop still cost the DDS thread their reassembly.
    let image_always = args.input == InputArg::Image || args.uses_rgb();
    let image_sub: Option<Subscription<Image>> = if image_always {
        Some(dds::subscription(
            &mut node,
            &topics.image,
            msg::types::image(),
            &reader,
        )?)
    } else {
        None
    };
    let info_sub: Subscription<CameraInfo> = dds::subscription(
        &mut node,
        &topics.camera_info,
        msg::types::camera_info(),
        &reader,
    )?;
    let pred_sub: Option<Subscription<Image>> = match args.input {
        InputArg::Prediction => Some(dds::subscription(
            &mut node,
            &topics.prediction,
            msg::types::image(),
            &reader,
        )?),
        InputArg::Image => None,
    };
    let mut depth_sensor_sub: Option<Subscription<Image>> = None;
    let mut image_sub_calib: Option<Subscription<Image>> = None;
    let outputs = Outputs {
        depth: dds::publisher(&mut node, &topics.depth, msg::types::image(), &sensor)?,
        points: dds::publisher(
            &mut node,
            &topics.points,
            msg::types::point_cloud2(),
            &sensor,
        )?,
        grasps: dds::publisher(&mut node, &topics.grasps, msg::types::pose_array(), &sensor)?,
        grasps_json: dds::publisher(
            &mut node,
            &topics.grasps_json,
            msg::types::string(),
            &sensor,
        )?,
        diagnostics: dds::publisher(
            &mut node,
            &topics.diagnostics,
            msg::types::diagnostic_array(),
            &sensor,
        )?,
    };
    let mut server = dds::trigger_server(&mut node, &topics.calibrate)?;

    let mut poll = Poll::new().context("creating the event poll")?;
    let registry = poll.registry();
    let mut image_sub = image_sub;
    let mut info_sub = info_sub;
    if let Some(s) = image_sub.as_mut() {
        registry.register(s, Token(0), Interest::READABLE)?;
    }
    registry.register(&mut info_sub, Token(1), Interest::READABLE)?;
    registry.register(&mut server, Token(3), Interest::READABLE)?;
    let mut pred_sub = pred_sub;
    if let Some(s) = pred_sub.as_mut() {
        registry.register(s, Token(4), Interest::READABLE)?;
    }

    let calib_out = args.calib_out.clone().unwrap_or_else(|| args.calib.clone());
    let mut state = NodeState {
        args: args.clone(),
        calib,
        calib_out,
        model,
        realign,
        camera_override,
        camera_info: None,
        distortion_warned: false,
        camera_info_warned: Vec::new(),
        empty_frame_id_warned: false,
        grasp,
        images: VecDeque::new(),
        predictions: VecDeque::new(),
        depth_sensor: VecDeque::new(),
        processed: 0,
        dropped: 0,
        skipped: 0,
    };
    eprintln!(
        "moma ros2: node {node_label} on domain {}, input {} on {}, publishing {} and {}{}",
        node.domain_id(),
        match args.input {
            InputArg::Image => "RGB",
            InputArg::Prediction => "predictions",
        },
        match args.input {
            InputArg::Image => &topics.image,
            InputArg::Prediction => &topics.prediction,
        },
        topics.depth,
        topics.points,
        if state.grasp.is_some() {
            format!(", {} and {}", topics.grasps, topics.grasps_json)
        } else {
            String::new()
        }
    );

    let started = Instant::now();
    let mut events = Events::with_capacity(16);
    let mut pending: Option<Pending> = None;
    let mut calib_request: Option<CalibRequest> = None;
    loop {
        if let Some(limit) = args.max_seconds
            && started.elapsed().as_secs_f64() >= limit
        {
            break;
        }
        // SIGINT / SIGTERM / SIGHUP: leave the loop, so that the node is dropped and leaves
        // the DDS domain at once
        if super::common::stop_requested().is_some() {
            break;
        }
        if let Some(n) = args.max_frames
            && state.processed >= n
        {
            break;
        }
        // Wake at least every 20 ms: calibration and pairing time-outs.
        poll.poll(&mut events, Some(Duration::from_millis(20)))
            .context("polling DDS")?;
        let mut malformed = Vec::new();

        // camera_info gives the intrinsics only when neither --camera nor the calibration
        // does: otherwise a bad one (an uncalibrated driver's K = 0, at camera rate) is not an
        // error nor a skipped frame; its distortion is still worth a warning
        let info_used = state.camera_override.is_none() && state.calib.intrinsics.is_none();
        // a camera_info that cannot be used is a warning: no frame is skipped for it (the
        // frames go on as depth only until a good one comes)
        let mut info_problems = Vec::new();
        let infos = drain(&info_sub, |e| {
            if info_used {
                info_problems.push(format!("camera_info: {e}"));
            }
        });
        for info in infos {
            // the node uses the rectified image's intrinsics (P) on the image as it comes: a
            // raw image with distortion has its points and grasps drift off towards the edges
            // (docs/ros2.md, "Frames and units")
            if !state.distortion_warned && info.d.iter().any(|&c| c != 0.0) {
                state.distortion_warned = true;
                state.diagnose(
                    &outputs,
                    Some(&info.header),
                    DiagnosticStatus::WARN,
                    &format!(
                        "camera_info has {} distortion coefficients ({}) that moma does not \
                         undo: it uses the rectified image's intrinsics (P), right for a \
                         rectified image (image_proc's image_rect) and wrong towards the edges \
                         of a raw one",
                        info.distortion_model,
                        info.d.len()
                    ),
                    Vec::new(),
                );
            }
            if !info_used {
                continue;
            }
            match convert::camera_info_to_intrinsics(&info) {
                Ok(k) if k.size() == state.calib.image_size => state.camera_info = Some(k),
                Ok(k) => info_problems.push(format!(
                    "camera_info is for {} images, the calibration for {}: ignored",
                    k.size(),
                    state.calib.image_size
                )),
                Err(e) => info_problems.push(format!("camera_info ignored: {e}")),
            }
        }
        for e in info_problems {
            let seen = state.camera_info_warned.iter().position(|(m, _)| *m == e);
            let due = match seen {
                Some(i) => state.camera_info_warned[i].1.elapsed() >= CAMERA_INFO_WARN_EVERY,
                None => state.camera_info_warned.len() < 16,
            };
            if due {
                state.diagnose(&outputs, None, DiagnosticStatus::WARN, &e, Vec::new());
                match seen {
                    Some(i) => state.camera_info_warned[i].1 = Instant::now(),
                    None => state.camera_info_warned.push((e, Instant::now())),
                }
            }
        }
        // Recent messages are kept (bounded) only where a pairing by stamp needs them: the
        // frame's image with --input prediction when the RGB is used, and everything while a
        // calibration waits for its pair (which must come after the request).
        let calibrating = calib_request.is_some();
        let keep_images = calibrating || (args.input == InputArg::Prediction && args.uses_rgb());
        let now = Instant::now();
        let image_source = image_sub.as_ref().or(image_sub_calib.as_ref());
        let images = image_source
            .map(|sub| drain(sub, |e| malformed.push(format!("image: {e}"))))
            .unwrap_or_default();
        let mut newest = |msg: Image, dropped: &mut u64| {
            if pending.replace(Pending { msg, received: now }).is_some() {
                *dropped += 1;
            }
        };
        for m in images {
            match (args.input, keep_images) {
                (InputArg::Image, true) => {
                    push_bounded(&mut state.images, m.clone());
                    newest(m, &mut state.dropped);
                }
                (InputArg::Image, false) => newest(m, &mut state.dropped),
                (InputArg::Prediction, true) => push_bounded(&mut state.images, m),
                (InputArg::Prediction, false) => {}
            }
        }
        if let Some(sub) = &pred_sub {
            for m in drain(sub, |e| malformed.push(format!("prediction: {e}"))) {
                if calibrating {
                    push_bounded(&mut state.predictions, m.clone());
                }
                newest(m, &mut state.dropped);
            }
        }
        let depth_frames = depth_sensor_sub
            .as_ref()
            .map(|sub| drain(sub, |e| malformed.push(format!("depth_sensor: {e}"))))
            .unwrap_or_default();
        for m in depth_frames {
            if calibrating {
                push_bounded(&mut state.depth_sensor, m);
            }
        }
        for e in malformed {
            state.skipped += 1;
            state.diagnose(&outputs, None, DiagnosticStatus::ERROR, &e, Vec::new());
        }

        // Live calibration.
        loop {
            match server.receive_request() {
                Ok(Some((id, _req))) => {
                    if calib_request.is_some() {
                        let _ = server.send_response(
                            id,
                            TriggerResponse {
                                success: false,
                                message: "a calibration is already waiting for its frame".into(),
                            },
                        );
                        continue;
                    }
                    calib_request = Some(CalibRequest {
                        id,
                        since: Instant::now(),
                    });
                    // Subscribed while the request waits (drained every turn, not polled).
                    depth_sensor_sub = Some(dds::subscription(
                        &mut node,
                        &topics.depth_sensor,
                        msg::types::image(),
                        &reader,
                    )?);
                    if image_sub.is_none() {
                        image_sub_calib = Some(dds::subscription(
                            &mut node,
                            &topics.image,
                            msg::types::image(),
                            &reader,
                        )?);
                    }
                }
                Ok(None) => break,
                Err(e) => {
                    state.diagnose(
                        &outputs,
                        None,
                        DiagnosticStatus::ERROR,
                        &format!("calibrate request: {e:?}"),
                        Vec::new(),
                    );
                    break;
                }
            }
        }
        if let Some(req) = &calib_request
            && let Some(response) = state.try_calibrate(req, &outputs)
            && let Some(req) = calib_request.take()
        {
            let _ = server.send_response(req.id, response);
            // The pairing buffers and subscriptions are for the next request's frames only.
            state.predictions.clear();
            state.depth_sensor.clear();
            depth_sensor_sub = None;
            image_sub_calib = None;
        }

        // The newest frame.
        if let Some(p) = pending.take() {
            match state.process(&p, &outputs) {
                Step::Done => state.processed += 1,
                Step::Skipped => state.skipped += 1,
                Step::Wait => pending = Some(p),
            }
        }
    }
    eprintln!(
        "moma ros2: stopped after {} frames ({} dropped as stale, {} skipped)",
        state.processed, state.dropped, state.skipped
    );
    Ok(())
}

/// What became of a frame.
enum Step {
    Done,
    Skipped,
    /// Waiting for the image of the same stamp.
    Wait,
}

impl NodeState {
    /// Publishes one diagnostic status (with the frame's header when there is one).
    fn diagnose(
        &self,
        out: &Outputs,
        header: Option<&Header>,
        level: u8,
        message: &str,
        mut values: Vec<KeyValue>,
    ) {
        if level != DiagnosticStatus::OK {
            eprintln!("moma ros2: {message}");
        }
        values.extend([
            kv("frames_processed", self.processed),
            kv("frames_dropped_stale", self.dropped),
            kv("frames_skipped", self.skipped),
        ]);
        // a status of no frame (camera_info, a calibration's time-out) is stamped now
        let header = header.cloned().unwrap_or_else(|| Header {
            stamp: super::ros2_replay::now_stamp(),
            frame_id: String::new(),
        });
        let status = DiagnosticStatus {
            level,
            name: "moma: frame".into(),
            message: message.to_string(),
            hardware_id: header.frame_id.clone(),
            values,
        };
        let _ = dds::publish(
            &out.diagnostics,
            DiagnosticArray {
                header,
                status: vec![status],
            },
        );
    }

    /// The intrinsics for points and grasps: --camera, the calibration's, then camera_info.
    fn intrinsics(&self) -> Option<Intrinsics> {
        self.camera_override
            .or(self.calib.intrinsics)
            .or(self.camera_info)
    }

    /// The frame's RGB: the input image, or the image of the same stamp.
    fn rgb_for(&self, frame: &Image) -> Option<std::result::Result<image::RgbImage, String>> {
        let img = match self.args.input {
            InputArg::Image => Some(frame),
            InputArg::Prediction => find_stamp(&self.images, frame.header.stamp),
        }?;
        Some(convert::image_to_rgb(img).map_err(|e| format!("image: {e}")))
    }

    fn process(&mut self, p: &Pending, out: &Outputs) -> Step {
        let header = p.msg.header.clone();
        let needs_rgb = self.args.uses_rgb();
        let rgb = if needs_rgb || self.args.input == InputArg::Image {
            match self.rgb_for(&p.msg) {
                Some(Ok(rgb)) => Some(rgb),
                Some(Err(e)) => {
                    self.diagnose(
                        out,
                        Some(&header),
                        DiagnosticStatus::ERROR,
                        &format!("frame skipped: {e}"),
                        Vec::new(),
                    );
                    return Step::Skipped;
                }
                None if p.received.elapsed().as_secs_f64() < self.args.sync_timeout_s => {
                    return Step::Wait;
                }
                None => {
                    let why = format!(
                        "frame skipped: no image of the same stamp within {} s (needed for {})",
                        self.args.sync_timeout_s,
                        if self.realign.is_some() {
                            "--realign"
                        } else {
                            "--points-rgb"
                        }
                    );
                    self.diagnose(
                        out,
                        Some(&header),
                        DiagnosticStatus::ERROR,
                        &why,
                        Vec::new(),
                    );
                    return Step::Skipped;
                }
            }
        } else {
            None
        };
        match self.align_and_publish(p, rgb, out) {
            Ok(()) => Step::Done,
            Err(e) => {
                let why = format!("frame skipped: {}", crate::error_chain(&e));
                self.diagnose(
                    out,
                    Some(&header),
                    DiagnosticStatus::ERROR,
                    &why,
                    Vec::new(),
                );
                Step::Skipped
            }
        }
    }

    /// The frame's prediction: the model's on the RGB, or the received map.
    fn prediction(&mut self, msg: &Image, rgb: Option<&image::RgbImage>) -> Result<Prediction> {
        match (&mut self.model, rgb) {
            (Some(model), Some(rgb)) => {
                let size = moma_core::ImageSize::new(rgb.width() as usize, rgb.height() as usize);
                self.calib
                    .image_size
                    .expect_eq("image", size)
                    .context("the image vs the calibration (one camera)")?;
                let pred = model.predict(rgb).context("the depth model")?;
                Ok(pred)
            }
            _ => {
                let mut values = convert::image_to_f32(msg).context("prediction")?;
                // a metric depth image marks "no measurement" by NaN (REP 118; ±inf: beyond
                // the range): moma's metric prediction marks it by 0, which aligns to no depth
                // (a relative prediction has a value at every pixel: NaN stays an error)
                if self.calib.prediction_kind == moma_core::PredictionKind::MetricDepth {
                    values.mapv_inplace(|v| if v.is_finite() { v } else { 0.0 });
                }
                let pred = Prediction::new(values, self.calib.prediction_kind);
                self.calib
                    .image_size
                    .expect_eq("prediction", pred.size())
                    .context("the prediction vs the calibration (one camera)")?;
                Ok(pred)
            }
        }
    }

    fn align_and_publish(
        &mut self,
        p: &Pending,
        rgb: Option<image::RgbImage>,
        out: &Outputs,
    ) -> Result<()> {
        let header = p.msg.header.clone();
        // the outputs carry the input's frame id: an empty one leaves rviz and tf nothing to
        // place them by (said once)
        // (in the frame's own status: a second status published at once could replace it in
        // the best-effort writer's history of one before it leaves)
        let frame_id_note =
            (header.frame_id.is_empty() && !self.empty_frame_id_warned).then(|| {
                self.empty_frame_id_warned = true;
                "the input's frame_id is empty: depth, points and grasps carry none (rviz and tf \
             cannot place them; set the camera driver's frame, e.g. camera_color_optical_frame)"
            });
        let t_model = Instant::now();
        let prediction = self.prediction(&p.msg, rgb.as_ref())?;
        let model_ms = if self.model.is_some() {
            Some(t_model.elapsed().as_secs_f64() * 1e3)
        } else {
            None
        };
        let grey = match (&self.realign, &rgb) {
            (Some(_), Some(rgb)) => Some(super::common::grey_of(rgb)?),
            _ => None,
        };
        let options = AlignOptions {
            realign: grey.as_ref().zip(self.realign.as_ref()),
            sigma_map: false,
        };
        let t_align = Instant::now();
        let aligned = self
            .calib
            .calibration
            .aligned(&prediction, &options)
            .context("aligning")?;
        let align_ms = t_align.elapsed().as_secs_f64() * 1e3;
        let intrinsics = self.intrinsics();
        let colours = rgb.as_ref().filter(|_| self.args.points_rgb);
        // The cloud is built on a second thread while this one publishes the depth: the two
        // overlap on the second core (docs/ros2.md, "Performance"); the points are published
        // after the depth, from this thread, as before.
        let (depth, cloud_header) = (&aligned.depth, header.clone());
        let (depth_ms, cloud) = std::thread::scope(|scope| {
            let cloud = intrinsics.map(|k| {
                scope.spawn(move || {
                    let t_cloud = Instant::now();
                    convert::depth_to_cloud(depth, &k, colours, cloud_header)
                        .map(|c| (c, t_cloud.elapsed().as_secs_f64() * 1e3))
                })
            });
            let published =
                dds::publish(&out.depth, convert::depth_to_image(depth, header.clone()));
            let depth_ms = p.received.elapsed().as_secs_f64() * 1e3;
            let cloud = cloud.map(|h| {
                h.join()
                    .map_err(|_| anyhow::anyhow!("the point-cloud thread panicked"))
            });
            published.map(|()| (depth_ms, cloud))
        })?;

        let mut values = vec![
            kv("latency_depth_ms", format!("{depth_ms:.3}")),
            kv("align_ms", format!("{align_ms:.3}")),
            kv("valid_pixels", aligned.depth.valid_count()),
        ];
        if let Some(ms) = model_ms {
            values.push(kv("model_ms", format!("{ms:.1}")));
        }
        if let Some(r) = &aligned.realign {
            values.extend([
                kv("realign_accepted", r.accepted),
                kv("realign_anchors", r.anchors),
                kv("realign_reason", &r.reason),
            ]);
        }
        let mut level = DiagnosticStatus::OK;
        let mut message = "ok".to_string();
        match intrinsics.zip(cloud) {
            Some((k, cloud)) => {
                let (cloud, cloud_ms) = cloud??;
                dds::publish(&out.points, cloud)?;
                values.push(kv("cloud_ms", format!("{cloud_ms:.3}")));
                values.push(kv(
                    "latency_points_ms",
                    format!("{:.3}", p.received.elapsed().as_secs_f64() * 1e3),
                ));
                if let Some((request, extrinsics, mask)) = &self.grasp {
                    let t = Instant::now();
                    // the error model of this frame's depth (re-aligned: its own background
                    // error), as `moma grasp` plans with it
                    let mut request = request.clone();
                    if request.error_model.is_some() {
                        request.error_model = aligned.error_model.clone();
                    }
                    let published = publish_grasps(
                        &aligned.depth,
                        &k,
                        &request,
                        extrinsics.as_ref(),
                        mask.as_ref(),
                        &header,
                        &self.args.base_frame,
                        out,
                    )?;
                    values.push(kv("grasps", published.grasps));
                    values.push(kv(
                        "grasp_ms",
                        format!("{:.1}", t.elapsed().as_secs_f64() * 1e3),
                    ));
                    if let Some(why) = published.no_grasp_reason {
                        values.push(kv("no_grasp_reason", why));
                    }
                    // what the planner left out (not a fault: a cell's frame edge or its bin)
                    for (key, note) in published.notes {
                        values.push(kv(key, note));
                    }
                }
            }
            None => {
                level = DiagnosticStatus::WARN;
                message = "no intrinsics (calibrate with --camera, give --camera, or publish \
                           camera_info): depth only, no points or grasps"
                    .to_string();
            }
        }
        if aligned.realign.as_ref().is_some_and(|r| !r.accepted) {
            level = level.max(DiagnosticStatus::WARN);
            message = "re-alignment not accepted (one-shot depth published)".to_string();
        }
        if let Some(note) = &aligned.normalisation_note {
            level = level.max(DiagnosticStatus::WARN);
            message = format!("{note}; {message}");
        }
        if let Some(note) = frame_id_note {
            level = level.max(DiagnosticStatus::WARN);
            message = format!("{note}; {message}");
        }
        self.diagnose(out, Some(&header), level, &message, values);
        Ok(())
    }

    /// Answers a waiting calibration request when its RGB-D pair is there (or it timed out).
    fn try_calibrate(&mut self, req: &CalibRequest, out: &Outputs) -> Option<TriggerResponse> {
        // Only frames received since the request are buffered: the pair is the next one.
        let pair = self.depth_sensor.iter().rev().find_map(|d| {
            let img = nearest_stamp(&self.images, d.header.stamp, self.args.calib_sync_slop_s)?;
            let pred = match self.args.input {
                InputArg::Prediction => {
                    Some(find_stamp(&self.predictions, img.header.stamp)?.clone())
                }
                InputArg::Image => None,
            };
            Some((d.clone(), img.clone(), pred))
        });
        let Some((depth_msg, image_msg, pred_msg)) = pair else {
            if req.since.elapsed().as_secs_f64() >= self.args.calib_timeout_s {
                // what did arrive: none at all (a topic not published, or remapped wrong), or
                // frames whose stamps are apart (a driver's clocks)
                let nearest_s = self
                    .depth_sensor
                    .iter()
                    .flat_map(|d| {
                        self.images.iter().map(move |i| {
                            (stamp_diff_ns(d.header.stamp, i.header.stamp) as f64 * 1e-9).abs()
                        })
                    })
                    .min_by(f64::total_cmp);
                let arrived = match nearest_s {
                    Some(apart) => format!(
                        "; {} depth_sensor frame(s) and {} image(s) arrived, the nearest {:.3} s \
                         apart",
                        self.depth_sensor.len(),
                        self.images.len(),
                        apart
                    ),
                    None => format!(
                        "; {} depth_sensor frame(s) and {} image(s) arrived",
                        self.depth_sensor.len(),
                        self.images.len()
                    ),
                };
                let why = format!(
                    "calibration failed: no {} frame with an image{} of the same stamp (within \
                     --calib-sync-slop-s {} s) within {} s{arrived}",
                    "depth_sensor",
                    if self.args.input == InputArg::Prediction {
                        " and a prediction"
                    } else {
                        ""
                    },
                    self.args.calib_sync_slop_s,
                    self.args.calib_timeout_s
                );
                self.diagnose(out, None, DiagnosticStatus::ERROR, &why, Vec::new());
                return Some(TriggerResponse {
                    success: false,
                    message: why,
                });
            }
            return None;
        };
        let header = depth_msg.header.clone();
        let result = self.calibrate_on(&depth_msg, &image_msg, pred_msg.as_ref());
        Some(match result {
            Ok(text) => {
                self.diagnose(out, Some(&header), DiagnosticStatus::OK, &text, Vec::new());
                TriggerResponse {
                    success: true,
                    message: text,
                }
            }
            Err(e) => {
                let why = format!("calibration failed: {}", crate::error_chain(&e));
                self.diagnose(
                    out,
                    Some(&header),
                    DiagnosticStatus::ERROR,
                    &why,
                    Vec::new(),
                );
                TriggerResponse {
                    success: false,
                    message: why,
                }
            }
        })
    }

    fn calibrate_on(
        &mut self,
        depth: &Image,
        image: &Image,
        pred: Option<&Image>,
    ) -> Result<String> {
        // the depth is compared with the image pixel by pixel: it must be registered to it
        // (unregistered depth of the same size calibrated wrong metres without a word)
        let (df, imf) = (&depth.header.frame_id, &image.header.frame_id);
        if !df.is_empty() && !imf.is_empty() && df != imf {
            bail!(
                "depth_sensor is in frame '{df}' but the image in '{imf}': the depth must be \
                 registered to the colour image (e.g. realsense-ros aligned_depth_to_color)"
            );
        }
        let gt = convert::depth_image_to_metres(depth).context("depth_sensor")?;
        // the units, as every reader of depth checks them: a calibration on millimetres given
        // as metres (32FC1), or metres written as millimetres (16UC1), would switch the node to
        // depth 1 000 × off
        match moma_core::unit_mistake(gt.depth_m.view()) {
            None => {}
            Some(moma_core::UnitMistake::Millimetres(median)) => bail!(
                "depth_sensor: median depth {median} m looks like millimetres (32FC1 depth is \
                 metres, 16UC1 millimetres)"
            ),
            Some(moma_core::UnitMistake::TooNear(median)) => bail!(
                "depth_sensor: median depth {:.1} mm: no scene a camera grasps in is that near \
                 (16UC1 depth is millimetres, 32FC1 metres: metres written as millimetres?)",
                f64::from(median) * 1e3
            ),
        }
        let rgb = convert::image_to_rgb(image).context("image")?;
        let prediction = match pred {
            Some(p) => self.prediction(p, None)?,
            None => self.prediction(image, Some(&rgb))?,
        };
        prediction
            .size()
            .expect_eq("depth_sensor", gt.size())
            .context("the depth sensor vs the image")?;
        let intrinsics = self.intrinsics();
        let method = match &self.args.calib_method {
            Some(m) => m.clone(),
            None => Method::with_defaults(self.calib.method),
        };
        let calibration = super::calibrate::fit_frame(
            &prediction,
            &gt,
            Some(&rgb),
            intrinsics,
            method,
            self.args
                .calib_samples
                .unwrap_or(moma_core::sampling::SamplingConfig::default().n),
            self.args.calib_seed,
            Some(&self.calib.calibration),
        )?;
        let mut created = CreationInfo::now();
        created.simulated_predictions = self.calib.created.simulated_predictions;
        let stamp = depth.header.stamp;
        let created = created.with_source(
            "live calibration (moma ros2)",
            format!(
                "depth_sensor frame stamped {}.{:09}",
                stamp.sec, stamp.nanosec
            ),
        );
        let file = CalibrationFile::new(calibration, intrinsics, created);
        moma_io::write_calibration(&self.calib_out, &file)?;
        let apart_ns = stamp_diff_ns(stamp, image.header.stamp);
        let apart = if apart_ns == 0 {
            String::new()
        } else {
            format!(" (the image {:+.1} ms from it)", apart_ns as f64 * 1e-6)
        };
        // a robust fit is not repeated: say so where the calibration replaced was one
        let least_squares = if self.calib.calibration.report.robust.is_some() {
            " (least squares: the robust fit of the calibration it replaces is not repeated)"
        } else {
            ""
        };
        let notes: String = file
            .calibration
            .normalisation_notes
            .iter()
            .map(|n| format!("; note: {n}"))
            .collect();
        let text = format!(
            "calibrated {} on {} samples (RMS residual {:.2} mm, normalisation {}){least_squares} \
             from the frame stamped {}.{:09}{apart}; wrote {} and switched to it{notes}",
            file.method,
            file.calibration.report.n_used,
            file.calibration.report.rms_residual_m * 1e3,
            file.calibration.normalisation.method,
            stamp.sec,
            stamp.nanosec,
            self.calib_out.display()
        );
        eprintln!("moma ros2: {text}");
        if let Some((request, _, _)) = &mut self.grasp {
            request.error_model = file.calibration.frame_error_model(None);
        }
        self.calib = file;
        Ok(text)
    }
}

/// What [`publish_grasps`] planned: the number of grasps, why there are none, and the scene's
/// notes (regions left out at the image border or as a container's walls, as `moma grasp`
/// notes them).
struct Published {
    grasps: usize,
    no_grasp_reason: Option<String>,
    notes: Vec<(&'static str, String)>,
}

/// Plans on `depth` and publishes the poses and the JSON.
#[allow(clippy::too_many_arguments)]
fn publish_grasps(
    depth: &MetricDepth,
    k: &Intrinsics,
    request: &GraspRequest,
    extrinsics: Option<&Extrinsics>,
    mask: Option<&moma_core::Mask>,
    header: &Header,
    base_frame: &str,
    out: &Outputs,
) -> Result<Published> {
    let (scene, mut outcome) =
        moma_grasp::plan_grasps(depth, k, mask, request).context("grasps")?;
    let mut pose_header = header.clone();
    if let Some(e) = extrinsics {
        outcome.set_base(e);
        pose_header.frame_id = base_frame.to_string();
    }
    let poses = convert::grasps_to_pose_array(&outcome.grasps, extrinsics.is_some(), pose_header)?;
    dds::publish(&out.grasps, poses)?;
    let json = serde_json::to_string(&outcome.grasps).context("grasps as JSON")?;
    dds::publish(&out.grasps_json, StringMsg { data: json })?;
    Ok(Published {
        grasps: outcome.grasps.len(),
        no_grasp_reason: outcome.no_grasp_reason.map(|r| r.to_string()),
        notes: scene.notes(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A table 0.7 m below the camera with a 40 mm box on it; the first 12 rows 15 mm nearer,
    /// as a sensor's depth curls along a frame's edge: that band touches the border and is left
    /// out, which the frame's diagnostics say under `border_note` with `moma grasp`'s text.
    #[test]
    fn the_regions_the_planner_leaves_out_are_diagnostic_values() {
        let k = Intrinsics {
            width: 320,
            height: 240,
            fx: 300.0,
            fy: 300.0,
            cx: 159.5,
            cy: 119.5,
        };
        let depth = |curl: bool| {
            MetricDepth::new(ndarray::Array2::from_shape_fn((240, 320), |(v, u)| {
                let on_box = (130..190).contains(&u) && (95..145).contains(&v);
                let lift = if curl && v < 12 { 0.015 } else { 0.0 };
                if on_box { 0.66 } else { 0.70 - lift }
            }))
        };
        let config = moma_grasp::SceneConfig::default();
        let clean = moma_grasp::Scene::build(&depth(false), &k, None, &config).unwrap();
        assert!(clean.notes().is_empty());
        let curled = moma_grasp::Scene::build(&depth(true), &k, None, &config).unwrap();
        let notes = curled.notes();
        assert_eq!(
            notes,
            vec![("border_note", curled.border_note().unwrap())],
            "{notes:?}"
        );
        assert!(notes[0].1.contains("1 region(s)"), "{notes:?}");
    }

    fn at(sec: i32, nanosec: u32) -> Image {
        Image {
            header: Header {
                stamp: Time { sec, nanosec },
                frame_id: format!("{sec}.{nanosec}"),
            },
            ..Image::default()
        }
    }

    #[test]
    fn the_live_calibration_pairs_the_nearest_image_within_the_slop() {
        // images at 10.000, 10.030, 10.060 s; depth at 10.032 s
        let buf: VecDeque<Image> = [at(10, 0), at(10, 30_000_000), at(10, 60_000_000)].into();
        let depth = Time {
            sec: 10,
            nanosec: 32_000_000,
        };
        let id = |m: Option<&Image>| m.map(|m| m.header.frame_id.clone());
        assert_eq!(
            id(nearest_stamp(&buf, depth, 0.02)),
            Some("10.30000000".into())
        );
        // 2 ms apart is outside a 1 ms slop; 0 pairs identical stamps only
        assert_eq!(id(nearest_stamp(&buf, depth, 0.001)), None);
        assert_eq!(id(nearest_stamp(&buf, depth, 0.0)), None);
        let exact = Time {
            sec: 10,
            nanosec: 60_000_000,
        };
        assert_eq!(
            id(nearest_stamp(&buf, exact, 0.0)),
            Some("10.60000000".into())
        );
        // across a second boundary, both signs
        let next = Time {
            sec: 11,
            nanosec: 5_000_000,
        };
        assert_eq!(stamp_diff_ns(next, buf[2].header.stamp), -945_000_000);
        assert_eq!(
            id(nearest_stamp(&buf, next, 1.0)),
            Some("10.60000000".into())
        );
    }
}
