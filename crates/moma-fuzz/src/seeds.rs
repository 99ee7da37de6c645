//! Seed corpora: small files generated in code by the current moma-io writers, and real files
//! read from `$MOMA_SHARED_DIR` at run time (never copied into the repository).

use std::path::{Path, PathBuf};

use moma_core::align::Method;
use moma_core::pipeline::CalibrationConfig;
use moma_core::{Intrinsics, Mask, MetricDepth, Prediction, PredictionKind};
use ndarray::Array2;

use crate::targets::Target;

/// One seed file.
#[derive(Debug, Clone)]
pub struct Seed {
    /// Where it came from (`generated:NAME` or the path it was read from).
    pub origin: String,
    /// Its bytes.
    pub data: Vec<u8>,
}

/// The seeds of one target.
#[derive(Debug, Clone, Default)]
pub struct Corpus {
    /// Generated in code (small; picked most of the time).
    pub generated: Vec<Seed>,
    /// Real files from the shared data (picked less often: they are large and slow to decode).
    pub shared: Vec<Seed>,
}

impl Corpus {
    /// All seeds.
    pub fn all(&self) -> impl Iterator<Item = &Seed> {
        self.generated.iter().chain(&self.shared)
    }

    /// Number of seeds.
    pub fn len(&self) -> usize {
        self.generated.len() + self.shared.len()
    }

    /// Whether there is no seed.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Builds the corpus of `target`: generated seeds (written to a temporary directory by moma-io's
/// writers and read back as bytes), plus real files under `shared` (`$MOMA_SHARED_DIR`) when given.
///
/// # Errors
/// A generated seed that cannot be written (a temporary directory problem).
pub fn corpus(target: Target, shared: Option<&Path>) -> anyhow::Result<Corpus> {
    let dir = tempfile::tempdir()?;
    let generated = generated(target, dir.path())?;
    let shared = match shared {
        Some(root) => shared_seeds(target, root),
        None => vec![],
    };
    Ok(Corpus { generated, shared })
}

fn gen_seed(name: &str, path: &Path) -> anyhow::Result<Seed> {
    Ok(Seed {
        origin: format!("generated:{name}"),
        data: std::fs::read(path)?,
    })
}

fn bytes_seed(name: &str, data: Vec<u8>) -> Seed {
    Seed {
        origin: format!("generated:{name}"),
        data,
    }
}

fn depth_map(h: usize, w: usize) -> MetricDepth {
    MetricDepth::new(Array2::from_shape_fn((h, w), |(v, u)| {
        if (u + v) % 5 == 4 {
            f32::NAN
        } else {
            0.4 + 0.01 * (u as f32) + 0.03 * (v as f32)
        }
    }))
}

/// An npy v1.0 file with a hand-written header (what numpy writes), then `data`.
fn npy(descr: &str, fortran: bool, shape: &str, data: &[u8]) -> Vec<u8> {
    let f = if fortran { "True" } else { "False" };
    let mut dict = format!("{{'descr': '{descr}', 'fortran_order': {f}, 'shape': {shape}, }}");
    while (10 + dict.len() + 1) % 64 != 0 {
        dict.push(' ');
    }
    dict.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out.extend_from_slice(data);
    out
}

/// A small scene for the calibration seeds: a tilted table (metres) with a box standing on it
/// and a hole, the RGB to match (the box darker), and a prediction of kind `kind` with a smooth
/// distortion, so that the local variants, `auto` and the robust fits have something to fit.
fn calibration_scene(
    h: usize,
    w: usize,
    kind: PredictionKind,
    frame: usize,
) -> (MetricDepth, Prediction, ndarray::Array3<u8>) {
    let on_box = |v: usize, u: usize| (8..16).contains(&v) && (10 + frame..20 + frame).contains(&u);
    let gt = MetricDepth::new(Array2::from_shape_fn((h, w), |(v, u)| {
        if v == 2 && u == 3 {
            f32::NAN
        } else if on_box(v, u) {
            0.55 + 0.001 * u as f32
        } else {
            0.6 + 0.004 * u as f32 + 0.002 * v as f32
        }
    }));
    let bump = |v: usize, u: usize| 1.0 + 0.02 * ((u as f32 * 0.3).sin() + (v as f32 * 0.2).cos());
    let pred = Prediction::new(
        Array2::from_shape_fn((h, w), |(v, u)| {
            let z = if gt.depth_m[[v, u]].is_finite() {
                gt.depth_m[[v, u]] * bump(v, u)
            } else {
                0.7
            };
            match kind {
                PredictionKind::RelativeDisparity => 1.0 / z - 0.4,
                _ => 1.1 * z,
            }
        }),
        kind,
    );
    let rgb = ndarray::Array3::from_shape_fn((h, w, 3), |(v, u, c)| {
        let base = if on_box(v, u) { 60 } else { 150 };
        (base + (u * 3 + v * 2 + c * 17) % 40) as u8
    });
    (gt, pred, rgb)
}

/// One calibration seed: a method calibrated on [`calibration_scene`].
struct SeedCase {
    /// Seed name (`calib-NAME.json`).
    name: String,
    /// Method name ([`Method::NAMES`]).
    method: &'static str,
    /// Prediction kind.
    kind: PredictionKind,
    /// Robust fit, if any.
    robust: Option<moma_core::align::robust::RobustKind>,
    /// Calibration frames (few-shot when > 1).
    frames: usize,
    /// Whether the file holds an anchor store.
    anchors: bool,
}

fn calibration_seeds(dir: &Path) -> anyhow::Result<Vec<Seed>> {
    use moma_core::align::robust::{Robust, RobustKind};
    use moma_core::pipeline::{CalibrationFrame, calibrate};
    let (h, w) = (24, 32);
    let k = Intrinsics {
        width: w,
        height: h,
        fx: 30.0,
        fy: 30.0,
        cx: 16.0,
        cy: 12.0,
    };
    let inverse = PredictionKind::RelativeDisparity;
    let case = |name: &str, method: &'static str, kind, robust, frames, anchors| SeedCase {
        name: name.to_string(),
        method,
        kind,
        robust,
        frames,
        anchors,
    };
    let mut cases: Vec<SeedCase> = Method::NAMES
        .iter()
        .filter(|m| **m != "raw")
        .map(|m| case(m, m, inverse, None, 1, false))
        .collect();
    cases.extend([
        case(
            "gssa-depth",
            "gssa",
            PredictionKind::MetricDepth,
            None,
            1,
            false,
        ),
        case(
            "raw-depth",
            "raw",
            PredictionKind::MetricDepth,
            None,
            1,
            false,
        ),
        case(
            "ssra-huber",
            "ssra",
            inverse,
            Some(RobustKind::Huber),
            1,
            false,
        ),
        case(
            "ssra-local-ransac",
            "ssra-local",
            inverse,
            Some(RobustKind::Ransac),
            1,
            false,
        ),
        case(
            "gssa-local-tukey",
            "gssa-local",
            inverse,
            Some(RobustKind::Tukey),
            1,
            false,
        ),
        case("ssra-3-frames", "ssra", inverse, None, 3, false),
        case("gssa-anchors", "gssa", inverse, None, 1, true),
        case("ssra-local-anchors", "ssra-local", inverse, None, 1, true),
    ]);
    let mut seeds = vec![];
    for SeedCase {
        name,
        method,
        kind,
        robust,
        frames: n_frames,
        anchors,
    } in cases
    {
        let method: Method = method
            .parse()
            .map_err(|e| anyhow::anyhow!("{method}: {e}"))?;
        let raw = matches!(method, Method::Raw);
        let config = CalibrationConfig {
            method: method.with_intrinsics(Some(k)),
            normalisation: moma_core::NormalisationConfig::native(
                if raw {
                    moma_core::Normalisation::None
                } else {
                    moma_core::Normalisation::Minmax
                },
                kind,
            ),
            sampling: moma_core::sampling::SamplingConfig {
                n: 60,
                ..Default::default()
            },
            robust: robust.map(Robust::new),
            workspace: None,
        };
        let scenes: Vec<_> = (0..n_frames)
            .map(|f| calibration_scene(h, w, kind, f))
            .collect();
        let frames: Vec<_> = scenes
            .iter()
            .map(|(gt, pred, _)| CalibrationFrame::new(pred, gt))
            .collect();
        let mut calibration =
            calibrate(&frames, &config).map_err(|e| anyhow::anyhow!("seed {name}: {e}"))?;
        if anchors {
            let (gt, pred, rgb) = &scenes[0];
            let grey =
                moma_io::grey_half(rgb.view()).map_err(|e| anyhow::anyhow!("seed {name}: {e}"))?;
            calibration = calibration
                .with_anchors(&grey, gt, pred)
                .map_err(|e| anyhow::anyhow!("seed {name}: {e}"))?;
        }
        let file =
            moma_io::CalibrationFile::new(calibration, Some(k), moma_io::CreationInfo::now());
        let p = dir.join(format!("calib-{name}.json"));
        moma_io::write_calibration(&p, &file)?;
        seeds.push(gen_seed(&format!("calib-{name}.json"), &p)?);
    }
    Ok(seeds)
}

fn generated(target: Target, dir: &Path) -> anyhow::Result<Vec<Seed>> {
    let p = |name: &str| dir.join(name);
    let mut seeds = vec![];
    match target {
        Target::DepthPng | Target::Mask => {
            for (name, h, w) in [("depth-3x2.png", 2, 3), ("depth-16x9.png", 9, 16)] {
                moma_io::write_depth(p(name), &depth_map(h, w))?;
                seeds.push(gen_seed(name, &p(name))?);
            }
            if target == Target::Mask {
                let mask = Mask::new(Array2::from_shape_fn((5, 7), |(v, u)| (u * v) % 3 == 0));
                moma_io::write_mask(p("mask.png"), &mask)?;
                seeds.push(gen_seed("mask.png", &p("mask.png"))?);
                let rgb = image::RgbImage::from_fn(6, 4, |x, y| {
                    image::Rgb([x as u8 * 40, y as u8 * 60, 0])
                });
                moma_io::write_rgb(p("rgb.png"), &rgb)?;
                seeds.push(gen_seed("rgb.png", &p("rgb.png"))?);
            }
        }
        Target::Rgb => {
            let rgb =
                image::RgbImage::from_fn(6, 4, |x, y| image::Rgb([x as u8 * 40, y as u8 * 60, 99]));
            for name in ["rgb.png", "rgb.jpg"] {
                moma_io::write_rgb(p(name), &rgb)?;
                seeds.push(gen_seed(name, &p(name))?);
            }
            let mask = Mask::new(Array2::from_shape_fn((3, 5), |(v, u)| u > v));
            moma_io::write_mask(p("mask.png"), &mask)?;
            seeds.push(gen_seed("mask.png", &p("mask.png"))?);
        }
        Target::Npy => {
            moma_io::write_npy_f32(p("d.npy"), depth_map(2, 3).depth_m.view())?;
            seeds.push(gen_seed("f4-2x3.npy", &p("d.npy"))?);
            let f8: Vec<u8> = (0..4)
                .flat_map(|i| (0.5 + f64::from(i)).to_le_bytes())
                .collect();
            seeds.push(bytes_seed(
                "f8-1x2x2.npy",
                npy("<f8", false, "(1, 2, 2)", &f8),
            ));
            let f4: Vec<u8> = (0..6)
                .flat_map(|i| (1.0 + i as f32).to_be_bytes())
                .collect();
            seeds.push(bytes_seed(
                "f4be-fortran-3x2.npy",
                npy(">f4", true, "(3, 2)", &f4),
            ));
            seeds.push(bytes_seed(
                "i4-2x1x1.npy",
                npy("<i4", false, "(2, 1, 1)", &[1, 0, 0, 0, 2, 0, 0, 0]),
            ));
        }
        Target::Pfm => {
            let m = depth_map(3, 4).depth_m;
            moma_io::write_pfm(p("le.pfm"), m.view(), moma_io::PfmByteOrder::LittleEndian)?;
            seeds.push(gen_seed("le-4x3.pfm", &p("le.pfm"))?);
            moma_io::write_pfm(p("be.pfm"), m.view(), moma_io::PfmByteOrder::BigEndian)?;
            seeds.push(gen_seed("be-4x3.pfm", &p("be.pfm"))?);
        }
        Target::Camera => {
            let k = seed_intrinsics();
            moma_io::write_camera(p("camera.json"), &k)?;
            seeds.push(gen_seed("camera.json", &p("camera.json"))?);
        }
        Target::Calibration | Target::CalibrationApply => seeds.extend(calibration_seeds(dir)?),
        Target::Extrinsics => {
            let m = [
                [0.0, -1.0, 0.0, 0.4],
                [-1.0, 0.0, 0.0, 0.1],
                [0.0, 0.0, -1.0, 0.9],
                [0.0, 0.0, 0.0, 1.0],
            ];
            moma_io::write_extrinsics(p("extrinsics.json"), &m)?;
            seeds.push(gen_seed("extrinsics.json", &p("extrinsics.json"))?);
        }
        Target::Gripper => {
            moma_io::write_json(p("parallel.json"), &moma_grasp::ParallelJaw::default())?;
            seeds.push(gen_seed("parallel.json", &p("parallel.json"))?);
            moma_io::write_json(p("suction.json"), &moma_grasp::SuctionCup::default())?;
            seeds.push(gen_seed("suction.json", &p("suction.json"))?);
        }
        Target::Ros2Image => {
            use moma_ros2::convert::{depth_to_mm_image, f32_to_image, rgb_to_image};
            use moma_ros2::msg::{Header, to_cdr_payload};
            let h = || Header {
                stamp: moma_ros2::msg::Time { sec: 1, nanosec: 2 },
                frame_id: "camera_optical_frame".into(),
            };
            let rgb = image::RgbImage::from_fn(3, 2, |u, v| image::Rgb([u as u8, v as u8, 9]));
            let mut bgr = rgb_to_image(&rgb, h());
            bgr.encoding = "bgr8".into();
            let depth = depth_map(3, 2);
            for (name, msg) in [
                ("rgb8-3x2.cdr", rgb_to_image(&rgb, h())),
                ("bgr8-3x2.cdr", bgr),
                ("32fc1-3x2.cdr", f32_to_image(&depth.depth_m, h())),
                ("16uc1-3x2.cdr", depth_to_mm_image(&depth, h())),
            ] {
                seeds.push(bytes_seed(name, to_cdr_payload(&msg)?));
            }
        }
        Target::Ros2CameraInfo => {
            let k = seed_intrinsics();
            let info = moma_ros2::convert::intrinsics_to_camera_info(&k, Default::default());
            seeds.push(bytes_seed(
                "camera-info.cdr",
                moma_ros2::msg::to_cdr_payload(&info)?,
            ));
        }
        Target::Safetensors => {
            let header = r#"{"__metadata__":{"format":"pt"},"a.weight":{"dtype":"F32","shape":[2,2],"data_offsets":[0,16]},"a.bias":{"dtype":"F16","shape":[2],"data_offsets":[16,20]}}"#;
            let file_len = 8 + header.len() as u64 + 20;
            let mut b = file_len.to_le_bytes().to_vec();
            b.extend_from_slice(&(header.len() as u64).to_le_bytes());
            b.extend_from_slice(header.as_bytes());
            seeds.push(bytes_seed("tiny.safetensors-header", b));
        }
    }
    Ok(seeds)
}

/// The intrinsics of the `camera.json` and `CameraInfo` seeds.
fn seed_intrinsics() -> Intrinsics {
    Intrinsics {
        width: 640,
        height: 480,
        fx: 525.0,
        fy: 525.5,
        cx: 319.5,
        cy: 239.5,
    }
}

/// Frames per set used as seeds (the first ones, in name order).
const SHARED_FRAMES_PER_SET: usize = 2;

fn read_seed(path: PathBuf) -> Option<Seed> {
    let data = std::fs::read(&path).ok()?;
    Some(Seed {
        origin: path.display().to_string(),
        data,
    })
}

fn sorted_dirs(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|r| {
            r.filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.is_dir())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

/// Real files under `root` (`$MOMA_SHARED_DIR`): the moma sets in `data/` and the Depth Anything
/// reference files in `reference/dav2/`.
fn shared_seeds(target: Target, root: &Path) -> Vec<Seed> {
    let sets = sorted_dirs(&root.join("data"));
    let frame_files = |names: &[&str]| -> Vec<Seed> {
        sets.iter()
            .flat_map(|set| {
                sorted_dirs(&set.join("frames"))
                    .into_iter()
                    .take(SHARED_FRAMES_PER_SET)
            })
            .flat_map(|frame| names.iter().map(move |n| frame.join(n)).collect::<Vec<_>>())
            .filter_map(read_seed)
            .collect()
    };
    let dav2 = root.join("reference/dav2");
    match target {
        Target::DepthPng => frame_files(&["depth.png", "raw_depth.png"]),
        Target::Mask => frame_files(&["mask.png"]),
        Target::Rgb => frame_files(&["rgb.png"]).into_iter().take(2).collect(),
        Target::Camera => sets
            .iter()
            .filter_map(|s| read_seed(s.join("camera.json")))
            .collect(),
        Target::Npy => [
            "tiny-metric-392.output_net.npy",
            "tiny-metric.output_full.npy",
        ]
        .iter()
        .filter_map(|n| read_seed(dav2.join(n)))
        .collect(),
        Target::Pfm
        | Target::Calibration
        | Target::CalibrationApply
        | Target::Extrinsics
        | Target::Gripper
        | Target::Ros2Image
        | Target::Ros2CameraInfo => vec![],
        Target::Safetensors => ["tiny-metric.safetensors", "tiny-metric-392.safetensors"]
            .iter()
            .filter_map(|n| {
                let seed = read_seed(dav2.join(n))?;
                let n = u64::from_le_bytes(seed.data.get(..8)?.try_into().ok()?);
                let end = usize::try_from(8 + n).ok()?.min(seed.data.len());
                let mut data = (seed.data.len() as u64).to_le_bytes().to_vec();
                data.extend_from_slice(&seed.data[..end]);
                Some(Seed {
                    origin: format!("{} (header)", seed.origin),
                    data,
                })
            })
            .collect(),
    }
}
