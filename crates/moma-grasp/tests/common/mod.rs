//! Analytic synthetic scenes: a pinhole camera looking at a plane with an optional box on it,
//! rendered by exact ray casting (independent of the crate's own geometry).

#![allow(dead_code)]

use moma_core::{Intrinsics, MetricDepth};
use moma_grasp::Vec3;
use ndarray::Array2;

pub const W: usize = 640;
pub const H: usize = 480;

pub fn intrinsics() -> Intrinsics {
    Intrinsics {
        width: W,
        height: H,
        fx: 600.0,
        fy: 600.0,
        cx: 319.5,
        cy: 239.5,
    }
}

/// A box standing on the table: footprint centre `(x, y)` in the table frame, sizes along its own
/// axes (`long` along the yawed x axis), yaw about up, radians.
#[derive(Debug, Clone, Copy)]
pub struct BoxSpec {
    pub x_m: f64,
    pub y_m: f64,
    pub long_m: f64,
    pub short_m: f64,
    pub height_m: f64,
    pub yaw_rad: f64,
}

impl BoxSpec {
    pub fn standard() -> Self {
        Self {
            x_m: 0.0,
            y_m: 0.0,
            long_m: 0.07,
            short_m: 0.04,
            height_m: 0.05,
            yaw_rad: 0.5,
        }
    }
}

/// Table frame: origin `o` on the table, in-plane axes `ex`, `ey`, `up = ex × ey` towards the camera.
#[derive(Debug, Clone, Copy)]
pub struct Scene {
    pub o: [f64; 3],
    pub ex: [f64; 3],
    pub ey: [f64; 3],
    pub up: [f64; 3],
    pub boxes: [Option<BoxSpec>; 2],
}

fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn mul(a: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
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

pub fn v3(a: [f64; 3]) -> Vec3 {
    Vec3::new(a[0] as f32, a[1] as f32, a[2] as f32)
}

impl Scene {
    /// Camera looking straight down at a table `dist_m` away, optional box.
    pub fn top_down(dist_m: f64, b: Option<BoxSpec>) -> Self {
        Self {
            o: [0.0, 0.0, dist_m],
            ex: [1.0, 0.0, 0.0],
            ey: [0.0, -1.0, 0.0],
            up: [0.0, 0.0, -1.0],
            boxes: [b, None],
        }
    }

    /// Table tilted by `tilt_rad` about the camera x axis (the camera looks at it obliquely).
    pub fn tilted(dist_m: f64, tilt_rad: f64, b: Option<BoxSpec>) -> Self {
        let (s, c) = tilt_rad.sin_cos();
        // Rotate the top-down frame about x.
        let rot = |v: [f64; 3]| [v[0], c * v[1] - s * v[2], s * v[1] + c * v[2]];
        let ey = rot([0.0, -1.0, 0.0]);
        let up = rot([0.0, 0.0, -1.0]);
        Self {
            o: [0.0, 0.0, dist_m],
            ex: [1.0, 0.0, 0.0],
            ey,
            up,
            boxes: [b, None],
        }
    }

    /// The box's axes in the camera frame: (long axis, short axis).
    pub fn box_axes(&self, b: &BoxSpec) -> ([f64; 3], [f64; 3]) {
        let (s, c) = b.yaw_rad.sin_cos();
        let long = add(mul(self.ex, c), mul(self.ey, s));
        let short = add(mul(self.ex, -s), mul(self.ey, c));
        (long, short)
    }

    /// Camera-frame centre of the box's top face.
    pub fn box_top_centre(&self, b: &BoxSpec) -> [f64; 3] {
        add(
            add(self.o, add(mul(self.ex, b.x_m), mul(self.ey, b.y_m))),
            mul(self.up, b.height_m),
        )
    }

    fn hit_box(&self, b: &BoxSpec, d: [f64; 3]) -> Option<f64> {
        let (long, short) = self.box_axes(b);
        let base = add(self.o, add(mul(self.ex, b.x_m), mul(self.ey, b.y_m)));
        let centre = add(base, mul(self.up, b.height_m / 2.0));
        let axes = [long, short, self.up];
        let half = [b.long_m / 2.0, b.short_m / 2.0, b.height_m / 2.0];
        // Ray from the origin: p(t) = t d. In box coordinates: q(t) = (t d - centre) · axis.
        let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
        for k in 0..3 {
            let o = -dot(centre, axes[k]);
            let dd = dot(d, axes[k]);
            if dd.abs() < 1e-12 {
                if o.abs() > half[k] {
                    return None;
                }
                continue;
            }
            let (a, c) = ((-half[k] - o) / dd, (half[k] - o) / dd);
            t0 = t0.max(a.min(c));
            t1 = t1.min(a.max(c));
        }
        (t0 <= t1 && t0 > 0.0).then_some(t0)
    }

    /// Renders the depth map (z of the nearest hit, metres; 0 where nothing is hit).
    pub fn render(&self) -> MetricDepth {
        let k = intrinsics();
        let depth = Array2::from_shape_fn((H, W), |(v, u)| {
            let d = [(u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0];
            let mut best = f64::INFINITY;
            let denom = dot(d, self.up);
            if denom.abs() > 1e-12 {
                let t = dot(self.o, self.up) / denom;
                if t > 0.0 {
                    best = t;
                }
            }
            for b in self.boxes.iter().flatten() {
                if let Some(t) = self.hit_box(b, d) {
                    best = best.min(t);
                }
            }
            if best.is_finite() { best as f32 } else { 0.0 }
        });
        MetricDepth::new(depth)
    }

    /// Distance from `p` to the line through the box's top-face centre along its long axis.
    pub fn dist_to_top_centre_line(&self, b: &BoxSpec, p: Vec3) -> f64 {
        let (long, _) = self.box_axes(b);
        let c = self.box_top_centre(b);
        let p = [p.x as f64, p.y as f64, p.z as f64];
        let d = sub(p, c);
        let along = dot(d, long);
        let perp = sub(d, mul(long, along));
        dot(perp, perp).sqrt()
    }

    /// Box coordinates (long, short, height above table) of a camera-frame point.
    pub fn box_coords(&self, b: &BoxSpec, p: Vec3) -> [f64; 3] {
        let (long, short) = self.box_axes(b);
        let base = add(self.o, add(mul(self.ex, b.x_m), mul(self.ey, b.y_m)));
        let d = sub([p.x as f64, p.y as f64, p.z as f64], base);
        [dot(d, long), dot(d, short), dot(d, self.up)]
    }

    pub fn cross_check(&self) -> [f64; 3] {
        cross(self.ex, self.ey)
    }
}
