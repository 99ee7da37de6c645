//! Depth maps and depth-model predictions: uint16 PNG (millimetres), `.npy` (float), PFM (float).
//!
//! Metric depth ([`MetricDepth`], metres) and raw predictions ([`Prediction`], unitless) are
//! read and written by separate functions, so uncalibrated output can never be written as metres:
//! [`write_depth`] takes only a [`MetricDepth`] and [`write_prediction`] refuses the millimetre PNG.

use std::path::Path;

use moma_core::{ImageSize, MetricDepth, Prediction, PredictionKind, UnitMistake, is_valid_depth};
use ndarray::{Array2, ArrayD, ArrayView2, Axis, Ix2};
use ndarray_npy::{ReadNpyError, ReadNpyExt, WriteNpyExt};

use crate::atomic::{atomic_write, write_err};
use crate::error::{IoError, Result};
use crate::limits::{MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE_PX, check_image_size};
use crate::png_util::{PngPixels, decode_image_bytes, encode_png, pixel_type};

/// Stored units per metre of a depth PNG: uint16 millimetres.
pub const PNG_DEPTH_UNITS_PER_M: f64 = 1000.0;
/// Largest depth a millimetre PNG can hold, metres (65535 mm).
pub const PNG_DEPTH_MAX_M: f64 = 65.535;

/// A file format for depth maps and predictions, chosen by file extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DepthFormat {
    /// `.png`: single-channel uint16, millimetres for depth, 0 = no measurement.
    Png16,
    /// `.npy`: NumPy array, float32 written (float32 or float64 read), metres for depth.
    Npy,
    /// `.pfm`: Portable Float Map, grayscale `Pf`, float32, rows stored bottom-to-top.
    Pfm,
}

impl DepthFormat {
    /// The format of `path` from its extension (`png`, `npy`, `pfm`; case-insensitive).
    ///
    /// # Errors
    /// [`IoError::Unsupported`] for any other or missing extension.
    pub fn from_path(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let ext = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        match ext.as_str() {
            "png" => Ok(Self::Png16),
            "npy" => Ok(Self::Npy),
            "pfm" => Ok(Self::Pfm),
            _ => Err(IoError::unsupported(
                path,
                "depth file extension",
                if ext.is_empty() {
                    "<none>".to_string()
                } else {
                    ext
                },
                "'.png' (uint16 millimetres), '.npy' (float metres) or '.pfm' (float metres)",
            )),
        }
    }

    /// The usual file extension, without the dot.
    pub fn extension(self) -> &'static str {
        match self {
            Self::Png16 => "png",
            Self::Npy => "npy",
            Self::Pfm => "pfm",
        }
    }
}

/// Byte order of a PFM file's samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum PfmByteOrder {
    /// Negative scale in the header (the common choice; what [`write_depth`] writes).
    #[default]
    LittleEndian,
    /// Positive scale in the header.
    BigEndian,
}

/// What [`write_depth`] did with pixels a format cannot store.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct DepthWriteStats {
    /// Pixels written.
    pub pixels: usize,
    /// Pixels that were already invalid (NaN, ±inf, ≤ 0 m). PNG: written as 0. npy/PFM: written unchanged.
    pub invalid: usize,
    /// Valid depths the format cannot represent, written as 0 ("no measurement"): PNG only,
    /// depths that round to 0 mm (< 0.5 mm) or exceed 65 535 mm (> 65.535 m). Always 0 for npy/PFM.
    pub out_of_range: usize,
}

// ---------------------------------------------------------------------------------------------
// Metric depth
// ---------------------------------------------------------------------------------------------

/// Reads a metric depth map (metres) in the format given by the extension ([`DepthFormat`]).
///
/// - PNG: uint16 millimetres; 0 becomes `NaN`, `v` becomes `v / 1000` metres.
/// - npy: float32 or float64 metres, shape `(H, W)`, `(1, H, W)` or `(H, W, 1)`; values unchanged
///   (0, negative, NaN and ±inf all count as invalid, see [`moma_core::is_valid_depth`]).
/// - PFM: grayscale float metres; rows flipped to top-to-bottom.
///
/// # Errors
/// Unsupported extension or pixel type/dtype/shape ([`IoError::Unsupported`]), missing file
/// ([`IoError::Io`]), truncated or corrupt content ([`IoError::Corrupt`]), a `.npy` / `.pfm`
/// whose valid median is above [`moma_core::MILLIMETRE_MEDIAN_M`] (millimetres given as metres),
/// any map whose valid median is below [`moma_core::NEAR_MEDIAN_M`] (metres written as
/// millimetres; [`IoError::Invalid`]).
pub fn read_depth(path: impl AsRef<Path>) -> Result<MetricDepth> {
    let path = path.as_ref();
    let format = DepthFormat::from_path(path)?;
    let depth_m = match format {
        DepthFormat::Png16 => read_png16(path)?.mapv(|mm| {
            if mm == 0 {
                f32::NAN
            } else {
                (f64::from(mm) / PNG_DEPTH_UNITS_PER_M) as f32
            }
        }),
        DepthFormat::Npy => read_npy_f32(path)?,
        DepthFormat::Pfm => read_pfm(path)?,
    };
    // a float map of millimetres (a sensor PNG cast without dividing by 1000) would be taken
    // as metres: a calibration of 5 km RMS, maps of hundreds of metres; the reverse (metres
    // written into a millimetre PNG, values 0–5, or metres divided by 1000 into a float file)
    // a scene a few millimetres from the camera
    match moma_core::unit_mistake(depth_m.view()) {
        None => {}
        Some(UnitMistake::Millimetres(median)) => {
            return Err(IoError::invalid(
                path,
                format!(
                    "median depth {median} m looks like millimetres: .npy and .pfm depth is in \
                     metres (divide by 1000, or save millimetres as a uint16 PNG; far \
                     background or sky stored as a large number: write it as NaN or 0, no \
                     depth)"
                ),
            ));
        }
        Some(UnitMistake::TooNear(median)) => {
            let mm = f64::from(median) * 1000.0;
            let why = if format == DepthFormat::Png16 {
                "a uint16 depth PNG holds millimetres: this one looks like metres (or tenths) \
                 written as integers; write round(metres × 1000)"
            } else {
                ".npy and .pfm depth is in metres: this looks like kilometres, metres divided \
                 by 1000 once too often, or no depth map at all (a σ map `NAME.sigma.npy` is \
                 read as an array, e.g. numpy.load)"
            };
            return Err(IoError::invalid(
                path,
                format!(
                    "median depth {mm:.1} mm: no scene a camera grasps in is that near ({why})"
                ),
            ));
        }
    }
    Ok(MetricDepth::new(depth_m))
}

/// Reads a metric depth map ([`read_depth`]) and checks its size in pixels.
///
/// # Errors
/// As [`read_depth`], plus [`IoError::SizeMismatch`] when the map is not `expected`.
pub fn read_depth_sized(path: impl AsRef<Path>, expected: ImageSize) -> Result<MetricDepth> {
    let path = path.as_ref();
    let depth = read_depth(path)?;
    IoError::expect_size(path, expected, depth.size())?;
    Ok(depth)
}

/// Writes a metric depth map (metres) atomically, in the format given by the extension.
///
/// - PNG: uint16 millimetres, `round(z · 1000)` (nearest mm, ties away from zero); invalid
///   pixels (NaN, ±inf, ≤ 0) and depths outside `[0.5 mm, 65.535 m]` are written as 0 and counted
///   in the returned [`DepthWriteStats`]. A `tEXt` chunk `moma:depth_units_per_m = 1000` records the unit.
/// - npy: float32 metres, `(H, W)`, values unchanged (NaN stays NaN).
/// - PFM: float32 metres, little-endian, values unchanged.
///
/// # Errors
/// Unsupported extension; destination not writable ([`IoError::Io`] / [`IoError::Invalid`]),
/// in which case nothing is left at `path`.
pub fn write_depth(path: impl AsRef<Path>, depth: &MetricDepth) -> Result<DepthWriteStats> {
    let path = path.as_ref();
    let values = depth.depth_m.view();
    let mut stats = DepthWriteStats {
        pixels: values.len(),
        invalid: values.iter().filter(|&&z| !is_valid_depth(z)).count(),
        out_of_range: 0,
    };
    match DepthFormat::from_path(path)? {
        DepthFormat::Png16 => {
            let (mm, out_of_range) = depth_to_mm(values);
            stats.out_of_range = out_of_range;
            write_png16(path, &mm, &[("moma:depth_units_per_m", "1000".to_string())])?;
        }
        DepthFormat::Npy => write_npy_f32(path, values)?,
        DepthFormat::Pfm => write_pfm(path, values, PfmByteOrder::LittleEndian)?,
    }
    Ok(stats)
}

/// Converts metres to uint16 millimetres as [`write_depth`] stores them; returns the map and the
/// number of valid depths that fell outside `[0.5 mm, 65.535 m]` (stored as 0).
pub fn depth_to_mm(depth_m: ArrayView2<'_, f32>) -> (Array2<u16>, usize) {
    let mut out_of_range = 0;
    let mm = depth_m.mapv(|z| {
        if !is_valid_depth(z) {
            return 0;
        }
        let v = (f64::from(z) * PNG_DEPTH_UNITS_PER_M).round();
        if v < 1.0 || v > f64::from(u16::MAX) {
            out_of_range += 1;
            0
        } else {
            v as u16
        }
    });
    (mm, out_of_range)
}

// ---------------------------------------------------------------------------------------------
// Predictions (not metres)
// ---------------------------------------------------------------------------------------------

/// Reads a depth model's raw prediction (unitless, not metres) and tags it with `kind`.
///
/// - npy: float32/float64 values unchanged; shapes `(H, W)`, `(1, H, W)`, `(H, W, 1)`.
/// - PFM: float values unchanged, rows flipped to top-to-bottom.
/// - PNG: uint16 raw values as floats (no millimetre conversion, 0 stays 0.0); 8-bit PNGs are
///   rejected as too coarse.
///
/// # Errors
/// As [`read_depth`].
pub fn read_prediction(path: impl AsRef<Path>, kind: PredictionKind) -> Result<Prediction> {
    let path = path.as_ref();
    let values = match DepthFormat::from_path(path)? {
        DepthFormat::Png16 => read_png16(path)?.mapv(f32::from),
        DepthFormat::Npy => read_npy_f32(path)?,
        DepthFormat::Pfm => read_pfm(path)?,
    };
    Ok(Prediction::new(values, kind))
}

/// Writes a raw prediction atomically as float32 `.npy` or `.pfm` (values unchanged, unitless).
///
/// The prediction kind is not stored in the file; keep it with the caller (e.g. in a
/// calibration file or file name).
///
/// # Errors
/// [`IoError::Unsupported`] for `.png`: a millimetre PNG would label uncalibrated values as
/// metres (calibrate first, then [`write_depth`]); unwritable destination as [`write_depth`].
pub fn write_prediction(path: impl AsRef<Path>, pred: &Prediction) -> Result<()> {
    let path = path.as_ref();
    match DepthFormat::from_path(path)? {
        DepthFormat::Npy => write_npy_f32(path, pred.values.view()),
        DepthFormat::Pfm => write_pfm(path, pred.values.view(), PfmByteOrder::LittleEndian),
        DepthFormat::Png16 => Err(IoError::unsupported(
            path,
            "prediction output format",
            "png",
            "'.npy' or '.pfm': a uint16 millimetre PNG is for calibrated metric depth only",
        )),
    }
}

// ---------------------------------------------------------------------------------------------
// Format-level readers and writers (raw arrays)
// ---------------------------------------------------------------------------------------------

/// Reads a single-channel 16-bit PNG as raw `u16` values, `(height, width)`.
///
/// # Errors
/// [`IoError::Unsupported`] for any other pixel type (8-bit, RGB, alpha...); unreadable or
/// corrupt file.
pub fn read_png16(path: impl AsRef<Path>) -> Result<Array2<u16>> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, "read", e))?;
    png16_from_bytes(path, &bytes)
}

/// [`read_png16`] on the content of a file already in memory; `path` names it in errors.
///
/// # Errors
/// As [`read_png16`]; [`IoError::TooLarge`] when the header claims more than
/// [`crate::MAX_IMAGE_PIXELS`] pixels or [`crate::MAX_IMAGE_SIDE_PX`] pixels per side, and
/// [`IoError::Corrupt`] when it claims more pixel data than the file can hold, both before
/// anything is allocated.
pub fn png16_from_bytes(path: &Path, bytes: &[u8]) -> Result<Array2<u16>> {
    let img = decode_image_bytes(path, bytes, Some(image::ImageFormat::Png))?;
    match img {
        image::DynamicImage::ImageLuma16(buf) => {
            let (w, h) = (buf.width() as usize, buf.height() as usize);
            Array2::from_shape_vec((h, w), buf.into_raw())
                .map_err(|e| IoError::corrupt(path, "PNG", e.to_string()))
        }
        other => Err(IoError::unsupported(
            path,
            "PNG pixel type",
            pixel_type(&other),
            "single-channel 16-bit grayscale (uint16 millimetres for depth)",
        )),
    }
}

/// Writes `(height, width)` `u16` values atomically as a 16-bit grayscale PNG with the given `tEXt` chunks.
pub(crate) fn write_png16(
    path: &Path,
    values: &Array2<u16>,
    texts: &[(&str, String)],
) -> Result<()> {
    let (h, w) = values.dim();
    crate::limits::check_writable_size(path, w, h)?;
    let data: Vec<u16> = values.iter().copied().collect();
    atomic_write(path, |out| {
        encode_png(out, path, w, h, PngPixels::Gray16(&data), texts)
    })
}

/// Reads a 2-D float array from `.npy` (float32 or float64, either byte order; float64 is
/// converted to float32). Shapes `(H, W)`, `(1, H, W)` and `(H, W, 1)` are accepted.
///
/// # Errors
/// [`IoError::Unsupported`] for other dtypes (e.g. `<i4`, `<u2`) or shapes;
/// [`IoError::Corrupt`] for a bad header or truncated data; [`IoError::Io`] when unreadable.
pub fn read_npy_f32(path: impl AsRef<Path>) -> Result<Array2<f32>> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, "read", e))?;
    npy_f32_from_bytes(path, &bytes)
}

/// [`read_npy_f32`] on the content of a file already in memory; `path` names it in errors.
///
/// # Errors
/// As [`read_npy_f32`]; [`IoError::TooLarge`] when the header's shape holds more than
/// [`crate::MAX_IMAGE_PIXELS`] elements or a side over [`crate::MAX_IMAGE_SIDE_PX`], and
/// [`IoError::Corrupt`] when the data length differs from what the shape and dtype need, both
/// before anything is allocated.
pub fn npy_f32_from_bytes(path: &Path, bytes: &[u8]) -> Result<Array2<f32>> {
    check_npy_header(path, bytes)?;
    let arr: ArrayD<f32> = match ArrayD::<f32>::read_npy(bytes) {
        Ok(a) => a,
        Err(ReadNpyError::WrongDescriptor(_)) => match ArrayD::<f64>::read_npy(bytes) {
            Ok(a) => a.mapv(|v| v as f32),
            Err(ReadNpyError::WrongDescriptor(desc)) => {
                return Err(IoError::unsupported(
                    path,
                    "npy dtype",
                    desc.to_string().trim_matches('\'').to_string(),
                    "float32 ('<f4') or float64 ('<f8')",
                ));
            }
            Err(e) => return Err(npy_read_error(path, e)),
        },
        Err(e) => return Err(npy_read_error(path, e)),
    };
    squeeze_2d(path, arr)
}

/// Checks the shape an npy header claims against the limits and the data length, before
/// `ndarray-npy` allocates for it. A header this function cannot parse is left to `ndarray-npy`
/// (which reports it as corrupt).
fn check_npy_header(path: &Path, bytes: &[u8]) -> Result<()> {
    if let Some((preamble, header_len)) = npy_header_len(bytes) {
        let follow = bytes.len() as u64 - preamble;
        if header_len > follow {
            // ndarray-npy would allocate the claimed header length before reading it.
            return Err(IoError::corrupt(
                path,
                "npy",
                format!(
                    "header claims {header_len} bytes, only {follow} follow (file is truncated)"
                ),
            ));
        }
    }
    let Some((header, data_start)) = npy_header_text(bytes) else {
        return Ok(());
    };
    let Some(shape) = npy_dict_shape(header) else {
        return Ok(());
    };
    let mut elements: u64 = 1;
    for &d in &shape {
        elements = elements.saturating_mul(d);
    }
    // (H, W), (1, H, W) or (H, W, 1): the two largest dimensions are height and width; any
    // other shape is refused later, but never allocated.
    let mut sides = shape.clone();
    sides.sort_unstable_by(|a, b| b.cmp(a));
    // the width is the product of the other dimensions (saturating: a division of a saturated
    // product misstated the shape)
    let (height, width) = match sides.split_first() {
        None => (1, 1),
        Some((a, rest)) => (*a, rest.iter().fold(1u64, |p, &d| p.saturating_mul(d))),
    };
    if elements > MAX_IMAGE_PIXELS || shape.iter().any(|&d| d > MAX_IMAGE_SIDE_PX) {
        return Err(IoError::TooLarge {
            path: path.to_path_buf(),
            format: "npy",
            width,
            height,
            limit: if elements > MAX_IMAGE_PIXELS {
                format!("{MAX_IMAGE_PIXELS} pixels")
            } else {
                format!("{MAX_IMAGE_SIDE_PX} pixels per side")
            },
        });
    }
    let Some(item_bytes) = npy_dict_item_bytes(header) else {
        return Ok(());
    };
    let need = elements * item_bytes;
    let have = (bytes.len() - data_start) as u64;
    if need != have {
        return Err(IoError::corrupt(
            path,
            "npy",
            format!(
                "header's shape {shape:?} of {item_bytes}-byte items needs {need} data bytes, \
                 the file has {have}{}",
                if need > have {
                    " (file is truncated)"
                } else {
                    ""
                }
            ),
        ));
    }
    Ok(())
}

/// The length of an npy file's preamble (magic, version, length field) and the header length it
/// claims, if the magic string and version are well-formed.
fn npy_header_len(bytes: &[u8]) -> Option<(u64, u64)> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return None;
    }
    match bytes[6] {
        1 => Some((10, u64::from(u16::from_le_bytes([bytes[8], bytes[9]])))),
        2 | 3 if bytes.len() >= 12 => Some((
            12,
            u64::from(u32::from_le_bytes([
                bytes[8], bytes[9], bytes[10], bytes[11],
            ])),
        )),
        _ => None,
    }
}

/// The header dictionary text of an npy file and the offset of its data, if the magic string,
/// version and header length are well-formed.
fn npy_header_text(bytes: &[u8]) -> Option<(&str, usize)> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return None;
    }
    let (len, start) = match bytes[6] {
        1 => (
            usize::from(u16::from_le_bytes([bytes[8], bytes[9]])),
            10usize,
        ),
        2 | 3 if bytes.len() >= 12 => {
            let n = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
            (usize::try_from(n).ok()?, 12)
        }
        _ => return None,
    };
    let end = len.checked_add(start)?;
    let text = std::str::from_utf8(bytes.get(start..end)?).ok()?;
    Some((text, end))
}

/// The tuple after `'shape':` in an npy header dictionary.
fn npy_dict_shape(header: &str) -> Option<Vec<u64>> {
    let rest = &header[header.find("'shape'")? + "'shape'".len()..];
    let rest = rest
        .trim_start()
        .strip_prefix(':')?
        .trim_start()
        .strip_prefix('(')?;
    let inner = &rest[..rest.find(')')?];
    inner
        .split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
        .map(|t| t.trim_end_matches('L').parse::<u64>().ok())
        .collect()
}

/// The item size in bytes of the `'descr'` of an npy header dictionary (`'<f4'` → 4).
fn npy_dict_item_bytes(header: &str) -> Option<u64> {
    let rest = &header[header.find("'descr'")? + "'descr'".len()..];
    let rest = rest.trim_start().strip_prefix(':')?.trim_start();
    let quote = rest.chars().next().filter(|c| *c == '\'' || *c == '"')?;
    let descr = &rest[1..][..rest[1..].find(quote)?];
    let digits = descr.trim_start_matches(|c: char| !c.is_ascii_digit());
    match digits.parse::<u64>() {
        Ok(n) if (1..=16).contains(&n) && descr.len() == 3 => Some(n),
        _ => None,
    }
}

fn npy_read_error(path: &Path, e: ReadNpyError) -> IoError {
    match e {
        ReadNpyError::Io(io) if io.kind() != std::io::ErrorKind::UnexpectedEof => {
            IoError::io(path, "read", io)
        }
        ReadNpyError::Io(_) | ReadNpyError::MissingData => IoError::corrupt(
            path,
            "npy",
            "file is truncated (fewer data bytes than the header's shape needs)",
        ),
        other => IoError::corrupt(path, "npy", other.to_string()),
    }
}

fn squeeze_2d(path: &Path, arr: ArrayD<f32>) -> Result<Array2<f32>> {
    let shape = arr.shape().to_vec();
    let arr = match shape.as_slice() {
        [_, _] => arr,
        [1, _, _] => arr.index_axis_move(Axis(0), 0),
        [_, _, 1] => arr.index_axis_move(Axis(2), 0),
        _ => {
            return Err(IoError::unsupported(
                path,
                "npy shape",
                format!("{shape:?}"),
                "(H, W), (1, H, W) or (H, W, 1)",
            ));
        }
    };
    let arr = arr
        .into_dimensionality::<Ix2>()
        .map_err(|e| IoError::corrupt(path, "npy", e.to_string()))?;
    if arr.is_empty() {
        return Err(IoError::invalid(
            path,
            format!("npy array of shape {shape:?} is empty"),
        ));
    }
    // Fortran-ordered files come back with transposed strides; normalise to row-major.
    Ok(arr.as_standard_layout().into_owned())
}

/// Writes a `(height, width)` array atomically as float32 little-endian `.npy` (C order).
///
/// # Errors
/// Destination not writable ([`IoError::Io`] / [`IoError::Invalid`]); an empty array (which
/// [`read_npy_f32`] would refuse: a file is not written that cannot be read back).
pub fn write_npy_f32(path: impl AsRef<Path>, values: ArrayView2<'_, f32>) -> Result<()> {
    let path = path.as_ref();
    let (h, w) = values.dim();
    if w == 0 || h == 0 {
        return Err(IoError::invalid(
            path,
            format!("cannot write an empty {w}x{h} map as npy"),
        ));
    }
    crate::limits::check_writable_size(path, w, h)?;
    atomic_write(path, |w| {
        values
            .as_standard_layout()
            .write_npy(w)
            .map_err(|e| match e {
                ndarray_npy::WriteNpyError::Io(io) => IoError::io(path, "write", io),
                other => IoError::invalid(path, format!("npy encoding failed: {other}")),
            })
    })
}

/// Reads a grayscale PFM (`Pf`) file of either byte order as `(height, width)` float32,
/// flipping its bottom-to-top rows to top-to-bottom. Values are unchanged (the header's scale
/// magnitude is ignored, only its sign is used as the byte order).
///
/// # Errors
/// [`IoError::Unsupported`] for colour PFM (`PF`); [`IoError::Corrupt`] for a malformed header,
/// truncated data or trailing bytes.
pub fn read_pfm(path: impl AsRef<Path>) -> Result<Array2<f32>> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, "read", e))?;
    pfm_from_bytes(path, &bytes)
}

/// [`read_pfm`] on the content of a file already in memory; `path` names it in errors.
///
/// # Errors
/// As [`read_pfm`]; [`IoError::TooLarge`] when the header claims more than
/// [`crate::MAX_IMAGE_PIXELS`] pixels or [`crate::MAX_IMAGE_SIDE_PX`] pixels per side (checked
/// before the data length and before anything is allocated).
pub fn pfm_from_bytes(path: &Path, bytes: &[u8]) -> Result<Array2<f32>> {
    parse_pfm(path, bytes)
}

fn parse_pfm(path: &Path, bytes: &[u8]) -> Result<Array2<f32>> {
    let bad = |reason: String| IoError::corrupt(path, "PFM", reason);
    let mut pos = 0usize;
    // Header: four whitespace-separated tokens (magic, width, height, scale), then exactly one
    // whitespace byte before the samples.
    let mut token = |what: &str| -> Result<String> {
        while pos < bytes.len() && bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        let start = pos;
        while pos < bytes.len() && !bytes[pos].is_ascii_whitespace() && pos - start < 32 {
            pos += 1;
        }
        if start == pos {
            return Err(bad(format!("header ends before the {what}")));
        }
        Ok(String::from_utf8_lossy(&bytes[start..pos]).into_owned())
    };
    let magic = token("magic number")?;
    match magic.as_str() {
        "Pf" => {}
        "PF" => {
            return Err(IoError::unsupported(
                path,
                "PFM type",
                "PF (3-channel colour)",
                "Pf (single-channel grayscale)",
            ));
        }
        other => return Err(bad(format!("magic number is '{other}', expected 'Pf'"))),
    }
    let width: usize = token("width")?
        .parse()
        .map_err(|e| bad(format!("width is not a positive integer: {e}")))?;
    let height: usize = token("height")?
        .parse()
        .map_err(|e| bad(format!("height is not a positive integer: {e}")))?;
    let scale_tok = token("scale")?;
    let scale: f32 = scale_tok
        .parse()
        .map_err(|_| bad(format!("scale '{scale_tok}' is not a number")))?;
    if width == 0 || height == 0 {
        return Err(bad(format!("image size {width}x{height} is empty")));
    }
    check_image_size(path, "PFM", width as u64, height as u64)?;
    if !scale.is_finite() || scale == 0.0 {
        // the header's own text: -1e300 parsed as f32 is -inf, which it did not say
        return Err(bad(format!(
            "scale '{scale_tok}' must be a finite, nonzero float32 (its sign is the byte order)"
        )));
    }
    if pos >= bytes.len() || !bytes[pos].is_ascii_whitespace() {
        return Err(bad("header is not followed by a whitespace byte".into()));
    }
    pos += 1;
    let little = scale < 0.0;
    let n = width
        .checked_mul(height)
        .and_then(|n| n.checked_mul(4))
        .ok_or_else(|| bad(format!("image size {width}x{height} is too large")))?;
    let data = &bytes[pos..];
    if data.len() < n {
        return Err(bad(format!(
            "file is truncated: {width}x{height} float32 samples need {n} bytes, found {}",
            data.len()
        )));
    }
    if data.len() > n {
        return Err(bad(format!(
            "{} unexpected bytes after the {width}x{height} samples",
            data.len() - n
        )));
    }
    let mut out = Array2::<f32>::zeros((height, width));
    for (file_row, chunk) in data.chunks_exact(width * 4).enumerate() {
        let mut row = out.row_mut(height - 1 - file_row);
        for (dst, b) in row.iter_mut().zip(chunk.chunks_exact(4)) {
            let b = [b[0], b[1], b[2], b[3]];
            *dst = if little {
                f32::from_le_bytes(b)
            } else {
                f32::from_be_bytes(b)
            };
        }
    }
    Ok(out)
}

/// Writes a `(height, width)` array atomically as grayscale PFM (`Pf`), rows bottom-to-top,
/// scale `-1.0` (little-endian) or `1.0` (big-endian).
///
/// # Errors
/// Destination not writable ([`IoError::Io`] / [`IoError::Invalid`]); an empty array.
pub fn write_pfm(
    path: impl AsRef<Path>,
    values: ArrayView2<'_, f32>,
    order: PfmByteOrder,
) -> Result<()> {
    let path = path.as_ref();
    let (h, w) = values.dim();
    if w == 0 || h == 0 {
        return Err(IoError::invalid(
            path,
            format!("cannot write an empty {w}x{h} map as PFM"),
        ));
    }
    crate::limits::check_writable_size(path, w, h)?;
    let scale = match order {
        PfmByteOrder::LittleEndian => "-1.0",
        PfmByteOrder::BigEndian => "1.0",
    };
    let mut buf = Vec::with_capacity(w * h * 4 + 32);
    buf.extend_from_slice(format!("Pf\n{w} {h}\n{scale}\n").as_bytes());
    for row in values.rows().into_iter().rev() {
        for &v in row {
            buf.extend_from_slice(&match order {
                PfmByteOrder::LittleEndian => v.to_le_bytes(),
                PfmByteOrder::BigEndian => v.to_be_bytes(),
            });
        }
    }
    atomic_write(path, |out| out.write_all(&buf).map_err(write_err(path)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::array;

    #[test]
    fn format_from_extension() {
        assert_eq!(
            DepthFormat::from_path("a/b.PNG").unwrap(),
            DepthFormat::Png16
        );
        assert_eq!(DepthFormat::from_path("x.npy").unwrap(), DepthFormat::Npy);
        assert_eq!(DepthFormat::from_path("x.pfm").unwrap(), DepthFormat::Pfm);
        let e = DepthFormat::from_path("x.tiff").unwrap_err().to_string();
        assert!(e.contains("x.tiff") && e.contains("tiff"), "{e}");
        assert!(DepthFormat::from_path("noext").is_err());
    }

    #[test]
    fn mm_conversion_rounds_and_counts() {
        let z = array![
            [0.0015f32, 0.0004, 65.535, 65.5356],
            [f32::NAN, -1.0, 1.2344, 1.2346]
        ];
        let (mm, oor) = depth_to_mm(z.view());
        assert_eq!(mm, array![[2u16, 0, 65535, 0], [0, 0, 1234, 1235]]);
        assert_eq!(oor, 2);
    }

    #[test]
    fn pfm_header_variants() {
        let p = Path::new("t.pfm");
        // Single-space separated header, big endian.
        let mut b = b"Pf 2 1 1.0\n".to_vec();
        b.extend_from_slice(&1.5f32.to_be_bytes());
        b.extend_from_slice(&(-2.0f32).to_be_bytes());
        assert_eq!(parse_pfm(p, &b).unwrap(), array![[1.5f32, -2.0]]);
        let e = parse_pfm(p, b"PF\n1 1\n-1\n\0\0\0\0\0\0\0\0\0\0\0\0").unwrap_err();
        assert!(matches!(e, IoError::Unsupported { .. }), "{e}");
        let e = parse_pfm(p, b"Pf\n2 2\n-1\n\0\0\0\0")
            .unwrap_err()
            .to_string();
        assert!(e.contains("truncated") && e.contains("t.pfm"), "{e}");
        let e = parse_pfm(p, b"P5\n2 2\n255\n").unwrap_err().to_string();
        assert!(e.contains("magic"), "{e}");
        let e = parse_pfm(p, b"Pf\n2 x\n-1\n").unwrap_err().to_string();
        assert!(e.contains("height"), "{e}");
        let e = parse_pfm(p, b"Pf\n1 1\n0\n\0\0\0\0")
            .unwrap_err()
            .to_string();
        assert!(e.contains("scale"), "{e}");
    }
}
