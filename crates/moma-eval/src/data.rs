//! Reading and writing the "moma set" layout and prediction folders.
//!
//! Layout (see the data README):
//! ```text
//! SET/camera.json               {"width","height","fx","fy","cx","cy"} (pixels)
//! SET/frames/ID/rgb.png         8-bit RGB
//! SET/frames/ID/depth.png       uint16 millimetres, 0 = no measurement (ground truth)
//! SET/frames/ID/mask.png        uint8 0/255 evaluation region (absent = whole image)
//! SET/frames/ID/raw_depth.png   optional: what the sensor saw (transparent sets)
//! ```
//! A prediction folder holds `<frame-id>.npy`, float32 (float64 accepted), shape `(H, W)`.
//!
//! This module is a small private reader/writer so the evaluation does not depend on the
//! progress of `moma-io`; the formats are the same.

use std::fs;
use std::path::{Path, PathBuf};

use image::{GrayImage, ImageBuffer, Luma, RgbImage};
use moma_core::{ImageSize, Intrinsics, Mask, MetricDepth};
use ndarray::Array2;

use crate::error::{EvalError, Result};

/// One metre in the unit of a uint16 depth PNG (millimetres).
pub const DEPTH_PNG_UNITS_PER_M: f32 = 1000.0;

/// One frame of a set, fully loaded.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Frame id (the folder name).
    pub id: String,
    /// 8-bit RGB, when `rgb.png` exists.
    pub rgb: Option<RgbImage>,
    /// Ground-truth depth in metres (invalid = 0).
    pub gt: MetricDepth,
    /// Evaluation region; `None` = whole image.
    pub mask: Option<Mask>,
    /// What the depth sensor saw (transparent sets), metres, invalid = 0.
    pub raw_depth: Option<MetricDepth>,
}

/// A fixed-camera set in the moma layout.
#[derive(Debug, Clone)]
pub struct MomaSet {
    /// Set name (the folder's name).
    pub name: String,
    /// The set folder.
    pub dir: PathBuf,
    /// Camera intrinsics (pixels).
    pub intrinsics: Intrinsics,
    /// Frames sorted by id.
    pub frames: Vec<Frame>,
}

impl MomaSet {
    /// Image size of the set.
    pub fn size(&self) -> ImageSize {
        self.intrinsics.size()
    }
    /// Index of a frame by id.
    pub fn frame_index(&self, id: &str) -> Option<usize> {
        self.frames.iter().position(|f| f.id == id)
    }
}

/// The set's name: the last component of its path.
pub fn set_name(dir: &Path) -> String {
    dir.canonicalize()
        .ok()
        .and_then(|p| p.file_name().map(|s| s.to_string_lossy().into_owned()))
        .or_else(|| dir.file_name().map(|s| s.to_string_lossy().into_owned()))
        .unwrap_or_else(|| dir.display().to_string())
}

/// Sorted frame ids of a set (folder names under `frames/`).
///
/// # Errors
/// The `frames/` folder cannot be read.
pub fn frame_ids(dir: &Path) -> Result<Vec<String>> {
    let frames = dir.join("frames");
    let rd = fs::read_dir(&frames).map_err(|e| EvalError::io(&frames, e))?;
    let mut ids = Vec::new();
    for entry in rd {
        let entry = entry.map_err(|e| EvalError::io(&frames, e))?;
        if entry.path().is_dir() {
            ids.push(entry.file_name().to_string_lossy().into_owned());
        }
    }
    ids.sort();
    Ok(ids)
}

/// Reads `camera.json`.
///
/// # Errors
/// Missing file, bad JSON, invalid intrinsics.
pub fn read_camera(path: &Path) -> Result<Intrinsics> {
    let text = fs::read_to_string(path).map_err(|e| EvalError::io(path, e))?;
    let k: Intrinsics = serde_json::from_str(&text).map_err(|e| EvalError::Format {
        path: path.to_path_buf(),
        message: format!("bad camera.json: {e}"),
    })?;
    k.validate().map_err(|e| EvalError::Format {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    Ok(k)
}

fn open_image(path: &Path) -> Result<image::DynamicImage> {
    image::open(path).map_err(|e| EvalError::Image {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

/// Reads a uint16 millimetre depth PNG as metres (0 stays 0 = invalid).
///
/// # Errors
/// Missing/undecodable file, not 16-bit grayscale.
pub fn read_depth_png(path: &Path) -> Result<MetricDepth> {
    let img = open_image(path)?;
    let img = match img {
        image::DynamicImage::ImageLuma16(i) => i,
        other => {
            return Err(EvalError::Format {
                path: path.to_path_buf(),
                message: format!(
                    "depth PNG must be 16-bit grayscale millimetres, found {:?}",
                    other.color()
                ),
            });
        }
    };
    let (w, h) = img.dimensions();
    let data: Vec<f32> = img
        .into_raw()
        .into_iter()
        .map(|mm| mm as f32 / DEPTH_PNG_UNITS_PER_M)
        .collect();
    let arr = Array2::from_shape_vec((h as usize, w as usize), data).map_err(|e| {
        EvalError::Format {
            path: path.to_path_buf(),
            message: e.to_string(),
        }
    })?;
    Ok(MetricDepth::new(arr))
}

/// Reads a mask PNG (nonzero = inside).
///
/// # Errors
/// Missing/undecodable file.
pub fn read_mask_png(path: &Path) -> Result<Mask> {
    let img = open_image(path)?.into_luma8();
    let (w, h) = img.dimensions();
    let data: Vec<bool> = img.into_raw().into_iter().map(|b| b > 0).collect();
    Mask::from_vec(ImageSize::new(w as usize, h as usize), data).map_err(|e| EvalError::Format {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

/// Reads an RGB PNG/JPEG.
///
/// # Errors
/// Missing/undecodable file.
pub fn read_rgb(path: &Path) -> Result<RgbImage> {
    Ok(open_image(path)?.into_rgb8())
}

/// Loads a whole set, checking that every map has the camera's size.
///
/// # Errors
/// Missing `camera.json` / `frames/` / `depth.png`, unreadable files, size mismatches (naming the frame).
pub fn load_set(dir: &Path) -> Result<MomaSet> {
    let name = set_name(dir);
    let intrinsics = read_camera(&dir.join("camera.json"))?;
    let size = intrinsics.size();
    let ids = frame_ids(dir)?;
    let mut frames = Vec::with_capacity(ids.len());
    for id in ids {
        let fdir = dir.join("frames").join(&id);
        let gt = read_depth_png(&fdir.join("depth.png"))?;
        let check = |what: &str, got: ImageSize| -> Result<()> {
            if got != size {
                Err(EvalError::frame(
                    &name,
                    &id,
                    format!("{what} is {got}, camera.json says {size}"),
                ))
            } else {
                Ok(())
            }
        };
        check("depth.png", gt.size())?;
        let mask = if fdir.join("mask.png").exists() {
            let m = read_mask_png(&fdir.join("mask.png"))?;
            check("mask.png", m.size())?;
            Some(m)
        } else {
            None
        };
        let rgb = if fdir.join("rgb.png").exists() {
            let r = read_rgb(&fdir.join("rgb.png"))?;
            check(
                "rgb.png",
                ImageSize::new(r.width() as usize, r.height() as usize),
            )?;
            Some(r)
        } else {
            None
        };
        let raw_depth = if fdir.join("raw_depth.png").exists() {
            let r = read_depth_png(&fdir.join("raw_depth.png"))?;
            check("raw_depth.png", r.size())?;
            Some(r)
        } else {
            None
        };
        frames.push(Frame {
            id,
            rgb,
            gt,
            mask,
            raw_depth,
        });
    }
    Ok(MomaSet {
        name,
        dir: dir.to_path_buf(),
        intrinsics,
        frames,
    })
}

/// Reads one prediction `<dir>/<frame-id>.npy` (float32 or float64, shape `(H, W)`).
///
/// # Errors
/// Missing file (naming the frame), unreadable array.
pub fn read_prediction(dir: &Path, set: &str, frame: &str) -> Result<Array2<f32>> {
    let path = dir.join(format!("{frame}.npy"));
    if !path.exists() {
        return Err(EvalError::frame(
            set,
            frame,
            format!("missing prediction file {}", path.display()),
        ));
    }
    read_npy_f32(&path)
}

/// Reads a 2-D `.npy` array of float32 (or float64, converted).
///
/// # Errors
/// Unreadable file or not a 2-D float array.
pub fn read_npy_f32(path: &Path) -> Result<Array2<f32>> {
    let open = || fs::File::open(path).map_err(|e| EvalError::io(path, e));
    use ndarray_npy::ReadNpyExt;
    match Array2::<f32>::read_npy(open()?) {
        Ok(a) => Ok(a),
        Err(e32) => match Array2::<f64>::read_npy(open()?) {
            Ok(a) => Ok(a.mapv(|x| x as f32)),
            Err(_) => Err(EvalError::Format {
                path: path.to_path_buf(),
                message: format!("expected a 2-D float32 .npy array: {e32}"),
            }),
        },
    }
}

/// Writes a 2-D float32 `.npy` array.
///
/// # Errors
/// I/O failure.
pub fn write_npy_f32(path: &Path, a: &Array2<f32>) -> Result<()> {
    use ndarray_npy::WriteNpyExt;
    let f = fs::File::create(path).map_err(|e| EvalError::io(path, e))?;
    a.write_npy(std::io::BufWriter::new(f))
        .map_err(|e| EvalError::Format {
            path: path.to_path_buf(),
            message: e.to_string(),
        })
}

/// Writes metric depth (metres) as a uint16 millimetre PNG (invalid / out of range → 0).
///
/// # Errors
/// I/O failure.
pub fn write_depth_png(path: &Path, depth: &MetricDepth) -> Result<()> {
    let (h, w) = depth.depth_m.dim();
    let data: Vec<u16> = depth
        .depth_m
        .iter()
        .map(|&z| {
            if moma_core::is_valid_depth(z) {
                (z * DEPTH_PNG_UNITS_PER_M).round().clamp(0.0, 65535.0) as u16
            } else {
                0
            }
        })
        .collect();
    let img: ImageBuffer<Luma<u16>, Vec<u16>> = ImageBuffer::from_raw(w as u32, h as u32, data)
        .ok_or_else(|| EvalError::InvalidParameter("depth buffer size".into()))?;
    save_image(path, &img)
}

/// Writes a mask as 0/255 PNG.
///
/// # Errors
/// I/O failure.
pub fn write_mask_png(path: &Path, mask: &Mask) -> Result<()> {
    let (h, w) = mask.data().dim();
    let data: Vec<u8> = mask.data().iter().map(|&b| if b { 255 } else { 0 }).collect();
    let img = GrayImage::from_raw(w as u32, h as u32, data)
        .ok_or_else(|| EvalError::InvalidParameter("mask buffer size".into()))?;
    save_image(path, &img)
}

/// Saves any `image` buffer, creating parent folders.
///
/// # Errors
/// I/O or encoding failure.
pub fn save_image<P, C>(path: &Path, img: &ImageBuffer<P, C>) -> Result<()>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    if let Some(parent) = path.parent() {
        fs::create_dir_all(parent).map_err(|e| EvalError::io(parent, e))?;
    }
    img.save(path).map_err(|e| EvalError::Image {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

/// Writes a set's `camera.json`.
///
/// # Errors
/// I/O failure.
pub fn write_camera(path: &Path, k: &Intrinsics) -> Result<()> {
    let text = serde_json::to_string_pretty(k).map_err(|e| EvalError::Format {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    write_text(path, &text)
}

/// Writes a text file, creating parent folders.
///
/// # Errors
/// I/O failure.
pub fn write_text(path: &Path, text: &str) -> Result<()> {
    if let Some(parent) = path.parent() {
        fs::create_dir_all(parent).map_err(|e| EvalError::io(parent, e))?;
    }
    fs::write(path, text).map_err(|e| EvalError::io(path, e))
}

/// Writes a whole set in the moma layout (depth as uint16 mm).
///
/// # Errors
/// I/O failure.
pub fn write_set(dir: &Path, set: &MomaSet) -> Result<()> {
    write_camera(&dir.join("camera.json"), &set.intrinsics)?;
    for f in &set.frames {
        let fdir = dir.join("frames").join(&f.id);
        write_depth_png(&fdir.join("depth.png"), &f.gt)?;
        if let Some(rgb) = &f.rgb {
            save_image(&fdir.join("rgb.png"), rgb)?;
        }
        if let Some(m) = &f.mask {
            write_mask_png(&fdir.join("mask.png"), m)?;
        }
        if let Some(r) = &f.raw_depth {
            write_depth_png(&fdir.join("raw_depth.png"), r)?;
        }
    }
    Ok(())
}

/// Writes a coloured point cloud as binary little-endian PLY (`x y z` float32 metres, camera
/// frame: x right, y down, z forward; `red green blue` uchar). Invalid depths are skipped.
///
/// # Errors
/// Size mismatch between depth, colours and intrinsics; I/O failure.
pub fn write_ply(
    path: &Path,
    depth: &MetricDepth,
    intrinsics: &Intrinsics,
    rgb: Option<&RgbImage>,
) -> Result<usize> {
    let points = moma_core::depth_to_points(depth, intrinsics)
        .map_err(|e| EvalError::core(path.display().to_string(), e))?;
    let mut buf = Vec::with_capacity(points.len() * 15 + 256);
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment moma point cloud, metres, camera frame (x right, y down, z forward)\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        points.len()
    );
    buf.extend_from_slice(header.as_bytes());
    for p in &points {
        for c in p.xyz_m {
            buf.extend_from_slice(&c.to_le_bytes());
        }
        let col = rgb
            .and_then(|im| im.get_pixel_checked(p.u, p.v))
            .map(|px| px.0)
            .unwrap_or([200, 200, 200]);
        buf.extend_from_slice(&col);
    }
    if let Some(parent) = path.parent() {
        fs::create_dir_all(parent).map_err(|e| EvalError::io(parent, e))?;
    }
    fs::write(path, buf).map_err(|e| EvalError::io(path, e))?;
    Ok(points.len())
}
