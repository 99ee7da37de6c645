//! Footprint candidates for the parallel-jaw planner: top-down grasps that do not rely on sharp
//! depth edges or on per-pixel surface normals, for depth aligned from a depth-model prediction
//! (soft silhouettes over 3–5 px, noisy surfaces, a few mm of global error; docs/method.md §6).
//!
//! Per object component (its top-view footprint = the object points projected along "up" onto
//! the support plane):
//! 1. PCA of the footprint gives its narrow (minor) and long (major) axes: the closing axes are
//!    the minor axis turned by [`FootprintConfig::axis_angles_deg`], the grasp centres lie on the
//!    major axis at [`FootprintConfig::centre_offsets`] of its half length.
//! 2. For each (centre, axis) the object pixels under the finger (a strip of the finger's height
//!    across the closing line) give the footprint extent along the axis; the opening leaves
//!    [`FootprintConfig::clearance_m`] free on each side. The contacts are the extreme object
//!    pixels of a narrow band around the closing line.
//! 3. Contact normals come from the footprint's boundary (mask or object labels, not depth jumps
//!    nor per-pixel normals): its extent along the closing axis in two bands
//!    [`FootprintConfig::normal_offset_m`] either side of the closing line gives the boundary's
//!    slope at each contact, `tan` of its angle to the closing line, which must not exceed
//!    `planner_mu`.
//! 4. The closing line runs [`FootprintConfig::grasp_depth_m`] below the smoothed top (a high
//!    percentile of the strip's heights), with the fingertips at least
//!    [`FootprintConfig::table_clearance_m`] above the support plane.
//! 5. Collisions of fingers and palm with the planning cloud are tested with the fingertips
//!    shortened by [`FootprintConfig::collision_margin_m`] (noise on the table and the soft skirt
//!    of the silhouette must not reject every grasp); the grasp must also hold enough object points.

use serde::{Deserialize, Serialize};

use crate::cloud::Vec3;
use crate::contact::{JawPose, perpendiculars};
use crate::error::{GraspError, Result, positive};
use crate::grasp::FailureReason;
use crate::gripper::ParallelJaw;
use crate::scene::Scene;

/// Settings of the footprint candidates (see the module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FootprintConfig {
    /// Whether footprint candidates are generated at all. Default true.
    pub enabled: bool,
    /// Closing axes: the footprint's minor axis turned about "up" by these angles, degrees.
    /// Default `[0, 20, -20, 45, -45, 90]`.
    pub axis_angles_deg: Vec<f32>,
    /// Grasp centres along the footprint's major axis, as fractions of its half length (from the
    /// footprint centre), dimensionless. Default `[0, 0.3, -0.3, 0.6, -0.6]`.
    pub centre_offsets: Vec<f32>,
    /// Depth of the closing line below the smoothed top of the object under the fingers, metres.
    /// Default 0.015 m.
    pub grasp_depth_m: f32,
    /// Least depth of the closing line below that top, metres (shorter objects give no footprint
    /// candidate). Default 0.004 m.
    pub min_grasp_depth_m: f32,
    /// The smoothed top is this quantile of the heights above the plane of the object pixels under
    /// the fingers, in `(0, 1]`. Default 0.9.
    pub top_quantile: f32,
    /// Least height of the fingertips above the support plane, metres. Default 0.008 m.
    pub table_clearance_m: f32,
    /// Free space between each finger and the footprint before closing, metres. Default 0.012 m
    /// (a σ = 1.5 px soft edge spreads over ≈ 6 px ≈ 7 mm at 0.7 m with f = 600 px).
    pub clearance_m: f32,
    /// Half width of the band around the closing line whose extreme object pixels are the planned
    /// contacts, metres. Default 0.003 m.
    pub contact_band_m: f32,
    /// The footprint's boundary direction at a contact is measured from the footprint's extent
    /// along the closing axis in two bands this far on either side of the closing line, metres.
    /// Default 0.005 m.
    pub normal_offset_m: f32,
    /// Only object pixels with every pixel of the same object within this (Chebyshev) distance
    /// enter the footprint: soft silhouettes blend object and background depth over a few pixels,
    /// and those blended points lie far behind the object along their rays. The footprint extent is
    /// grown back by this many pixels (at the contact's depth). Pixels. Default 3.
    pub erode_px: usize,
    /// The planning collision test shortens the fingertips by this, metres. Default 0.005 m.
    pub collision_margin_m: f32,
}

impl Default for FootprintConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            axis_angles_deg: vec![0.0, 20.0, -20.0, 45.0, -45.0, 90.0],
            centre_offsets: vec![0.0, 0.3, -0.3, 0.6, -0.6],
            grasp_depth_m: 0.015,
            min_grasp_depth_m: 0.004,
            top_quantile: 0.9,
            table_clearance_m: 0.008,
            clearance_m: 0.012,
            contact_band_m: 0.003,
            normal_offset_m: 0.005,
            erode_px: 3,
            collision_margin_m: 0.005,
        }
    }
}

impl FootprintConfig {
    /// Checks the settings.
    ///
    /// # Errors
    /// [`GraspError::InvalidConfig`] naming the field.
    pub fn validate(&self) -> Result<()> {
        let e = GraspError::InvalidConfig;
        positive("footprint.grasp_depth_m", self.grasp_depth_m, e)?;
        positive("footprint.min_grasp_depth_m", self.min_grasp_depth_m, e)?;
        positive("footprint.table_clearance_m", self.table_clearance_m, e)?;
        positive("footprint.clearance_m", self.clearance_m, e)?;
        positive("footprint.contact_band_m", self.contact_band_m, e)?;
        if !(self.collision_margin_m.is_finite() && self.collision_margin_m >= 0.0) {
            return Err(e(format!(
                "footprint.collision_margin_m = {} must be >= 0",
                self.collision_margin_m
            )));
        }
        if !(self.top_quantile > 0.0 && self.top_quantile <= 1.0) {
            return Err(e(format!(
                "footprint.top_quantile = {} must lie in (0, 1]",
                self.top_quantile
            )));
        }
        positive("footprint.normal_offset_m", self.normal_offset_m, e)?;
        if self
            .axis_angles_deg
            .iter()
            .chain(&self.centre_offsets)
            .any(|x| !x.is_finite())
        {
            return Err(e(
                "footprint.axis_angles_deg and centre_offsets must be finite".into(),
            ));
        }
        Ok(())
    }
}

/// A footprint candidate: the pose and the friction its footprint normals need.
#[derive(Debug, Clone, Copy)]
pub(crate) struct FootprintGrasp {
    pub pose: JawPose,
    pub mu_needed: f32,
    pub label: u32,
}

/// One object pixel of a footprint: index, in-plane coordinates (e1, e2) and height, metres.
#[derive(Debug, Clone, Copy)]
struct Px {
    i: usize,
    x: f32,
    y: f32,
    h: f32,
}

/// Object pixels whose Chebyshev `r`-neighbourhood lies inside the image and holds only pixels of
/// their own object (separable min filter over rows, then columns).
fn eroded(scene: &Scene, r: usize) -> Vec<bool> {
    let c = &scene.cloud;
    let (w, h) = (c.width, c.height);
    let n = w * h;
    if r == 0 {
        return (0..n).map(|i| scene.is_object(i)).collect();
    }
    // Rows: pixel keeps its label when the whole horizontal window has that label.
    let mut row_ok = vec![false; n];
    for v in 0..h {
        for u in r..w.saturating_sub(r) {
            let i = c.index(u, v);
            let l = scene.label(i);
            row_ok[i] = l != 0 && (u - r..=u + r).all(|nu| scene.label(c.index(nu, v)) == l);
        }
    }
    let mut out = vec![false; n];
    for v in r..h.saturating_sub(r) {
        for u in 0..w {
            let i = c.index(u, v);
            out[i] = row_ok[i]
                && (v - r..=v + r).all(|nv| {
                    let j = c.index(u, nv);
                    row_ok[j] && scene.label(j) == scene.label(i)
                });
        }
    }
    out
}

/// Quantile `q` of `values` (sorted in place), nearest rank.
fn quantile(values: &mut [f32], q: f32) -> f32 {
    values.sort_unstable_by(f32::total_cmp);
    let k = ((values.len() as f32 - 1.0) * q).round() as usize;
    values[k.min(values.len() - 1)]
}

/// Footprint candidates of every object of `scene`, in a deterministic order; rejected ones with
/// their reason.
pub(crate) fn footprint_candidates(
    scene: &Scene,
    jaw: &ParallelJaw,
    planner_mu: f32,
    config: &FootprintConfig,
    exec: &crate::contact::ExecConfig,
    soft: &crate::contact::Soft,
) -> Vec<std::result::Result<FootprintGrasp, FailureReason>> {
    let Some(plane) = scene.plane else {
        return Vec::new();
    };
    let up = plane.up();
    let (e1, e2) = perpendiculars(&up);
    let n_labels = scene.components().len();
    let mut per_label: Vec<Vec<Px>> = vec![Vec::new(); n_labels];
    let mut all_label: Vec<Vec<Px>> = vec![Vec::new(); n_labels];
    let cloud = &scene.cloud;
    let interior = eroded(scene, config.erode_px);
    for (i, (p, &inside)) in cloud.points.iter().zip(&interior).enumerate() {
        let l = scene.label(i);
        if l == 0 {
            continue;
        }
        let px = Px {
            i,
            x: p.dot(&e1),
            y: p.dot(&e2),
            h: plane.height_m(p),
        };
        all_label[l as usize - 1].push(px);
        if inside {
            per_label[l as usize - 1].push(px);
        }
    }
    // The plane point below in-plane coordinates (x, y): x e1 + y e2 − offset · up.
    let on_plane = |x: f32, y: f32| e1 * x + e2 * y - up * plane.offset_m;
    let mut out = Vec::new();
    // Shortened fingertips for the planning collision test (same finger base and palm).
    let margin = config
        .collision_margin_m
        .min(jaw.contact_to_tip_m + jaw.finger_length_m * 0.5);
    let test_jaw = ParallelJaw {
        contact_to_tip_m: jaw.contact_to_tip_m - margin,
        finger_length_m: jaw.finger_length_m - margin,
        ..*jaw
    };
    for (k, (pxs, all)) in per_label.iter().zip(&all_label).enumerate() {
        // Objects too thin to erode keep all their pixels.
        let pxs = if pxs.len() >= 3 { pxs } else { all };
        if pxs.len() < 3 {
            continue;
        }
        let label = k as u32 + 1;
        let n = pxs.len() as f64;
        let (mx, my) = pxs.iter().fold((0.0f64, 0.0f64), |(a, b), p| {
            (a + p.x as f64, b + p.y as f64)
        });
        let (mx, my) = (mx / n, my / n);
        let (mut sxx, mut sxy, mut syy) = (0.0f64, 0.0f64, 0.0f64);
        for p in pxs {
            let (dx, dy) = (p.x as f64 - mx, p.y as f64 - my);
            sxx += dx * dx;
            sxy += dx * dy;
            syy += dy * dy;
        }
        // Major axis angle of the 2×2 covariance.
        let theta = 0.5 * (2.0 * sxy).atan2(sxx - syy);
        let (major, minor) = (
            (theta.cos() as f32, theta.sin() as f32),
            (-theta.sin() as f32, theta.cos() as f32),
        );
        let (mut lo, mut hi) = (f32::MAX, f32::MIN);
        for p in pxs {
            let t = (p.x - mx as f32) * major.0 + (p.y - my as f32) * major.1;
            lo = lo.min(t);
            hi = hi.max(t);
        }
        let half_len = 0.5 * (hi - lo);
        let mid = 0.5 * (hi + lo);
        for &f in &config.centre_offsets {
            let s = mid + f * half_len;
            let (cx, cy) = (mx as f32 + major.0 * s, my as f32 + major.1 * s);
            for &ang in &config.axis_angles_deg {
                let (sa, ca) = ang.to_radians().sin_cos();
                let b2 = (minor.0 * ca - minor.1 * sa, minor.0 * sa + minor.1 * ca);
                out.push(one_candidate(
                    scene,
                    pxs,
                    label,
                    (cx, cy),
                    b2,
                    &OneCtx {
                        soft,
                        up,
                        e1,
                        e2,
                        on_plane: &on_plane,
                        jaw,
                        test_jaw: &test_jaw,
                        planner_mu,
                        config,
                        exec,
                    },
                ));
            }
        }
    }
    out
}

struct OneCtx<'a> {
    soft: &'a crate::contact::Soft,
    up: Vec3,
    e1: Vec3,
    e2: Vec3,
    on_plane: &'a dyn Fn(f32, f32) -> Vec3,
    jaw: &'a ParallelJaw,
    test_jaw: &'a ParallelJaw,
    planner_mu: f32,
    config: &'a FootprintConfig,
    exec: &'a crate::contact::ExecConfig,
}

fn one_candidate(
    scene: &Scene,
    pxs: &[Px],
    label: u32,
    centre: (f32, f32),
    b2: (f32, f32),
    ctx: &OneCtx<'_>,
) -> std::result::Result<FootprintGrasp, FailureReason> {
    let cfg = ctx.config;
    let jaw = ctx.jaw;
    let half_h = jaw.finger_height_m / 2.0;
    let (mut t0, mut t1) = (f32::MAX, f32::MIN);
    let (mut c0, mut c1) = ((f32::MAX, 0usize), (f32::MIN, 0usize));
    let mut heights = Vec::new();
    // Extent (min, max along the axis) in the bands at −offset and +offset across the line.
    let (off, band) = (cfg.normal_offset_m, cfg.contact_band_m);
    let mut side = [(f32::MAX, f32::MIN); 2];
    for p in pxs {
        let (dx, dy) = (p.x - centre.0, p.y - centre.1);
        let t = dx * b2.0 + dy * b2.1;
        let sperp = -dx * b2.1 + dy * b2.0;
        for (k, sgn) in [-1.0f32, 1.0].into_iter().enumerate() {
            if (sperp - sgn * off).abs() <= band {
                side[k].0 = side[k].0.min(t);
                side[k].1 = side[k].1.max(t);
            }
        }
        let perp = sperp.abs();
        if perp > half_h {
            continue;
        }
        t0 = t0.min(t);
        t1 = t1.max(t);
        heights.push(p.h);
        if perp <= cfg.contact_band_m {
            if t < c0.0 {
                c0 = (t, p.i);
            }
            if t > c1.0 {
                c1 = (t, p.i);
            }
        }
    }
    if heights.is_empty() || c0.0 > c1.0 {
        return Err(FailureReason::MissedObject);
    }
    let t_mid = 0.5 * (c0.0 + c1.0);
    let grow = cfg.erode_px as f32 * scene.cloud.metres_per_px(scene.cloud.points[c0.1].z);
    let half_w = (t1 - t_mid).max(t_mid - t0) + grow + cfg.clearance_m;
    let width = 2.0 * half_w;
    if width > jaw.stroke_m {
        return Err(FailureReason::NotAntipodal);
    }
    // Friction from the footprint boundary's slope at each contact: tan of the angle between
    // the boundary normal and the closing line.
    let b = ctx.e1 * b2.0 + ctx.e2 * b2.1;
    if side.iter().any(|(lo, hi)| lo > hi) {
        return Err(FailureReason::NotAntipodal);
    }
    let slope0 = (side[1].0 - side[0].0) / (2.0 * off);
    let slope1 = (side[1].1 - side[0].1) / (2.0 * off);
    let mu_needed = slope0.abs().max(slope1.abs());
    if mu_needed > ctx.planner_mu {
        return Err(FailureReason::NotAntipodal);
    }
    // Height of the closing line.
    let top = quantile(&mut heights, cfg.top_quantile);
    let lowest = jaw.contact_to_tip_m + cfg.table_clearance_m;
    let h_c = (top - cfg.grasp_depth_m).max(lowest);
    if top - h_c < cfg.min_grasp_depth_m {
        return Err(FailureReason::Collision);
    }
    let (cx, cy) = (centre.0 + b2.0 * t_mid, centre.1 + b2.1 * t_mid);
    let pose = JawPose {
        center: (ctx.on_plane)(cx, cy) + ctx.up * h_c,
        approach: -ctx.up,
        closing: b,
        width,
    };
    let (collide, between, between_obj) = scene.scan_jaw(
        &pose,
        ctx.test_jaw,
        Some(ctx.soft),
        ctx.exec.collision_min_points,
    );
    if collide >= ctx.exec.collision_min_points {
        return Err(FailureReason::Collision);
    }
    if between < ctx.exec.empty_min_points {
        return Err(FailureReason::Empty);
    }
    if between_obj == 0 {
        return Err(FailureReason::MissedObject);
    }
    Ok(FootprintGrasp {
        pose,
        mu_needed,
        label,
    })
}
