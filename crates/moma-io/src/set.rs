//! The "moma set" layout: one fixed camera, many RGB-D frames.
//!
//! ```text
//! SET/
//!   camera.json              {"width","height","fx","fy","cx","cy"} (pixels)
//!   README.md                optional: origin, licence, notes
//!   frames/ID/rgb.png        8-bit RGB (required)
//!   frames/ID/depth.png      uint16 millimetres, 0 = no measurement (required, ground truth)
//!   frames/ID/mask.png       optional: objects to evaluate (nonzero = inside); absent = whole image
//!   frames/ID/raw_depth.png  optional: what the depth sensor saw (transparent-object sets)
//! ```

use std::path::{Path, PathBuf};

use image::RgbImage;
use moma_core::{ImageSize, Intrinsics, Mask, MetricDepth};

use crate::atomic::{atomic_write, write_err};
use crate::camera::{read_camera, write_camera};
use crate::depth::{DepthWriteStats, read_depth_sized, write_depth};
use crate::error::{IoError, Result};
use crate::raster::{read_mask_sized, read_rgb_sized, rgb_size, write_mask, write_rgb};

/// File name of the intrinsics in a set directory.
pub const CAMERA_FILE: &str = "camera.json";
/// Directory holding one sub-directory per frame.
pub const FRAMES_DIR: &str = "frames";
/// Per-frame RGB image.
pub const RGB_FILE: &str = "rgb.png";
/// Per-frame ground-truth depth (uint16 mm).
pub const DEPTH_FILE: &str = "depth.png";
/// Per-frame evaluation mask (optional).
pub const MASK_FILE: &str = "mask.png";
/// Per-frame raw sensor depth (optional, uint16 mm).
pub const RAW_DEPTH_FILE: &str = "raw_depth.png";

/// One frame of a moma set: its id and the paths of its files. Loaders check every image against
/// the set's camera size.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Frame id: the name of its directory under `frames/`.
    pub id: String,
    /// The frame directory.
    pub dir: PathBuf,
    /// `rgb.png`.
    pub rgb: PathBuf,
    /// `depth.png` (ground truth, uint16 mm).
    pub depth: PathBuf,
    /// `mask.png`, when present.
    pub mask: Option<PathBuf>,
    /// `raw_depth.png`, when present.
    pub raw_depth: Option<PathBuf>,
    /// Image size from the set's `camera.json`, pixels.
    pub size: ImageSize,
}

impl Frame {
    /// Loads the ground-truth depth in metres (0 mm → `NaN`).
    ///
    /// # Errors
    /// Unreadable/corrupt file; [`IoError::SizeMismatch`] against `camera.json`.
    pub fn load_depth(&self) -> Result<MetricDepth> {
        read_depth_sized(&self.depth, self.size)
    }

    /// Loads the RGB image (8-bit).
    ///
    /// # Errors
    /// Unreadable/corrupt file; [`IoError::SizeMismatch`] against `camera.json`.
    pub fn load_rgb(&self) -> Result<RgbImage> {
        read_rgb_sized(&self.rgb, self.size)
    }

    /// Loads the evaluation mask, `None` when the frame has none.
    ///
    /// # Errors
    /// Unreadable/corrupt file; [`IoError::SizeMismatch`] against `camera.json`.
    pub fn load_mask(&self) -> Result<Option<Mask>> {
        self.mask
            .as_ref()
            .map(|p| read_mask_sized(p, self.size))
            .transpose()
    }

    /// Loads the evaluation mask, or a full mask (whole image) when the frame has none.
    ///
    /// # Errors
    /// As [`Frame::load_mask`].
    pub fn load_mask_or_full(&self) -> Result<Mask> {
        Ok(self.load_mask()?.unwrap_or_else(|| Mask::full(self.size)))
    }

    /// Loads the raw sensor depth in metres, `None` when the frame has none.
    ///
    /// # Errors
    /// Unreadable/corrupt file; [`IoError::SizeMismatch`] against `camera.json`.
    pub fn load_raw_depth(&self) -> Result<Option<MetricDepth>> {
        self.raw_depth
            .as_ref()
            .map(|p| read_depth_sized(p, self.size))
            .transpose()
    }

    /// Path of any other file in the frame directory (e.g. a cached prediction), whether or not it exists.
    pub fn file(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }
}

/// An opened moma set: the camera and the frames, sorted by id.
#[derive(Debug, Clone, PartialEq)]
pub struct MomaSet {
    /// The set directory.
    pub root: PathBuf,
    /// Intrinsics from `camera.json` (validated).
    pub camera: Intrinsics,
    /// Frames sorted by id (byte-wise string order, as Python's `sorted`).
    pub frames: Vec<Frame>,
}

impl MomaSet {
    /// Opens a set directory: reads `camera.json` and lists `frames/*/` (hidden entries and plain
    /// files under `frames/` are ignored). No image is decoded here; use the [`Frame`] loaders.
    ///
    /// # Errors
    /// [`IoError::Invalid`] when the directory, `camera.json` or `frames/` is missing, when
    /// `frames/` holds no frame, or when a frame lacks `depth.png` or `rgb.png`; any
    /// [`crate::read_camera`] error.
    pub fn open(root: impl AsRef<Path>) -> Result<Self> {
        let root = root.as_ref().to_path_buf();
        if !root.is_dir() {
            return Err(IoError::invalid(&root, "moma set directory does not exist"));
        }
        let camera_path = root.join(CAMERA_FILE);
        if !camera_path.is_file() {
            return Err(IoError::invalid(
                &root,
                format!(
                    "not a moma set: '{CAMERA_FILE}' is missing (expected at {})",
                    camera_path.display()
                ),
            ));
        }
        let camera = read_camera(&camera_path)?;
        let frames_dir = root.join(FRAMES_DIR);
        if !frames_dir.is_dir() {
            return Err(IoError::invalid(
                &root,
                format!("not a moma set: directory '{FRAMES_DIR}/' is missing"),
            ));
        }
        let entries =
            std::fs::read_dir(&frames_dir).map_err(|e| IoError::io(&frames_dir, "list", e))?;
        let mut frames = Vec::new();
        for entry in entries {
            let entry = entry.map_err(|e| IoError::io(&frames_dir, "list", e))?;
            let dir = entry.path();
            let id = entry.file_name().to_string_lossy().into_owned();
            if id.starts_with('.') || !dir.is_dir() {
                continue;
            }
            let depth = dir.join(DEPTH_FILE);
            if !depth.is_file() {
                return Err(IoError::invalid(
                    &dir,
                    format!("frame '{id}' has no ground-truth depth '{DEPTH_FILE}'"),
                ));
            }
            let rgb = dir.join(RGB_FILE);
            if !rgb.is_file() {
                return Err(IoError::invalid(
                    &dir,
                    format!("frame '{id}' has no '{RGB_FILE}'"),
                ));
            }
            let optional = |name: &str| Some(dir.join(name)).filter(|p| p.is_file());
            frames.push(Frame {
                mask: optional(MASK_FILE),
                raw_depth: optional(RAW_DEPTH_FILE),
                id,
                rgb,
                depth,
                size: camera.size(),
                dir,
            });
        }
        if frames.is_empty() {
            return Err(IoError::invalid(
                &frames_dir,
                "moma set has no frames (no sub-directory in frames/)",
            ));
        }
        frames.sort_by(|a, b| a.id.cmp(&b.id));
        Ok(Self {
            root,
            camera,
            frames,
        })
    }

    /// The image size from `camera.json`, pixels.
    pub fn size(&self) -> ImageSize {
        self.camera.size()
    }

    /// The frame with id `id`.
    pub fn frame(&self, id: &str) -> Option<&Frame> {
        self.frames.iter().find(|f| f.id == id)
    }

    /// The set's name: its directory name.
    pub fn name(&self) -> String {
        self.root
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| self.root.display().to_string())
    }
}

/// The name a set folder is loaded with ([`LoadedSet::name`]): its folder's name, links and
/// relative parts resolved (`.` or a link named otherwise gives the real folder's name); the
/// path as written when it does not resolve.
pub fn loaded_set_name(root: &Path) -> String {
    let real = root.canonicalize().unwrap_or_else(|_| root.to_path_buf());
    real.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| root.display().to_string())
}

/// One frame of a [`LoadedSet`], in memory. Invalid depth is `NaN`, as [`crate::read_depth`]
/// returns it (the one convention of moma; [`moma_core::is_valid_depth`] also accepts 0 as
/// invalid for maps made elsewhere).
#[derive(Debug, Clone)]
pub struct LoadedFrame {
    /// Frame id (its directory name).
    pub id: String,
    /// 8-bit RGB, when loaded or generated.
    pub rgb: Option<RgbImage>,
    /// Ground-truth depth, metres.
    pub gt: MetricDepth,
    /// Evaluation mask (objects), when the frame has one.
    pub mask: Option<Mask>,
    /// Raw sensor depth, metres, when the frame has one.
    pub raw_depth: Option<MetricDepth>,
}

/// A whole moma set in memory: what the evaluation visits once per seed and method.
#[derive(Debug, Clone)]
pub struct LoadedSet {
    /// Set name (its directory name).
    pub name: String,
    /// Directory it was loaded from (or will be written to).
    pub dir: PathBuf,
    /// Camera intrinsics, pixels.
    pub intrinsics: Intrinsics,
    /// Frames in id order.
    pub frames: Vec<LoadedFrame>,
}

impl LoadedSet {
    /// What the frames' masks mean for an evaluation, when it is not that every frame has one:
    /// `None` then. A frame without `mask.png` is scored over the whole image, which beside
    /// masked frames is rarely meant (a mask lost in a copy): the note names those frames.
    pub fn mask_note(&self) -> Option<String> {
        let without: Vec<&str> = self
            .frames
            .iter()
            .filter(|f| f.mask.is_none())
            .map(|f| f.id.as_str())
            .collect();
        match without.len() {
            0 => None,
            n if n == self.frames.len() => Some(format!(
                "{}: no frame has a {MASK_FILE}: every frame is scored over the whole image",
                self.name
            )),
            n => Some(format!(
                "{}: {n} of {} frames have no {MASK_FILE} and are scored over the whole image, \
                 the others inside their masks: {}",
                self.name,
                self.frames.len(),
                without.join(", ")
            )),
        }
    }
}

impl MomaSet {
    /// Loads every frame's images into memory.
    ///
    /// # Errors
    /// Any read error, naming the file.
    pub fn load(&self) -> Result<LoadedSet> {
        let frames = self
            .frames
            .iter()
            .map(|f| {
                Ok(LoadedFrame {
                    id: f.id.clone(),
                    rgb: Some(f.load_rgb()?),
                    gt: f.load_depth()?,
                    mask: f.load_mask()?,
                    raw_depth: f.load_raw_depth()?,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(LoadedSet {
            name: loaded_set_name(&self.root),
            dir: self.root.clone(),
            intrinsics: self.camera,
            frames,
        })
    }
}

impl LoadedSet {
    /// Opens and loads the set at `dir` ([`MomaSet::open`] + [`MomaSet::load`]).
    ///
    /// # Errors
    /// As those.
    pub fn open(dir: impl AsRef<Path>) -> Result<Self> {
        MomaSet::open(dir)?.load()
    }

    /// The image size, pixels.
    pub fn size(&self) -> ImageSize {
        self.intrinsics.size()
    }

    /// Index of the frame with id `id`.
    pub fn frame_index(&self, id: &str) -> Option<usize> {
        self.frames.iter().position(|f| f.id == id)
    }

    /// Writes the set in the moma set layout at `dir` (a mid-grey RGB where a frame has none).
    ///
    /// # Errors
    /// Any write error, naming the file.
    pub fn write(&self, dir: impl AsRef<Path>) -> Result<()> {
        let writer = MomaSetWriter::create(dir, &self.intrinsics)?;
        let size = self.size();
        let placeholder =
            RgbImage::from_pixel(size.width as u32, size.height as u32, image::Rgb([128; 3]));
        for f in &self.frames {
            writer.write_frame(
                &f.id,
                FrameData {
                    rgb: f.rgb.as_ref().unwrap_or(&placeholder),
                    depth: &f.gt,
                    mask: f.mask.as_ref(),
                    raw_depth: f.raw_depth.as_ref(),
                },
            )?;
        }
        Ok(())
    }
}

/// One frame's content for [`MomaSetWriter::write_frame`]; all images must have the camera size.
#[derive(Debug, Clone, Copy)]
pub struct FrameData<'a> {
    /// 8-bit RGB.
    pub rgb: &'a RgbImage,
    /// Ground-truth depth, metres (written as uint16 mm).
    pub depth: &'a MetricDepth,
    /// Evaluation mask (written as 0/255).
    pub mask: Option<&'a Mask>,
    /// Raw sensor depth, metres.
    pub raw_depth: Option<&'a MetricDepth>,
}

/// Writes a moma set (e.g. a generated demo scene) in the layout [`MomaSet::open`] reads.
/// Every file is written atomically.
#[derive(Debug, Clone)]
pub struct MomaSetWriter {
    root: PathBuf,
    camera: Intrinsics,
}

impl MomaSetWriter {
    /// Creates `root` and `root/frames/` (parents included; existing directories are reused)
    /// and writes `camera.json`.
    ///
    /// # Errors
    /// Invalid intrinsics; directories or file not creatable.
    pub fn create(root: impl AsRef<Path>, camera: &Intrinsics) -> Result<Self> {
        let root = root.as_ref().to_path_buf();
        let frames = root.join(FRAMES_DIR);
        std::fs::create_dir_all(&frames)
            .map_err(|e| IoError::io(&frames, "create directory", e))?;
        write_camera(root.join(CAMERA_FILE), camera)?;
        Ok(Self {
            root,
            camera: *camera,
        })
    }

    /// The set directory.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Writes `README.md` (origin, licence, notes).
    ///
    /// # Errors
    /// File not writable.
    pub fn write_readme(&self, text: &str) -> Result<()> {
        let path = self.root.join("README.md");
        atomic_write(&path, |w| {
            w.write_all(text.as_bytes()).map_err(write_err(&path))
        })
    }

    /// Writes frame `id` (its directory is created): `rgb.png`, `depth.png` (uint16 mm) and the
    /// optional `mask.png` / `raw_depth.png`. Returns the statistics of the depth PNG
    /// (pixels not representable in millimetres are written as 0, see [`crate::write_depth`]).
    ///
    /// # Errors
    /// [`IoError::Invalid`] for an id that is empty, starts with `.` or holds a path separator;
    /// [`IoError::SizeMismatch`] when an image differs from the camera size; write errors.
    pub fn write_frame(&self, id: &str, data: FrameData<'_>) -> Result<DepthWriteStats> {
        let dir = self.root.join(FRAMES_DIR).join(id);
        if id.is_empty() || id.starts_with('.') || id.contains(['/', '\\']) {
            return Err(IoError::invalid(&dir, format!("invalid frame id '{id}'")));
        }
        let size = self.camera.size();
        IoError::expect_size(&dir.join(RGB_FILE), size, rgb_size(data.rgb))?;
        IoError::expect_size(&dir.join(DEPTH_FILE), size, data.depth.size())?;
        if let Some(m) = data.mask {
            IoError::expect_size(&dir.join(MASK_FILE), size, m.size())?;
        }
        if let Some(r) = data.raw_depth {
            IoError::expect_size(&dir.join(RAW_DEPTH_FILE), size, r.size())?;
        }
        std::fs::create_dir_all(&dir).map_err(|e| IoError::io(&dir, "create directory", e))?;
        write_rgb(dir.join(RGB_FILE), data.rgb)?;
        let stats = write_depth(dir.join(DEPTH_FILE), data.depth)?;
        if let Some(m) = data.mask {
            write_mask(dir.join(MASK_FILE), m)?;
        }
        if let Some(r) = data.raw_depth {
            write_depth(dir.join(RAW_DEPTH_FILE), r)?;
        }
        Ok(stats)
    }
}
