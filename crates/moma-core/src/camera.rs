//! Pinhole camera intrinsics and back-projection to camera-frame points.

use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};
use crate::image::{ImageSize, MetricDepth, is_valid_depth};

/// Pinhole intrinsics in pixels, for an image of `width × height` pixels.
///
/// Pixel `(u, v)` = (column, row), origin at the centre of the top-left pixel.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Focal length along u, pixels.
    pub fx: f64,
    /// Focal length along v, pixels.
    pub fy: f64,
    /// Principal point column, pixels.
    pub cx: f64,
    /// Principal point row, pixels.
    pub cy: f64,
}

/// `v` as written in a message: plain digits for everyday magnitudes, scientific notation for
/// the rest (a subnormal printed plainly is 330 characters long).
fn readable(v: f64) -> String {
    if v == 0.0 || !v.is_finite() || (1e-3..1e7).contains(&v.abs()) {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// Focal lengths a camera's intrinsics can have, pixels: from a fisheye's few pixels on a tiny
/// image to a long telephoto lens on a large sensor.
pub const FOCAL_RANGE_PX: std::ops::RangeInclusive<f64> = 1.0..=1.0e6;

impl Intrinsics {
    /// The image size these intrinsics belong to.
    pub fn size(&self) -> ImageSize {
        ImageSize::new(self.width, self.height)
    }

    /// Default intrinsics when none are known: principal point at the image centre, `f = width` pixels
    /// (the canonical choice for reporting SSRA parameters, docs/method.md §2).
    pub fn nominal(size: ImageSize) -> Self {
        Self {
            width: size.width,
            height: size.height,
            fx: size.width as f64,
            fy: size.width as f64,
            cx: (size.width as f64 - 1.0) / 2.0,
            cy: (size.height as f64 - 1.0) / 2.0,
        }
    }

    /// Checks the size is non-empty, the focal lengths lie in [`FOCAL_RANGE_PX`] and the
    /// principal point within its upper end of the image's origin (a crop's principal point
    /// may lie far outside the crop): intrinsics outside them are no camera's (a subnormal
    /// focal length made every back-projected point infinite, exit 0) and would write points,
    /// clouds and grasps of no meaning.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] naming the bad field.
    pub fn validate(&self) -> Result<()> {
        if self.width == 0 || self.height == 0 {
            return Err(CoreError::InvalidParameter(format!(
                "camera image size {}x{} is empty",
                self.width, self.height
            )));
        }
        for (name, f) in [("fx", self.fx), ("fy", self.fy)] {
            if !(f.is_finite() && FOCAL_RANGE_PX.contains(&f)) {
                return Err(CoreError::InvalidParameter(format!(
                    "camera {name} = {} px is not valid: a focal length in pixels lies in {}–{} px",
                    readable(f),
                    FOCAL_RANGE_PX.start(),
                    FOCAL_RANGE_PX.end()
                )));
            }
        }
        // a crop of a larger image (a ROI, a planner's window) puts the principal point far
        // outside it, so only its magnitude is bounded, as the focal length's
        for (name, c) in [("cx", self.cx), ("cy", self.cy)] {
            if !(c.is_finite() && c.abs() <= *FOCAL_RANGE_PX.end()) {
                return Err(CoreError::InvalidParameter(format!(
                    "camera {name} = {} px is not valid: a principal point lies within {} px of \
                     the image's origin",
                    readable(c),
                    FOCAL_RANGE_PX.end()
                )));
            }
        }
        Ok(())
    }

    /// Projects a camera-frame point (metres) to the image: `(u, v)` in pixels (f32), `None`
    /// when the point is not in front of the camera (z ≤ 1 µm).
    #[inline]
    pub fn project(&self, p_m: [f32; 3]) -> Option<(f32, f32)> {
        let [x, y, z] = p_m;
        (z > 1e-6).then(|| {
            (
                (self.fx as f32) * x / z + self.cx as f32,
                (self.fy as f32) * y / z + self.cy as f32,
            )
        })
    }

    /// Back-projects pixel `(u, v)` (pixels) at depth `z_m` (metres) to a camera-frame point
    /// `[x, y, z]` in metres (x right, y down, z forward).
    #[inline]
    pub fn backproject(&self, u: f64, v: f64, z_m: f64) -> [f64; 3] {
        [
            (u - self.cx) * z_m / self.fx,
            (v - self.cy) * z_m / self.fy,
            z_m,
        ]
    }
}

/// A camera-frame point with the pixel it came from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraPoint {
    /// `[x, y, z]` in metres, camera frame (x right, y down, z forward).
    pub xyz_m: [f32; 3],
    /// Source pixel column.
    pub u: u32,
    /// Source pixel row.
    pub v: u32,
}

/// Back-projects every valid pixel of `depth` to a camera-frame point (metres).
///
/// # Errors
/// [`CoreError::SizeMismatch`] when `depth` does not match the intrinsics' image size.
pub fn depth_to_points(depth: &MetricDepth, intrinsics: &Intrinsics) -> Result<Vec<CameraPoint>> {
    intrinsics.size().expect_eq("depth map", depth.size())?;
    let mut points = Vec::with_capacity(depth.valid_count());
    for ((v, u), &z) in depth.depth_m.indexed_iter() {
        if is_valid_depth(z) {
            let [x, y, z] = intrinsics.backproject(u as f64, v as f64, z as f64);
            points.push(CameraPoint {
                xyz_m: [x as f32, y as f32, z as f32],
                u: u as u32,
                v: v as u32,
            });
        }
    }
    Ok(points)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(fx: f64, cx: f64) -> Intrinsics {
        Intrinsics {
            width: 640,
            height: 480,
            fx,
            fy: 525.0,
            cx,
            cy: 239.5,
        }
    }

    #[test]
    fn intrinsics_outside_any_cameras_are_refused_by_name() {
        // a 200×200 crop at (1720, 880) of a 1920×1080 camera: cx = 960 − 1720
        let crop = Intrinsics {
            width: 200,
            height: 200,
            cx: -760.0,
            cy: -340.0,
            ..camera(1400.0, 0.0)
        };
        for ok in [
            camera(525.0, 319.5),
            camera(1.0, -1.0e6),
            camera(1.0e6, 1.0e6),
            crop,
        ] {
            ok.validate().unwrap();
        }
        for (bad, named) in [
            (camera(5e-324, 319.5), "fx = 5e-324 px"),
            (camera(0.5, 319.5), "fx = 0.5 px"),
            (camera(-525.0, 319.5), "fx = -525 px"),
            (camera(1.0e9, 319.5), "fx = 1e9 px"),
            (camera(f64::NAN, 319.5), "fx = NaN px"),
            (camera(525.0, 1e300), "cx = 1e300 px"),
            (camera(525.0, -1.5e6), "cx = -1500000 px"),
            (camera(525.0, f64::INFINITY), "cx = inf px"),
        ] {
            let e = bad.validate().unwrap_err().to_string();
            assert!(e.contains(named), "{e}");
        }
        let e = Intrinsics {
            cy: 2.0e6,
            ..camera(525.0, 319.5)
        }
        .validate()
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("cy = 2000000 px") && e.contains("1000000 px of"),
            "{e}"
        );
    }
}
