//! Organised point cloud (one point per pixel) with surface normals and silhouette edges.
//!
//! The pixel grid makes every neighbourhood query O(1): planners and the scorer project 3-D
//! points back to pixels instead of searching a k-d tree.

use moma_core::{Intrinsics, MetricDepth, is_valid_depth};
use nalgebra::Vector3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{GraspError, Result, positive};

/// A 3-D vector in metres (points) or a unit vector (directions), `f32`.
pub type Vec3 = Vector3<f32>;

/// How normals and edges are computed from the depth map.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CloudConfig {
    /// Distance to the neighbours whose difference vectors span a pixel's tangent plane, pixels.
    /// Default 2.
    pub normal_step_px: usize,
    /// Largest depth difference between a pixel and a neighbour that still counts as the same
    /// surface for its normal, metres. A larger jump is a discontinuity: the normal then uses the
    /// one-sided difference on the other side, or is left unknown. Default 0.01 m.
    pub normal_max_jump_m: f32,
    /// Depth jump between 8-neighbours that marks a silhouette edge (the nearer pixel is the
    /// edge pixel), metres. Default 0.005 m (gqcnn uses a 2.5 mm gradient on smoothed depth).
    pub edge_jump_m: f32,
    /// A [`crate::Scene`] computes normals and edges only in the bounding box of its object pixels
    /// grown by this margin (the rest of the image is never queried for them), pixels. Default 48
    /// (a 10 mm cup radius spans 30 px at 0.2 m with f = 600 px).
    pub object_margin_px: usize,
}

impl Default for CloudConfig {
    fn default() -> Self {
        Self {
            normal_step_px: 2,
            normal_max_jump_m: 0.01,
            edge_jump_m: 0.005,
            object_margin_px: 48,
        }
    }
}

impl CloudConfig {
    /// Checks every threshold is positive.
    ///
    /// # Errors
    /// [`GraspError::InvalidConfig`] naming the field.
    pub fn validate(&self) -> Result<()> {
        if self.normal_step_px == 0 {
            return Err(GraspError::InvalidConfig(
                "normal_step_px must be >= 1".into(),
            ));
        }
        positive(
            "normal_max_jump_m",
            self.normal_max_jump_m,
            GraspError::InvalidConfig,
        )?;
        positive("edge_jump_m", self.edge_jump_m, GraspError::InvalidConfig)
    }
}

/// One camera-frame point per pixel (x right, y down, z forward, metres), row-major
/// (`index = v * width + u`).
#[derive(Debug, Clone)]
pub struct OrganisedCloud {
    pub(crate) width: usize,
    pub(crate) height: usize,
    pub(crate) fx: f32,
    pub(crate) fy: f32,
    pub(crate) cx: f32,
    pub(crate) cy: f32,
    pub(crate) edge_jump_m: f32,
    pub(crate) points: Vec<Vec3>,
    pub(crate) valid: Vec<bool>,
    pub(crate) normals: Vec<Vec3>,
    pub(crate) near_edge: Vec<bool>,
}

impl OrganisedCloud {
    /// Back-projects `depth` with `intrinsics` and computes normals and silhouette edges.
    ///
    /// Normals are unit vectors pointing towards the camera (`n · p < 0`), from the cross product
    /// of the horizontal and vertical neighbour differences at `normal_step_px`, using only
    /// neighbours within `normal_max_jump_m` in depth (one-sided differences at a discontinuity or a
    /// hole); a pixel with no usable neighbour in a direction has the zero vector (unknown).
    ///
    /// # Errors
    /// Invalid intrinsics or config, intrinsics of another size, an all-invalid depth map.
    pub fn from_depth(
        depth: &MetricDepth,
        intrinsics: &Intrinsics,
        config: &CloudConfig,
    ) -> Result<Self> {
        Self::build(depth, intrinsics, config, true)
    }

    /// Points only (normals unknown, no edges) when `with_normals` is false; see
    /// [`Self::compute_normals`].
    pub(crate) fn build(
        depth: &MetricDepth,
        intrinsics: &Intrinsics,
        config: &CloudConfig,
        with_normals: bool,
    ) -> Result<Self> {
        intrinsics.validate().map_err(GraspError::Intrinsics)?;
        config.validate()?;
        let size = depth.size();
        if intrinsics.size() != size {
            return Err(GraspError::SizeMismatch {
                what: "camera intrinsics",
                expected: size,
                got: intrinsics.size(),
            });
        }
        let (width, height) = (size.width, size.height);
        let (fx, fy) = (intrinsics.fx as f32, intrinsics.fy as f32);
        let (cx, cy) = (intrinsics.cx as f32, intrinsics.cy as f32);
        let n = width * height;
        let mut points = vec![Vec3::zeros(); n];
        let mut valid = vec![false; n];
        for (v, row) in depth.depth_m.outer_iter().enumerate() {
            let y = (v as f32 - cy) / fy;
            for (u, &z) in row.iter().enumerate() {
                if is_valid_depth(z) {
                    let i = v * width + u;
                    points[i] = Vec3::new((u as f32 - cx) / fx * z, y * z, z);
                    valid[i] = true;
                }
            }
        }
        if !valid.iter().any(|&b| b) {
            return Err(GraspError::AllInvalidDepth);
        }
        let mut cloud = Self {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            edge_jump_m: config.edge_jump_m,
            points,
            valid,
            normals: vec![Vec3::zeros(); n],
            near_edge: vec![false; n],
        };
        if with_normals {
            cloud.compute_normals(0, width, 0, height, config);
        }
        Ok(cloud)
    }

    /// Computes normals and edge flags of the pixels `u0..u1` × `v0..v1` (the rest keep theirs).
    pub(crate) fn compute_normals(
        &mut self,
        u0: usize,
        u1: usize,
        v0: usize,
        v1: usize,
        config: &CloudConfig,
    ) {
        let width = self.width;
        let mut normals = std::mem::take(&mut self.normals);
        let mut near_edge = std::mem::take(&mut self.near_edge);
        let this = &*self;
        normals
            .par_chunks_mut(width)
            .zip(near_edge.par_chunks_mut(width))
            .enumerate()
            .skip(v0)
            .take(v1.saturating_sub(v0))
            .for_each(|(v, (nrow, erow))| {
                for u in u0..u1 {
                    nrow[u] = this.normal_at(u, v, config);
                    erow[u] = this.edge_at(u, v);
                }
            });
        self.normals = normals;
        self.near_edge = near_edge;
    }

    /// Image width, pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Image height, pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Row-major index of pixel `(u, v)`.
    #[inline]
    pub fn index(&self, u: usize, v: usize) -> usize {
        v * self.width + u
    }

    /// The point of pixel `index` (camera frame, metres); meaningful only where [`Self::is_valid`].
    #[inline]
    pub fn point(&self, index: usize) -> Vec3 {
        self.points[index]
    }

    /// Whether pixel `index` has valid depth.
    #[inline]
    pub fn is_valid(&self, index: usize) -> bool {
        self.valid[index]
    }

    /// Unit surface normal at pixel `index`, pointing towards the camera; `None` where unknown.
    #[inline]
    pub fn normal(&self, index: usize) -> Option<Vec3> {
        let n = self.normals[index];
        (n != Vec3::zeros()).then_some(n)
    }

    /// Whether pixel `index` is the near side of a depth discontinuity (or borders a hole).
    #[inline]
    pub fn is_near_edge(&self, index: usize) -> bool {
        self.near_edge[index]
    }

    /// The pixel index a camera-frame point projects to (nearest pixel centre), or `None` when it is
    /// behind the camera or outside the image.
    #[inline]
    pub fn project(&self, p: &Vec3) -> Option<usize> {
        if p.z <= 1e-6 {
            return None;
        }
        let u = (self.fx * p.x / p.z + self.cx).round();
        let v = (self.fy * p.y / p.z + self.cy).round();
        if u < 0.0 || v < 0.0 || u >= self.width as f32 || v >= self.height as f32 {
            return None;
        }
        Some(self.index(u as usize, v as usize))
    }

    /// Sub-pixel projection `(u, v)` of a point in front of the camera (pixels), unclamped.
    #[inline]
    pub(crate) fn project_uv(&self, p: &Vec3) -> Option<(f32, f32)> {
        (p.z > 1e-6).then(|| (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy))
    }

    fn tangent(
        &self,
        i: usize,
        prev: Option<usize>,
        next: Option<usize>,
        max_jump: f32,
    ) -> Option<Vec3> {
        let p = self.points[i];
        let ok = |j: &usize| self.valid[*j] && (self.points[*j].z - p.z).abs() <= max_jump;
        match (prev.filter(ok), next.filter(ok)) {
            (Some(a), Some(b)) => Some(self.points[b] - self.points[a]),
            (Some(a), None) => Some(p - self.points[a]),
            (None, Some(b)) => Some(self.points[b] - p),
            (None, None) => None,
        }
    }

    fn normal_at(&self, u: usize, v: usize, config: &CloudConfig) -> Vec3 {
        let i = self.index(u, v);
        if !self.valid[i] {
            return Vec3::zeros();
        }
        let s = config.normal_step_px;
        let left = (u >= s).then(|| self.index(u - s, v));
        let right = (u + s < self.width).then(|| self.index(u + s, v));
        let up = (v >= s).then(|| self.index(u, v - s));
        let down = (v + s < self.height).then(|| self.index(u, v + s));
        let (Some(tx), Some(ty)) = (
            self.tangent(i, left, right, config.normal_max_jump_m),
            self.tangent(i, up, down, config.normal_max_jump_m),
        ) else {
            return Vec3::zeros();
        };
        let n = ty.cross(&tx);
        let norm = n.norm();
        if norm.is_nan() || norm <= 1e-12 {
            return Vec3::zeros();
        }
        let n = n / norm;
        if n.dot(&self.points[i]) > 0.0 { -n } else { n }
    }

    /// The plane of the surface patch within `radius_m` (3-D distance) of pixel `index`'s point:
    /// its unit normal, pointing towards the camera, and the RMS distance of the patch's points
    /// to it (metres). A suction cup conforms to its whole footprint, so on a noisy depth this
    /// is the normal it seals on; the per-pixel normal ([`Self::normal`]) follows bumps of a few
    /// pixels. `None` where the pixel is invalid or fewer than 6 points support the plane. At
    /// most 17 points per row and column of the window are read.
    pub(crate) fn patch_plane(&self, index: usize, radius_m: f32) -> Option<(Vec3, f32)> {
        if !self.valid[index] {
            return None;
        }
        let p = self.points[index];
        let (u, v) = (index % self.width, index / self.width);
        let r_px = (radius_m / self.metres_per_px(p.z)).ceil().max(1.0) as usize;
        let step = (r_px / 8).max(1);
        let mut pts = Vec::with_capacity((2 * r_px / step + 1).pow(2));
        for nv in (v.saturating_sub(r_px)..=(v + r_px).min(self.height - 1)).step_by(step) {
            for nu in (u.saturating_sub(r_px)..=(u + r_px).min(self.width - 1)).step_by(step) {
                let j = nv * self.width + nu;
                if self.valid[j] && (self.points[j] - p).norm_squared() <= radius_m * radius_m {
                    pts.push(self.points[j]);
                }
            }
        }
        if pts.len() < 6 {
            return None;
        }
        let (n, d) = crate::plane::refit(&pts)?;
        let ms = pts.iter().map(|q| (n.dot(q) + d).powi(2)).sum::<f32>() / pts.len() as f32;
        Some((if n.dot(&p) > 0.0 { -n } else { n }, ms.sqrt()))
    }

    /// Near side of a depth jump: some valid 8-neighbour is farther by more than the edge jump, or
    /// at least 3 of the 8 neighbours are holes (isolated invalid pixels are not edges).
    fn edge_at(&self, u: usize, v: usize) -> bool {
        let i = self.index(u, v);
        if !self.valid[i] {
            return false;
        }
        let z = self.points[i].z;
        let mut holes = 0;
        for nv in v.saturating_sub(1)..=(v + 1).min(self.height - 1) {
            for nu in u.saturating_sub(1)..=(u + 1).min(self.width - 1) {
                let j = self.index(nu, nv);
                if j == i {
                    continue;
                }
                if !self.valid[j] {
                    holes += 1;
                } else if self.points[j].z - z > self.edge_jump_m {
                    return true;
                }
            }
        }
        holes >= 3
    }

    /// Outward normal of a silhouette at pixel `index`, in the image: the centroid direction of the
    /// farther (or missing) pixels in the disc of `radius_px` (a disc, so that a straight edge gives
    /// its exact perpendicular), turned into a camera-frame direction at the pixel's depth. `None`
    /// when no neighbour is farther by more than the edge jump.
    pub(crate) fn silhouette_direction(&self, index: usize, radius_px: usize) -> Option<Vec3> {
        self.silhouette_direction_with(index, radius_px, self.edge_jump_m)
    }

    /// [`Self::silhouette_direction`] with pixels farther by more than `jump_m` counting as the
    /// far side.
    pub(crate) fn silhouette_direction_with(
        &self,
        index: usize,
        radius_px: usize,
        jump_m: f32,
    ) -> Option<Vec3> {
        if !self.valid[index] {
            return None;
        }
        let (u, v) = ((index % self.width) as i64, (index / self.width) as i64);
        let z = self.points[index].z;
        let r = radius_px as i64;
        let r2 = r * r + r / 2;
        let (mut gu, mut gv) = (0i64, 0i64);
        for dv in -r..=r {
            for du in -r..=r {
                let (nu, nv) = (u + du, v + dv);
                if du * du + dv * dv > r2
                    || nu < 0
                    || nv < 0
                    || nu >= self.width as i64
                    || nv >= self.height as i64
                {
                    continue;
                }
                let j = self.index(nu as usize, nv as usize);
                if !self.valid[j] || self.points[j].z - z > jump_m {
                    gu += du;
                    gv += dv;
                }
            }
        }
        let d = Vec3::new(gu as f32 * z / self.fx, gv as f32 * z / self.fy, 0.0);
        let norm = d.norm();
        (norm > 1e-9).then(|| d / norm)
    }

    /// Whether a valid pixel within `window_px` (Chebyshev) of `index` lies farther than it by more
    /// than `jump_m`: a silhouette spread over a few pixels (soft edges of predicted depth).
    pub(crate) fn is_soft_edge(&self, index: usize, window_px: usize, jump_m: f32) -> bool {
        if !self.valid[index] {
            return false;
        }
        let (u, v) = (index % self.width, index / self.width);
        let z = self.points[index].z;
        (v.saturating_sub(window_px)..=(v + window_px).min(self.height - 1)).any(|nv| {
            (u.saturating_sub(window_px)..=(u + window_px).min(self.width - 1)).any(|nu| {
                let j = self.index(nu, nv);
                self.valid[j] && self.points[j].z - z > jump_m
            })
        })
    }

    /// Whether pixel `index` lies inside a soft silhouette: within `window_px` some valid pixel is
    /// farther and some nearer by more than `jump_m` (a blend of the object and what lies behind
    /// it, which predicted depth puts in mid-air behind the object).
    pub(crate) fn is_mixed(&self, index: usize, window_px: usize, jump_m: f32) -> bool {
        if !self.valid[index] {
            return false;
        }
        let (u, v) = (index % self.width, index / self.width);
        let z = self.points[index].z;
        let (mut far, mut near) = (false, false);
        for nv in v.saturating_sub(window_px)..=(v + window_px).min(self.height - 1) {
            for nu in u.saturating_sub(window_px)..=(u + window_px).min(self.width - 1) {
                let j = self.index(nu, nv);
                if self.valid[j] {
                    let d = self.points[j].z - z;
                    far |= d > jump_m;
                    near |= d < -jump_m;
                }
            }
        }
        far && near
    }

    /// Metric size of one pixel at depth `z_m` (metres per pixel, along u).
    #[inline]
    pub(crate) fn metres_per_px(&self, z_m: f32) -> f32 {
        z_m / self.fx
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use moma_core::Intrinsics;
    use ndarray::Array2;

    fn k() -> Intrinsics {
        Intrinsics {
            width: 160,
            height: 120,
            fx: 150.0,
            fy: 150.0,
            cx: 79.5,
            cy: 59.5,
        }
    }

    /// On a plane n·p = d rendered exactly, the patch plane is that plane (normal towards the
    /// camera, RMS 0); points across a depth step farther than the radius stay out of it.
    #[test]
    fn the_patch_plane_of_a_tilted_plane_is_exact_and_ignores_a_step_beyond_the_radius() {
        let k = k();
        let n = Vector3::new(0.2f64, -0.3, -1.0).normalize(); // towards the camera
        let d = -0.6; // n·p = d
        let depth = Array2::from_shape_fn((k.height, k.width), |(v, u)| {
            let ray = Vector3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
            let z = d / n.dot(&ray);
            // a 50 mm step up (towards the camera) right of column 100
            (if u > 100 { z - 0.05 } else { z }) as f32
        });
        let cloud =
            OrganisedCloud::from_depth(&MetricDepth::new(depth), &k, &CloudConfig::default())
                .unwrap();
        let i = cloud.index(70, 60);
        let (normal, rms) = cloud.patch_plane(i, 0.02).unwrap();
        let angle = normal.cast::<f64>().dot(&n).clamp(-1.0, 1.0).acos();
        assert!(
            angle.to_degrees() < 0.05,
            "normal {normal:?} is {angle} rad off"
        );
        assert!(rms < 1e-5, "rms {rms} m on an exact plane");
        // next to the step: the step's points are more than 20 mm away in 3-D
        let j = cloud.index(98, 60);
        let (normal, rms) = cloud.patch_plane(j, 0.02).unwrap();
        assert!(normal.cast::<f64>().dot(&n) > 0.9999, "{normal:?}");
        assert!(rms < 1e-5);
        // an invalid pixel has no patch
        let mut holes = Array2::from_elem((k.height, k.width), 0.6f32);
        holes[[60, 70]] = 0.0;
        let cloud =
            OrganisedCloud::from_depth(&MetricDepth::new(holes), &k, &CloudConfig::default())
                .unwrap();
        assert!(cloud.patch_plane(cloud.index(70, 60), 0.02).is_none());
    }
}
