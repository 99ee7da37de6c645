//! Conversions between ROS 2 messages and moma's types, each checked: a message that does not
//! hold what its header fields promise is an error naming the field, never a panic or a guess.

use image::RgbImage;
use moma_core::{ImageSize, Intrinsics, MetricDepth};
use moma_grasp::Grasp;
use ndarray::Array2;
use serde_bytes::ByteBuf;

use crate::error::{Result, RosError};
use crate::msg::{
    CameraInfo, Header, Image, Point, PointCloud2, PointField, Pose, PoseArray, Quaternion,
};

/// The most pixels one image may claim (a 16k × 16k frame); a larger `width × height` is a
/// corrupt or hostile header, refused before any allocation.
pub const MAX_PIXELS: u64 = 1 << 28;

/// Encodings of colour images the node takes.
pub const COLOUR_ENCODINGS: [&str; 5] = ["rgb8", "bgr8", "rgba8", "bgra8", "mono8"];

/// Size and row layout of `img` checked against its data: `(size, step)`.
fn checked_layout(img: &Image, bytes_per_pixel: usize) -> Result<(ImageSize, usize)> {
    let (w, h) = (img.width as usize, img.height as usize);
    if w == 0 || h == 0 {
        return Err(RosError::malformed(format!(
            "image is {w}×{h} pixels (empty)"
        )));
    }
    if u64::from(img.width) * u64::from(img.height) > MAX_PIXELS {
        return Err(RosError::malformed(format!(
            "image claims {w}×{h} pixels, more than {MAX_PIXELS}"
        )));
    }
    let step = img.step as usize;
    if step < w * bytes_per_pixel {
        return Err(RosError::malformed(format!(
            "step {step} bytes is less than width {w} × {bytes_per_pixel} bytes per pixel ({})",
            img.encoding
        )));
    }
    let needed = step * (h - 1) + w * bytes_per_pixel;
    if img.data.len() < needed {
        return Err(RosError::malformed(format!(
            "data holds {} bytes, {w}×{h} {} with step {step} needs {needed} (truncated)",
            img.data.len(),
            img.encoding
        )));
    }
    Ok((ImageSize::new(w, h), step))
}

/// A colour image (`rgb8`, `bgr8`, `rgba8`, `bgra8` or `mono8`) as RGB.
///
/// # Errors
/// [`RosError::Encoding`] for any other encoding; [`RosError::Malformed`] when the data do not
/// hold the announced image.
pub fn image_to_rgb(img: &Image) -> Result<RgbImage> {
    // (bytes per pixel, index of r, g, b)
    let (bpp, idx) = match img.encoding.as_str() {
        "rgb8" => (3, [0, 1, 2]),
        "bgr8" => (3, [2, 1, 0]),
        "rgba8" => (4, [0, 1, 2]),
        "bgra8" => (4, [2, 1, 0]),
        "mono8" | "8UC1" => (1, [0, 0, 0]),
        other => {
            return Err(RosError::Encoding {
                encoding: other.to_string(),
                expected: COLOUR_ENCODINGS.join(", "),
            });
        }
    };
    let (size, step) = checked_layout(img, bpp)?;
    let mut out = Vec::with_capacity(size.width * size.height * 3);
    for row in img.data.chunks(step).take(size.height) {
        for px in row[..size.width * bpp].chunks_exact(bpp) {
            out.extend_from_slice(&[px[idx[0]], px[idx[1]], px[idx[2]]]);
        }
    }
    RgbImage::from_raw(size.width as u32, size.height as u32, out)
        .ok_or_else(|| RosError::malformed("RGB buffer size".to_string()))
}

/// A single-channel float image (`32FC1`) as a `(height, width)` array, values as sent.
///
/// # Errors
/// Another encoding; data that do not hold the image.
pub fn image_to_f32(img: &Image) -> Result<Array2<f32>> {
    if img.encoding != "32FC1" {
        return Err(RosError::Encoding {
            encoding: img.encoding.clone(),
            expected: "32FC1".to_string(),
        });
    }
    let (size, step) = checked_layout(img, 4)?;
    let mut out = Vec::with_capacity(size.width * size.height);
    // The byte order decided once, outside the pixel loop, by two loops with the conversion
    // inlined (through a `fn` pointer it is an indirect call per pixel and nothing vectorises:
    // 9 % of the node's time in a profile).
    let rows = img.data.chunks(step).take(size.height);
    if img.is_bigendian != 0 {
        for row in rows {
            out.extend(
                row[..size.width * 4]
                    .chunks_exact(4)
                    .map(|b| f32::from_be_bytes([b[0], b[1], b[2], b[3]])),
            );
        }
    } else {
        for row in rows {
            out.extend(
                row[..size.width * 4]
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            );
        }
    }
    Array2::from_shape_vec((size.height, size.width), out)
        .map_err(|e| RosError::malformed(format!("32FC1 buffer: {e}")))
}

/// A depth sensor's image as metres: `16UC1` (millimetres, 0 = no depth, read as a depth PNG is) or `32FC1` (metres,
/// NaN or ≤ 0 = no depth); invalid pixels become NaN.
///
/// # Errors
/// Another encoding; data that do not hold the image.
pub fn depth_image_to_metres(img: &Image) -> Result<MetricDepth> {
    match img.encoding.as_str() {
        "32FC1" => Ok(MetricDepth::new(image_to_f32(img)?.mapv(|z| {
            if z.is_finite() && z > 0.0 {
                z
            } else {
                f32::NAN
            }
        }))),
        "16UC1" | "mono16" => {
            let (size, step) = checked_layout(img, 2)?;
            let big = img.is_bigendian != 0;
            let mut out = Vec::with_capacity(size.width * size.height);
            for row in img.data.chunks(step).take(size.height) {
                out.extend(row[..size.width * 2].chunks_exact(2).map(|b| {
                    let mm = if big {
                        u16::from_be_bytes([b[0], b[1]])
                    } else {
                        u16::from_le_bytes([b[0], b[1]])
                    };
                    // as a depth PNG is read (moma_io::read_depth)
                    if mm == 0 {
                        f32::NAN
                    } else {
                        (f64::from(mm) / moma_io::PNG_DEPTH_UNITS_PER_M) as f32
                    }
                }));
            }
            Array2::from_shape_vec((size.height, size.width), out)
                .map(MetricDepth::new)
                .map_err(|e| RosError::malformed(format!("16UC1 buffer: {e}")))
        }
        other => Err(RosError::Encoding {
            encoding: other.to_string(),
            expected: "16UC1 (millimetres) or 32FC1 (metres)".to_string(),
        }),
    }
}

/// A `(height, width)` float map as a `32FC1` image (little-endian, rows packed).
pub fn f32_to_image(values: &Array2<f32>, header: Header) -> Image {
    f32_image_with(values, header, |v| v)
}

/// `values` mapped by `f`, as `32FC1`, in one pass over the pixels (no intermediate map).
fn f32_image_with(values: &Array2<f32>, header: Header, f: impl Fn(f32) -> f32) -> Image {
    let (h, w) = values.dim();
    let mut data = Vec::with_capacity(h * w * 4);
    // Row-major slices when the map is contiguous (always, from moma's code), so that the loop
    // compiles to straight-line code; any other layout through ndarray's iterator.
    match values.as_slice() {
        Some(px) => data.extend(px.iter().flat_map(|&v| f(v).to_le_bytes())),
        None => data.extend(values.iter().flat_map(|&v| f(v).to_le_bytes())),
    }
    Image {
        header,
        height: h as u32,
        width: w as u32,
        encoding: "32FC1".to_string(),
        is_bigendian: 0,
        step: (w * 4) as u32,
        data: ByteBuf::from(data),
    }
}

/// Metric depth as a `32FC1` image in metres, NaN where there is no depth (REP 118).
pub fn depth_to_image(depth: &MetricDepth, header: Header) -> Image {
    f32_image_with(&depth.depth_m, header, |z| {
        if moma_core::is_valid_depth(z) {
            z
        } else {
            f32::NAN
        }
    })
}

/// An RGB image as `rgb8`.
pub fn rgb_to_image(rgb: &RgbImage, header: Header) -> Image {
    Image {
        header,
        height: rgb.height(),
        width: rgb.width(),
        encoding: "rgb8".to_string(),
        is_bigendian: 0,
        step: rgb.width() * 3,
        data: ByteBuf::from(rgb.as_raw().clone()),
    }
}

/// Millimetres (0 = no depth) as `16UC1`, as a RealSense driver publishes them.
pub fn mm_to_image(mm: &Array2<u16>, header: Header) -> Image {
    let (h, w) = mm.dim();
    let mut data = Vec::with_capacity(h * w * 2);
    for v in mm {
        data.extend_from_slice(&v.to_le_bytes());
    }
    Image {
        header,
        height: h as u32,
        width: w as u32,
        encoding: "16UC1".to_string(),
        is_bigendian: 0,
        step: (w * 2) as u32,
        data: ByteBuf::from(data),
    }
}

/// Metric depth in millimetres as `16UC1` (0 = no depth; depths beyond 65.535 m are 0): the
/// millimetres a depth PNG holds (`moma_io::depth_to_mm`).
pub fn depth_to_mm_image(depth: &MetricDepth, header: Header) -> Image {
    mm_to_image(&moma_io::depth_to_mm(depth.depth_m.view()).0, header)
}

/// Intrinsics of the image a `CameraInfo` describes, as `image_geometry`'s `PinholeCameraModel`
/// reads them for a rectified image: the projection matrix `p` (`k` where `p` is unset, as some
/// drivers leave it), then binning and region of interest applied (the image is `roi` of the
/// full `width × height` sensor, every `binning_x × binning_y` block one pixel: focal lengths
/// divided by the binning, the principal point moved by the ROI's offset, then divided).
///
/// # Errors
/// [`RosError::Malformed`] for an empty size, a focal length that is not positive and finite, or
/// a region of interest outside the image.
pub fn camera_info_to_intrinsics(info: &CameraInfo) -> Result<Intrinsics> {
    let malformed = |what: String| RosError::malformed(format!("CameraInfo: {what}"));
    let p_set = [info.p[0], info.p[5]]
        .iter()
        .all(|f| f.is_finite() && *f > 0.0);
    let (fx, fy, cx, cy) = if p_set {
        (info.p[0], info.p[5], info.p[2], info.p[6])
    } else {
        (info.k[0], info.k[4], info.k[2], info.k[5])
    };
    // ROS: 0 and 1 both mean no binning; as image_geometry, only an all-zero region of
    // interest is the full image
    let (bx, by) = (info.binning_x.max(1), info.binning_y.max(1));
    let roi = &info.roi;
    let full_roi = roi.x_offset == 0 && roi.y_offset == 0 && roi.width == 0 && roi.height == 0;
    let (x0, y0, roi_w, roi_h) = if full_roi {
        (0, 0, info.width, info.height)
    } else {
        (roi.x_offset, roi.y_offset, roi.width, roi.height)
    };
    let inside =
        |offset: u32, len: u32, full: u32| u64::from(offset) + u64::from(len) <= u64::from(full);
    if !(inside(x0, roi_w, info.width) && inside(y0, roi_h, info.height)) {
        return Err(malformed(format!(
            "region of interest {}×{} at ({}, {}) is outside the {}×{} image",
            roi_w, roi_h, x0, y0, info.width, info.height
        )));
    }
    let k = Intrinsics {
        width: (roi_w / bx) as usize,
        height: (roi_h / by) as usize,
        fx: fx / f64::from(bx),
        fy: fy / f64::from(by),
        cx: (cx - f64::from(x0)) / f64::from(bx),
        cy: (cy - f64::from(y0)) / f64::from(by),
    };
    k.validate().map_err(|e| malformed(e.to_string()))?;
    Ok(k)
}

/// Intrinsics as a `CameraInfo` (no distortion: rectified images).
pub fn intrinsics_to_camera_info(k: &Intrinsics, header: Header) -> CameraInfo {
    CameraInfo {
        header,
        height: k.height as u32,
        width: k.width as u32,
        distortion_model: "plumb_bob".to_string(),
        d: vec![0.0; 5],
        k: [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [
            k.fx, 0.0, k.cx, 0.0, 0.0, k.fy, k.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
        ],
        binning_x: 0,
        binning_y: 0,
        roi: Default::default(),
    }
}

/// An organised point cloud (`height × width` of the depth map) with float32 `x`, `y`, `z` in
/// metres (camera frame: x right, y down, z forward), NaN where there is no depth, and a packed
/// `rgb` float field when `rgb` is given (PCL's layout: 0x00RRGGBB in the float's bits).
///
/// # Errors
/// [`RosError::Size`] when the intrinsics or `rgb` are of another size than `depth`.
pub fn depth_to_cloud(
    depth: &MetricDepth,
    k: &Intrinsics,
    rgb: Option<&RgbImage>,
    header: Header,
) -> Result<PointCloud2> {
    let size = depth.size();
    if k.size() != size {
        return Err(RosError::Size {
            what: "camera intrinsics".to_string(),
            got: k.size(),
            expected: size,
        });
    }
    if let Some(img) = rgb {
        let got = ImageSize::new(img.width() as usize, img.height() as usize);
        if got != size {
            return Err(RosError::Size {
                what: "RGB image for the point colours".to_string(),
                got,
                expected: size,
            });
        }
    }
    let field = |name: &str, offset: u32| PointField {
        name: name.to_string(),
        offset,
        datatype: PointField::FLOAT32,
        count: 1,
    };
    let mut fields = vec![field("x", 0), field("y", 4), field("z", 8)];
    let point_step: usize = if rgb.is_some() {
        fields.push(field("rgb", 12));
        16
    } else {
        12
    };
    // x = z·(u − cx)/fx and y = z·(v − cy)/fy with the factors per column and per row, in
    // f32: within two f32 roundings of `Intrinsics::backproject`, without two divisions per
    // pixel, and in a form that vectorises: one pass computes a row's points (NaN propagates
    // through the products), a second writes their bytes (2.5 → 1.1 → 0.71 → 0.46 ms at
    // 640×480, `cargo bench -p moma-ros2`).
    let kx: Vec<f32> = (0..size.width)
        .map(|u| ((u as f64 - k.cx) / k.fx) as f32)
        .collect();
    let depth_m = depth.depth_m.as_standard_layout();
    // a standard-layout array is one slice; `None` cannot happen
    let depth_m = depth_m
        .as_slice()
        .ok_or_else(|| RosError::Malformed("depth map is not contiguous".to_string()))?;
    let mut data = vec![0u8; size.width * size.height * point_step];
    let mut points = vec![[0f32; 3]; size.width];
    let colours = rgb.map(|img| img.as_raw().as_slice());
    let out_rows = data.chunks_exact_mut(size.width * point_step);
    for (v, (row, out)) in depth_m.chunks_exact(size.width).zip(out_rows).enumerate() {
        let ky = ((v as f64 - k.cy) / k.fy) as f32;
        for ((&z, &kx), p) in row.iter().zip(&kx).zip(points.iter_mut()) {
            let z = if moma_core::is_valid_depth(z) {
                z
            } else {
                f32::NAN
            };
            *p = [z * kx, z * ky, z];
        }
        let out = out.chunks_exact_mut(point_step);
        match colours {
            None => {
                for (p, o) in points.iter().zip(out) {
                    write_point(o, p);
                }
            }
            Some(c) => {
                let row_rgb = &c[v * size.width * 3..(v + 1) * size.width * 3];
                for ((p, o), c) in points.iter().zip(out).zip(row_rgb.chunks_exact(3)) {
                    write_point(o, p);
                    let packed = (u32::from(c[0]) << 16) | (u32::from(c[1]) << 8) | u32::from(c[2]);
                    o[12..16].copy_from_slice(&packed.to_le_bytes());
                }
            }
        }
    }
    Ok(PointCloud2 {
        header,
        height: size.height as u32,
        width: size.width as u32,
        fields,
        is_bigendian: false,
        point_step: point_step as u32,
        row_step: (point_step * size.width) as u32,
        data: ByteBuf::from(data),
        is_dense: false,
    })
}

/// Writes x, y, z as little-endian f32 into the first 12 bytes of `out`.
fn write_point(out: &mut [u8], p: &[f32; 3]) {
    out[0..4].copy_from_slice(&p[0].to_le_bytes());
    out[4..8].copy_from_slice(&p[1].to_le_bytes());
    out[8..12].copy_from_slice(&p[2].to_le_bytes());
}

/// The pose of a grasp, in metres: position `p`, and an orientation whose x axis is `approach`
/// and whose y axis is `closing` made orthogonal to it (for suction, any axis orthogonal to the
/// approach: the camera's x or, when the approach is along it, its y).
pub fn grasp_pose(p: [f32; 3], approach: [f32; 3], closing: Option<[f32; 3]>) -> Pose {
    let a = normalised(approach.map(f64::from)).unwrap_or([0.0, 0.0, 1.0]);
    let seed = closing.map(|c| c.map(f64::from)).unwrap_or_else(|| {
        if a[0].abs() < 0.9 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        }
    });
    // Gram–Schmidt: y = seed − (seed·a) a
    let d = dot(seed, a);
    let y = normalised([seed[0] - d * a[0], seed[1] - d * a[1], seed[2] - d * a[2]])
        .or_else(|| normalised(cross(a, [0.0, 0.0, 1.0])))
        .unwrap_or([0.0, 1.0, 0.0]);
    let z = cross(a, y);
    Pose {
        position: Point {
            x: f64::from(p[0]),
            y: f64::from(p[1]),
            z: f64::from(p[2]),
        },
        orientation: quaternion_from_columns(a, y, z),
    }
}

/// A `PoseArray` of grasps, best first: in the camera frame, or in the robot base frame
/// (`base`) when `base` is true and every grasp carries one.
///
/// # Errors
/// [`RosError::Malformed`] when `base` is asked for and a grasp has no base pose.
pub fn grasps_to_pose_array(grasps: &[Grasp], base: bool, header: Header) -> Result<PoseArray> {
    let poses = grasps
        .iter()
        .map(|g| {
            let (point, approach, closing) = match (g, base) {
                (Grasp::Parallel(p), false) => {
                    (p.pose.center_m, p.pose.approach, Some(p.pose.closing))
                }
                (Grasp::Suction(s), false) => (s.pose.point_m, s.pose.approach, None),
                (Grasp::Parallel(p), true) => {
                    let b = p
                        .base
                        .ok_or_else(|| RosError::malformed("grasp without a base pose"))?;
                    (b.center_m, b.approach, Some(b.closing))
                }
                (Grasp::Suction(s), true) => {
                    let b = s
                        .base
                        .ok_or_else(|| RosError::malformed("grasp without a base pose"))?;
                    (b.point_m, b.approach, None)
                }
            };
            Ok(grasp_pose(point, approach, closing))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(PoseArray { header, poses })
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalised(v: [f64; 3]) -> Option<[f64; 3]> {
    let n = dot(v, v).sqrt();
    (n.is_finite() && n > 1e-9).then(|| [v[0] / n, v[1] / n, v[2] / n])
}

/// The unit quaternion of the rotation whose matrix has columns `x`, `y`, `z` (Shepperd's method:
/// the largest of the four candidates, for accuracy).
fn quaternion_from_columns(x: [f64; 3], y: [f64; 3], z: [f64; 3]) -> Quaternion {
    let (m00, m01, m02) = (x[0], y[0], z[0]);
    let (m10, m11, m12) = (x[1], y[1], z[1]);
    let (m20, m21, m22) = (x[2], y[2], z[2]);
    let trace = m00 + m11 + m22;
    let (qx, qy, qz, qw);
    if trace > 0.0 {
        let s = (trace + 1.0).sqrt() * 2.0;
        qw = 0.25 * s;
        qx = (m21 - m12) / s;
        qy = (m02 - m20) / s;
        qz = (m10 - m01) / s;
    } else if m00 > m11 && m00 > m22 {
        let s = (1.0 + m00 - m11 - m22).sqrt() * 2.0;
        qw = (m21 - m12) / s;
        qx = 0.25 * s;
        qy = (m01 + m10) / s;
        qz = (m02 + m20) / s;
    } else if m11 > m22 {
        let s = (1.0 + m11 - m00 - m22).sqrt() * 2.0;
        qw = (m02 - m20) / s;
        qx = (m01 + m10) / s;
        qy = 0.25 * s;
        qz = (m12 + m21) / s;
    } else {
        let s = (1.0 + m22 - m00 - m11).sqrt() * 2.0;
        qw = (m10 - m01) / s;
        qx = (m02 + m20) / s;
        qy = (m12 + m21) / s;
        qz = 0.25 * s;
    }
    Quaternion {
        x: qx,
        y: qy,
        z: qz,
        w: qw,
    }
}
