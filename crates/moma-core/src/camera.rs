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

    /// Checks focal lengths are positive and finite and the size is non-empty.
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
        for (name, v, positive) in [
            ("fx", self.fx, true),
            ("fy", self.fy, true),
            ("cx", self.cx, false),
            ("cy", self.cy, false),
        ] {
            if !v.is_finite() || (positive && v <= 0.0) {
                return Err(CoreError::InvalidParameter(format!(
                    "camera {name} = {v} is not valid"
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
