//! A procedural fixed-camera scene for `moma demo`: a pinhole camera (640×480, f = 600 px)
//! looking down about 0.7 m at a slightly tilted table, with boxes, cylinders and spheres
//! placed differently in each frame. Depth is ray-cast exactly (metres along the optical axis),
//! RGB is Lambert-shaded, masks mark the objects. No files are needed.

use image::RgbImage;
use moma_core::{ImageSize, Intrinsics, Mask, MetricDepth};
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::data::{LoadedFrame, LoadedSet};

type V3 = [f64; 3];

fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn scale(a: V3, k: f64) -> V3 {
    [a[0] * k, a[1] * k, a[2] * k]
}
fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn norm(a: V3) -> V3 {
    scale(a, 1.0 / dot(a, a).sqrt())
}

/// A shape standing on the table; coordinates in the table frame (metres): x, y in the table
/// plane, h up towards the camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// Box with half extents `(hx, hy, hz)` rotated by `yaw_rad` about the table normal.
    Box {
        /// Centre x, y on the table.
        x: f64,
        /// Centre y.
        y: f64,
        /// Half extents, metres.
        half: V3,
        /// Rotation about the table normal, radians.
        yaw_rad: f64,
    },
    /// Upright cylinder.
    Cylinder {
        /// Axis x.
        x: f64,
        /// Axis y.
        y: f64,
        /// Radius, metres.
        radius: f64,
        /// Height, metres.
        height: f64,
    },
    /// Sphere resting on the table.
    Sphere {
        /// Centre x.
        x: f64,
        /// Centre y.
        y: f64,
        /// Radius, metres.
        radius: f64,
    },
}

/// One object: shape and colour.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Object {
    /// Geometry.
    pub shape: Shape,
    /// Albedo RGB in [0, 1].
    pub colour: V3,
}

/// Scene settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DemoSceneConfig {
    /// Image size.
    pub size: ImageSize,
    /// Focal length, pixels.
    pub focal_px: f64,
    /// Distance camera → table along the optical axis, metres.
    pub table_distance_m: f64,
    /// Table tilt about the camera x axis, degrees.
    pub tilt_x_deg: f64,
    /// Table tilt about the camera y axis, degrees.
    pub tilt_y_deg: f64,
    /// Number of frames.
    pub frames: usize,
    /// Seed of the object placement.
    pub seed: u64,
}

impl Default for DemoSceneConfig {
    fn default() -> Self {
        Self {
            size: ImageSize::new(640, 480),
            focal_px: 600.0,
            table_distance_m: 0.7,
            tilt_x_deg: 12.0,
            tilt_y_deg: -6.0,
            frames: 6,
            seed: 7,
        }
    }
}

struct TableFrame {
    origin: V3,
    e1: V3,
    e2: V3,
    n: V3,
}

impl TableFrame {
    fn new(c: &DemoSceneConfig) -> Self {
        let (tx, ty) = (c.tilt_x_deg.to_radians(), c.tilt_y_deg.to_radians());
        // normal pointing towards the camera (−z), tilted
        let n = norm([ty.sin(), tx.sin(), -tx.cos() * ty.cos()]);
        let e1 = norm(sub([1.0, 0.0, 0.0], scale(n, n[0])));
        let e2 = cross(n, e1);
        Self {
            origin: [0.0, 0.0, c.table_distance_m],
            e1,
            e2,
            n,
        }
    }
    fn to_local(&self, p: V3) -> V3 {
        let d = sub(p, self.origin);
        [dot(d, self.e1), dot(d, self.e2), dot(d, self.n)]
    }
    fn dir_to_local(&self, d: V3) -> V3 {
        [dot(d, self.e1), dot(d, self.e2), dot(d, self.n)]
    }
    fn normal_to_camera(&self, l: V3) -> V3 {
        [
            l[0] * self.e1[0] + l[1] * self.e2[0] + l[2] * self.n[0],
            l[0] * self.e1[1] + l[1] * self.e2[1] + l[2] * self.n[1],
            l[0] * self.e1[2] + l[1] * self.e2[2] + l[2] * self.n[2],
        ]
    }
}

/// Ray–shape intersection in the table frame: nearest `t > 0` and the local normal.
fn intersect(shape: &Shape, o: V3, d: V3) -> Option<(f64, V3)> {
    match *shape {
        Shape::Sphere { x, y, radius } => {
            let c = [x, y, radius];
            let oc = sub(o, c);
            let b = dot(oc, d);
            let cc = dot(oc, oc) - radius * radius;
            let a = dot(d, d);
            let disc = b * b - a * cc;
            if disc < 0.0 {
                return None;
            }
            let t = (-b - disc.sqrt()) / a;
            (t > 0.0).then(|| {
                let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
                (t, norm(sub(p, c)))
            })
        }
        Shape::Cylinder {
            x,
            y,
            radius,
            height,
        } => {
            let mut best: Option<(f64, V3)> = None;
            let (ox, oy) = (o[0] - x, o[1] - y);
            let a = d[0] * d[0] + d[1] * d[1];
            if a > 1e-15 {
                let b = ox * d[0] + oy * d[1];
                let c = ox * ox + oy * oy - radius * radius;
                let disc = b * b - a * c;
                if disc >= 0.0 {
                    let t = (-b - disc.sqrt()) / a;
                    let h = o[2] + t * d[2];
                    if t > 0.0 && (0.0..=height).contains(&h) {
                        best = Some((t, norm([ox + t * d[0], oy + t * d[1], 0.0])));
                    }
                }
            }
            if d[2].abs() > 1e-15 {
                let t = (height - o[2]) / d[2];
                let (px, py) = (ox + t * d[0], oy + t * d[1]);
                if t > 0.0 && px * px + py * py <= radius * radius && best.is_none_or(|b| t < b.0) {
                    best = Some((t, [0.0, 0.0, 1.0]));
                }
            }
            best
        }
        Shape::Box {
            x,
            y,
            half,
            yaw_rad,
        } => {
            let (s, c) = yaw_rad.sin_cos();
            let rot = |v: V3| [c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2]];
            let ol = rot([o[0] - x, o[1] - y, o[2] - half[2]]);
            let dl = rot(d);
            let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
            let mut axis = 0;
            let mut sign = 1.0;
            for k in 0..3 {
                if dl[k].abs() < 1e-15 {
                    if ol[k].abs() > half[k] {
                        return None;
                    }
                    continue;
                }
                let ta = (-half[k] - ol[k]) / dl[k];
                let tb = (half[k] - ol[k]) / dl[k];
                let (lo, hi) = if ta < tb { (ta, tb) } else { (tb, ta) };
                if lo > t0 {
                    t0 = lo;
                    axis = k;
                    sign = if dl[k] > 0.0 { -1.0 } else { 1.0 };
                }
                t1 = t1.min(hi);
            }
            if t0 > t1 || t0 <= 0.0 {
                return None;
            }
            let mut nl = [0.0; 3];
            nl[axis] = sign;
            // back to table frame (inverse yaw)
            let n = [c * nl[0] - s * nl[1], s * nl[0] + c * nl[1], nl[2]];
            Some((t0, n))
        }
    }
}

/// Renders one frame: (depth in metres, RGB, object mask).
pub fn render(config: &DemoSceneConfig, objects: &[Object]) -> (MetricDepth, RgbImage, Mask) {
    let k = intrinsics(config);
    let tf = TableFrame::new(config);
    let (w, h) = (config.size.width, config.size.height);
    let mut depth = Array2::<f32>::zeros((h, w));
    let mut mask = Array2::from_elem((h, w), false);
    let mut rgb = RgbImage::new(w as u32, h as u32);
    let light = norm([0.35, -0.55, -1.0]); // direction towards the light, camera frame
    let o_local = tf.to_local([0.0, 0.0, 0.0]);
    for v in 0..h {
        for u in 0..w {
            let d = [(u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0];
            let dl = tf.dir_to_local(d);
            // table
            let mut best: Option<(f64, V3, V3, bool)> = None;
            if dl[2].abs() > 1e-12 {
                let t = -o_local[2] / dl[2];
                if t > 0.0 {
                    let p = [o_local[0] + t * dl[0], o_local[1] + t * dl[1]];
                    let checker =
                        (((p[0] / 0.05).floor() + (p[1] / 0.05).floor()) as i64).rem_euclid(2);
                    let grain = 0.04 * ((p[0] * 90.0).sin() * (p[1] * 7.0).cos());
                    let base = if checker == 0 { 0.78 } else { 0.70 } + grain;
                    best = Some((t, [0.0, 0.0, 1.0], [base, base * 0.82, base * 0.6], false));
                }
            }
            for obj in objects {
                if let Some((t, n)) = intersect(&obj.shape, o_local, dl)
                    && best.is_none_or(|b| t < b.0)
                {
                    best = Some((t, n, obj.colour, true));
                }
            }
            if let Some((t, nl, col, is_obj)) = best {
                depth[[v, u]] = t as f32; // d_z = 1, so t is the depth along the optical axis
                mask[[v, u]] = is_obj;
                let n = tf.normal_to_camera(nl);
                let lambert = dot(n, light).max(0.0);
                let shade = 0.3 + 0.7 * lambert;
                rgb.put_pixel(
                    u as u32,
                    v as u32,
                    image::Rgb([
                        (col[0] * shade * 255.0).clamp(0.0, 255.0) as u8,
                        (col[1] * shade * 255.0).clamp(0.0, 255.0) as u8,
                        (col[2] * shade * 255.0).clamp(0.0, 255.0) as u8,
                    ]),
                );
            }
        }
    }
    (MetricDepth::new(depth), rgb, Mask::new(mask))
}

/// The camera of the scene (principal point at the image centre).
pub fn intrinsics(config: &DemoSceneConfig) -> Intrinsics {
    Intrinsics {
        width: config.size.width,
        height: config.size.height,
        fx: config.focal_px,
        fy: config.focal_px,
        cx: (config.size.width as f64 - 1.0) / 2.0,
        cy: (config.size.height as f64 - 1.0) / 2.0,
    }
}

const PALETTE: [V3; 8] = [
    [0.85, 0.2, 0.15],
    [0.2, 0.45, 0.85],
    [0.25, 0.7, 0.3],
    [0.95, 0.8, 0.2],
    [0.6, 0.3, 0.7],
    [0.95, 0.5, 0.15],
    [0.3, 0.75, 0.8],
    [0.9, 0.9, 0.9],
];

/// Random objects for frame `index` (3–5 objects, sizes 3–10 cm, non-overlapping footprints).
pub fn objects_for_frame(config: &DemoSceneConfig, index: usize) -> Vec<Object> {
    let mut rng =
        ChaCha8Rng::seed_from_u64(config.seed.wrapping_mul(1000).wrapping_add(index as u64));
    let count = 3 + rng.random_range(0..3);
    let mut objs: Vec<(f64, f64, f64, Object)> = Vec::new();
    let extent = 0.22;
    let mut tries = 0;
    while objs.len() < count && tries < 200 {
        tries += 1;
        let x = rng.random_range(-extent..extent);
        let y = rng.random_range(-extent * 0.7..extent * 0.7);
        let colour = PALETTE[rng.random_range(0..PALETTE.len())];
        let (shape, r) = match rng.random_range(0..3) {
            0 => {
                let half: V3 = [
                    rng.random_range(0.02..0.05),
                    rng.random_range(0.02..0.05),
                    rng.random_range(0.02..0.06),
                ];
                let r = (half[0] * half[0] + half[1] * half[1]).sqrt();
                (
                    Shape::Box {
                        x,
                        y,
                        half,
                        yaw_rad: rng.random_range(0.0..std::f64::consts::PI),
                    },
                    r,
                )
            }
            1 => {
                let radius = rng.random_range(0.02..0.045);
                (
                    Shape::Cylinder {
                        x,
                        y,
                        radius,
                        height: rng.random_range(0.04..0.12),
                    },
                    radius,
                )
            }
            _ => {
                let radius = rng.random_range(0.02..0.045);
                (Shape::Sphere { x, y, radius }, radius)
            }
        };
        if objs
            .iter()
            .all(|(ox, oy, orr, _)| ((ox - x).powi(2) + (oy - y).powi(2)).sqrt() > orr + r + 0.01)
        {
            objs.push((x, y, r, Object { shape, colour }));
        }
    }
    objs.into_iter().map(|(_, _, _, o)| o).collect()
}

/// Builds the whole demo set in memory (frames `frame_00`, `frame_01`, ...).
pub fn build_scene(config: &DemoSceneConfig) -> LoadedSet {
    let intrinsics = intrinsics(config);
    let frames = (0..config.frames)
        .map(|i| {
            let objects = objects_for_frame(config, i);
            let (gt, rgb, mask) = render(config, &objects);
            LoadedFrame {
                id: format!("frame_{i:02}"),
                rgb: Some(rgb),
                gt,
                mask: Some(mask),
                raw_depth: None,
            }
        })
        .collect();
    LoadedSet {
        name: "demo-scene".into(),
        dir: std::path::PathBuf::from("demo-scene"),
        intrinsics,
        frames,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_depth_is_about_the_configured_distance_and_objects_are_nearer() {
        let c = DemoSceneConfig {
            frames: 2,
            ..Default::default()
        };
        let set = build_scene(&c);
        assert_eq!(set.frames.len(), 2);
        for f in &set.frames {
            let d = &f.gt.depth_m;
            let centre = d[[240, 320]] as f64;
            assert!(f.gt.valid_count() == 640 * 480);
            let m = f.mask.as_ref().unwrap();
            assert!(m.count() > 1000, "objects visible");
            // the table at the centre (or an object in front of it)
            assert!(centre <= 0.701 && centre > 0.5, "centre {centre}");
            // every object pixel is nearer than the table plane behind it would be: check min depth
            let min = d.iter().cloned().fold(f32::INFINITY, f32::min);
            assert!(min > 0.45 && min < 0.69);
        }
    }

    #[test]
    fn sphere_depth_matches_closed_form() {
        // camera looking straight down at a flat table: the sphere top is at distance − 2r
        let c = DemoSceneConfig {
            tilt_x_deg: 0.0,
            tilt_y_deg: 0.0,
            ..Default::default()
        };
        let obj = Object {
            shape: Shape::Sphere {
                x: 0.0,
                y: 0.0,
                radius: 0.05,
            },
            colour: [1.0, 0.0, 0.0],
        };
        let (d, _, m) = render(&c, &[obj]);
        // pixel (319.5, 239.5) is between pixels; the nearest pixel ray is almost axial
        let z = d.depth_m[[240, 320]] as f64;
        assert!((z - (0.7 - 0.1)).abs() < 1e-4, "{z}");
        assert!(m.data()[[240, 320]]);
        assert!((d.depth_m[[5, 5]] as f64 - 0.7).abs() < 1e-6);
    }
}
