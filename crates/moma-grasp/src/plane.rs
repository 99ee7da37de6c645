//! The dominant support plane (table or tote floor): seeded RANSAC, then a least-squares refit.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::cloud::{OrganisedCloud, Vec3};
use crate::error::{GraspError, Result, positive};

/// RANSAC settings of the support-plane fit.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PlaneConfig {
    /// RANSAC hypotheses (3 random points each). Default 200.
    pub iterations: usize,
    /// Largest point-to-plane distance of an inlier, metres. Default 0.005 m.
    pub inlier_threshold_m: f32,
    /// At most this many points (an even stride over the valid region) take part. Default 5000.
    pub max_points: usize,
    /// Fewest inliers (among the points taking part) for a plane to count as found. Default 50.
    pub min_inliers: usize,
    /// Seed of the hypothesis sampler. Default 0.
    pub seed: u64,
}

impl Default for PlaneConfig {
    fn default() -> Self {
        Self {
            iterations: 200,
            inlier_threshold_m: 0.005,
            max_points: 5000,
            min_inliers: 50,
            seed: 0,
        }
    }
}

impl PlaneConfig {
    /// Checks the settings.
    ///
    /// # Errors
    /// [`GraspError::InvalidConfig`] naming the field.
    pub fn validate(&self) -> Result<()> {
        if self.iterations == 0 || self.max_points < 3 {
            return Err(GraspError::InvalidConfig(
                "plane iterations must be >= 1 and max_points >= 3".into(),
            ));
        }
        positive(
            "inlier_threshold_m",
            self.inlier_threshold_m,
            GraspError::InvalidConfig,
        )
    }
}

/// The plane `normal · p + offset_m = 0` (camera frame); `normal` is "up": unit, pointing to the
/// camera's side, so [`SupportPlane::height_m`] is positive above the plane.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SupportPlane {
    /// Unit normal towards the camera ("up").
    pub normal: [f32; 3],
    /// Plane offset, metres (the camera's height above the plane).
    pub offset_m: f32,
    /// Inliers of the final fit among the points that took part.
    pub inliers: usize,
    /// Points that took part.
    pub points_used: usize,
    /// RMS distance of the inliers to the plane, metres.
    pub rms_m: f32,
}

impl SupportPlane {
    /// "Up" as a vector.
    #[inline]
    pub fn up(&self) -> Vec3 {
        Vec3::from(self.normal)
    }

    /// Signed height of `p` above the plane along "up", metres.
    #[inline]
    pub fn height_m(&self, p: &Vec3) -> f32 {
        self.up().dot(p) + self.offset_m
    }
}

/// Least-squares plane of `points` (smallest principal axis): unit normal `n` and offset `d`
/// with `n·p + d = 0`; `None` for fewer than 3 points or a degenerate set.
pub(crate) fn refit(points: &[Vec3]) -> Option<(Vec3, f32)> {
    if points.len() < 3 {
        return None;
    }
    let n = points.len() as f64;
    let mut c = Vector3::<f64>::zeros();
    for p in points {
        c += p.cast::<f64>();
    }
    c /= n;
    let mut cov = Matrix3::<f64>::zeros();
    for p in points {
        let d = p.cast::<f64>() - c;
        cov += d * d.transpose();
    }
    let eig = SymmetricEigen::new(cov);
    let k = eig.eigenvalues.imin();
    let normal = eig.eigenvectors.column(k).into_owned();
    let norm = normal.norm();
    if !norm.is_finite() || norm < 1e-12 {
        return None;
    }
    let normal = normal / norm;
    Some((normal.cast::<f32>(), -(normal.dot(&c)) as f32))
}

/// Fits the dominant plane on the valid pixels of `cloud` inside `region` (all valid pixels when
/// `None`): RANSAC with `config.seed`, then two least-squares refits on the inliers. Returns
/// `None` when fewer than `config.min_inliers` points support any plane.
///
/// # Errors
/// Invalid `config`.
pub fn fit_support_plane(
    cloud: &OrganisedCloud,
    region: Option<&[bool]>,
    config: &PlaneConfig,
) -> Result<Option<SupportPlane>> {
    config.validate()?;
    let all: Vec<usize> = (0..cloud.valid.len())
        .filter(|&i| cloud.valid[i] && region.is_none_or(|r| r[i]))
        .collect();
    let stride = all.len().div_ceil(config.max_points).max(1);
    let pts: Vec<Vec3> = all
        .iter()
        .step_by(stride)
        .map(|&i| cloud.points[i])
        .collect();
    if pts.len() < 3 {
        return Ok(None);
    }
    let thr = config.inlier_threshold_m;
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
    let mut best: Option<(usize, Vec3, f32)> = None;
    for _ in 0..config.iterations {
        let a = pts[rng.random_range(0..pts.len())];
        let b = pts[rng.random_range(0..pts.len())];
        let c = pts[rng.random_range(0..pts.len())];
        let n = (b - a).cross(&(c - a));
        let norm = n.norm();
        if norm.is_nan() || norm < 1e-9 {
            continue;
        }
        let n = n / norm;
        let d = -n.dot(&a);
        let count = pts.iter().filter(|p| (n.dot(p) + d).abs() < thr).count();
        if best.is_none_or(|(bc, _, _)| count > bc) {
            best = Some((count, n, d));
        }
    }
    let Some((_, mut n, mut d)) = best else {
        return Ok(None);
    };
    let mut inliers: Vec<Vec3> = Vec::new();
    for _ in 0..2 {
        inliers.clear();
        inliers.extend(pts.iter().filter(|p| (n.dot(p) + d).abs() < thr));
        match refit(&inliers) {
            Some((n2, d2)) => (n, d) = (n2, d2),
            None => return Ok(None),
        }
    }
    inliers.clear();
    inliers.extend(pts.iter().filter(|p| (n.dot(p) + d).abs() < thr));
    if inliers.len() < config.min_inliers {
        return Ok(None);
    }
    if d < 0.0 {
        n = -n;
        d = -d;
    }
    let rms =
        (inliers.iter().map(|p| (n.dot(p) + d).powi(2)).sum::<f32>() / inliers.len() as f32).sqrt();
    Ok(Some(SupportPlane {
        normal: [n.x, n.y, n.z],
        offset_m: d,
        inliers: inliers.len(),
        points_used: pts.len(),
        rms_m: rms,
    }))
}
