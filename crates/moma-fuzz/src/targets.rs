//! The fuzz targets: one parser entry point each, on bytes in memory.

use moma_core::AlignOptions;
use std::path::Path;

/// A parser under test.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Target {
    /// `moma_io::png16_from_bytes`: uint16 depth PNGs (millimetres).
    DepthPng,
    /// `moma_io::npy_f32_from_bytes`: float depth / prediction `.npy`.
    Npy,
    /// `moma_io::pfm_from_bytes`: float depth / prediction PFM.
    Pfm,
    /// `moma_io::mask_from_bytes`: mask PNGs (any pixel type).
    Mask,
    /// `moma_io::rgb_from_bytes`: RGB images (PNG or JPEG).
    Rgb,
    /// `moma_io::parse_camera`: `camera.json`.
    Camera,
    /// `moma_io::parse_calibration`: calibration files.
    Calibration,
    /// A calibration file parsed, then used: a prediction of its size and kind aligned, and,
    /// when it holds an anchor store, re-aligned with every correction form. A file that parses
    /// must never make the alignment panic or write infinite metres.
    CalibrationApply,
    /// `moma_depth::weights_limits::check_safetensors_header`: the input's first 8 bytes are the
    /// claimed file length (u64 little-endian), the rest the start of the file.
    Safetensors,
    /// `moma_io::parse_json::<ExtrinsicsFile>` then `moma_grasp::Extrinsics::new` (rigidity):
    /// `moma grasp --extrinsics`.
    Extrinsics,
    /// `moma_io::parse_json` of a parallel-jaw and of a suction-cup configuration, then their
    /// validation: `moma grasp --gripper-config`.
    Gripper,
    /// A `sensor_msgs/msg/Image` RTPS payload decoded (`moma_ros2::msg::from_cdr_payload`), then
    /// converted as `moma ros2` converts what it receives: as a colour image, a prediction and a
    /// depth sensor's image.
    Ros2Image,
    /// A `sensor_msgs/msg/CameraInfo` RTPS payload decoded, then its intrinsics checked.
    Ros2CameraInfo,
}

impl Target {
    /// Every target, in the order `all` runs them.
    pub const ALL: [Target; 13] = [
        Target::DepthPng,
        Target::Npy,
        Target::Pfm,
        Target::Mask,
        Target::Rgb,
        Target::Camera,
        Target::Calibration,
        Target::CalibrationApply,
        Target::Safetensors,
        Target::Extrinsics,
        Target::Gripper,
        Target::Ros2Image,
        Target::Ros2CameraInfo,
    ];

    /// The target's name on the command line and in findings.
    pub fn name(self) -> &'static str {
        match self {
            Target::DepthPng => "depth-png",
            Target::Npy => "npy",
            Target::Pfm => "pfm",
            Target::Mask => "mask",
            Target::Rgb => "rgb",
            Target::Camera => "camera-json",
            Target::Calibration => "calibration-json",
            Target::CalibrationApply => "calibration-apply",
            Target::Safetensors => "safetensors-header",
            Target::Extrinsics => "extrinsics-json",
            Target::Gripper => "gripper-json",
            Target::Ros2Image => "ros2-image",
            Target::Ros2CameraInfo => "ros2-camera-info",
        }
    }

    /// The target called `name`.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|t| t.name() == name)
    }

    /// Whether inputs are JSON documents (they also get structure-aware mutations).
    pub fn is_json(self) -> bool {
        matches!(
            self,
            Target::Camera
                | Target::Calibration
                | Target::CalibrationApply
                | Target::Extrinsics
                | Target::Gripper
        )
    }

    /// Whether inputs are PNG files (their chunk CRCs are repaired after mutation, most of the time).
    pub fn is_png(self) -> bool {
        matches!(self, Target::DepthPng | Target::Mask | Target::Rgb)
    }

    /// Runs the parser on `data`. Returns `Ok` when it accepted the input and `Err(message)` when
    /// it refused it: both are fine; only a panic, an abort or a hang is a finding.
    ///
    /// # Errors
    /// The parser's error message.
    pub fn run(self, data: &[u8]) -> Result<(), String> {
        let name = |ext: &str| Path::new("fuzz-input").with_extension(ext);
        let text = || std::str::from_utf8(data).map_err(|e| format!("not UTF-8: {e}"));
        let s = |e: &dyn std::fmt::Display| e.to_string();
        match self {
            Target::DepthPng => moma_io::png16_from_bytes(&name("png"), data)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::Npy => moma_io::npy_f32_from_bytes(&name("npy"), data)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::Pfm => moma_io::pfm_from_bytes(&name("pfm"), data)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::Mask => moma_io::mask_from_bytes(&name("png"), data)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::Rgb => moma_io::rgb_from_bytes(&name("png"), data)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::Camera => moma_io::parse_camera(&name("json"), text()?)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::Calibration => moma_io::parse_calibration(&name("json"), text()?)
                .map(drop)
                .map_err(|e| s(&e)),
            Target::CalibrationApply => apply_calibration(&name("json"), text()?),
            Target::Extrinsics => {
                let f: moma_io::ExtrinsicsFile =
                    moma_io::parse_json(&name("json"), text()?).map_err(|e| s(&e))?;
                moma_grasp::Extrinsics::new(f.camera_to_base)
                    .map(drop)
                    .map_err(|e| s(&e))
            }
            Target::Gripper => {
                let t = text()?;
                let jaw = moma_io::parse_json::<moma_grasp::ParallelJaw>(&name("json"), t)
                    .map_err(|e| s(&e))
                    .and_then(|j| j.validate().map_err(|e| s(&e)));
                let cup = moma_io::parse_json::<moma_grasp::SuctionCup>(&name("json"), t)
                    .map_err(|e| s(&e))
                    .and_then(|c| c.validate().map_err(|e| s(&e)));
                jaw.or(cup)
            }
            Target::Ros2Image => {
                let img: moma_ros2::msg::Image =
                    moma_ros2::msg::from_cdr_payload(data).map_err(|e| s(&e))?;
                let rgb = moma_ros2::convert::image_to_rgb(&img).map(drop);
                let pred = moma_ros2::convert::image_to_f32(&img).map(drop);
                let depth = moma_ros2::convert::depth_image_to_metres(&img).map(drop);
                rgb.or(pred).or(depth).map_err(|e| s(&e))
            }
            Target::Ros2CameraInfo => {
                let info: moma_ros2::msg::CameraInfo =
                    moma_ros2::msg::from_cdr_payload(data).map_err(|e| s(&e))?;
                moma_ros2::convert::camera_info_to_intrinsics(&info)
                    .map(drop)
                    .map_err(|e| s(&e))
            }
            Target::Safetensors => {
                let (len, prefix) = data.split_at_checked(8).ok_or("shorter than 8 bytes")?;
                let mut n = [0u8; 8];
                n.copy_from_slice(len);
                let file_len = u64::from_le_bytes(n);
                moma_depth::weights_limits::check_safetensors_header(
                    &name("safetensors"),
                    prefix,
                    file_len,
                )
                .map(drop)
                .map_err(|e| s(&e))
            }
        }
    }
}

/// Largest calibration image [`Target::CalibrationApply`] aligns, pixels: a parsed file may
/// claim up to `MAX_IMAGE_PIXELS`, and aligning that for every input would stall the fuzzer.
pub const APPLY_MAX_PIXELS: usize = 64 * 64;

/// [`Target::CalibrationApply`]: parse, align a prediction of the calibration's size and kind
/// (a ramp with one 0), and re-align it when the file holds an anchor store.
fn apply_calibration(path: &Path, text: &str) -> Result<(), String> {
    use moma_core::realign::{CorrectionModel, RealignConfig};
    let s = |e: &dyn std::fmt::Display| e.to_string();
    let file = moma_io::parse_calibration(path, text).map_err(|e| s(&e))?;
    let c = &file.calibration;
    let size = c.image_size();
    if size.pixels() > APPLY_MAX_PIXELS {
        return Ok(());
    }
    let (h, w) = (size.height, size.width);
    // A ramp with one 0 (an inverse-depth model's "infinitely far"); non-finite predictions are
    // refused before any model runs, so they would test nothing here.
    let values = ndarray::Array2::from_shape_fn((h, w), |(v, u)| {
        if (u, v) == (1, 0) {
            0.0
        } else {
            0.5 + 0.01 * u as f32 + 0.02 * v as f32
        }
    });
    let pred = moma_core::Prediction::new(values, c.prediction_kind);
    let no_inf = |d: &moma_core::MetricDepth, what: &str| {
        if let Some(z) = d.depth_m.iter().find(|z| z.is_infinite()) {
            panic!("{what} wrote {z} metres");
        }
    };
    let depth = c
        .aligned(&pred, &AlignOptions::default())
        .map(|a| a.depth)
        .map_err(|e| s(&e))?;
    no_inf(&depth, "align");
    if c.anchors.is_some() {
        let rgb = ndarray::Array3::from_shape_fn((h, w, 3), |(v, u, ch)| {
            (100 + (u * 7 + v * 3 + ch * 11) % 60) as u8
        });
        let grey = moma_io::grey_half(rgb.view()).map_err(|e| s(&e))?;
        for model in [
            CorrectionModel::ScaleShift,
            CorrectionModel::Planar,
            CorrectionModel::PredictionAffine,
        ] {
            let config = RealignConfig {
                model,
                ..Default::default()
            };
            // A refusal (e.g. a store without the normalised prediction) is fine; a panic is not.
            if let Ok(a) = c.aligned(&pred, &AlignOptions::realigned(&grey, &config)) {
                no_inf(&a.depth, "re-alignment");
            }
        }
    }
    Ok(())
}
