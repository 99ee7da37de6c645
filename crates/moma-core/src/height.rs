//! Heights above the support plane, and how far a calibration's scale there can be trusted
//! (the error model's height part, [`DepthErrorModel::height_sigma`]; docs/grasping.md, "The
//! objects' height: what one calibration object says about the others").
//!
//! # The support plane
//! A fixed camera looks at a table or a bin floor. A plane in 3-D is a plane in inverse depth over
//! the pixels for a pinhole camera (`1/z = a·u + b·v + c`, whatever the intrinsics), so the
//! support plane is fitted there without intrinsics: least squares on every
//! [`PLANE_GRID_PX`]-th pixel, then [`PLANE_PASSES`] passes each keeping the [`PLANE_KEEP`] share
//! of those pixels nearest the plane (relative residual) and refitting. Objects stand in front of
//! the plane and fall out of the kept share; a depth model's smooth bumps of a few per cent stay
//! in. It is a support plane only if at least [`PLANE_MIN_INLIERS`] of the grid lies within
//! [`PLANE_INLIER_REL`] of it (an office seen across a room has none). A pixel's *height* is the
//! depth it stands in front of the plane along its ray, `z_plane(u, v) − z` (metres, ≥ 0).
//!
//! # The scale of heights
//! Heights are the prediction's differences scaled by the calibration's slope (target per unit
//! of prediction). A depth model flattens small objects; samples that land on the calibration
//! frame's object then pull a fit with spatial freedom (SSRA's planar scale field, LWLR's local
//! scale) towards a scale that undoes that object's flattening where it stands, which another
//! object of another size, at the same place in a later frame, does not share: on the simulated
//! graspnet6dof-table (SSRA, its 6–12 samples on the calibration frame's mug) the objects of the
//! other frames came out 10–30 mm too near on a 66 mm height, with a flat σ of 6 mm. Two numbers
//! measure it from the calibration samples alone, and their quadrature sum is the σ of a
//! per-frame relative error of every height ([`DepthErrorModel::height_sigma`]):
//! - **object pull** ([`object_scale_pull`]): the samples above the calibration frame's support
//!   plane are grouped by the object regions of its ground truth (each frame's own, few-shot);
//!   each object is left out in turn, and the RMS relative change of the fit's slope at that
//!   object's own samples is its pull, less the left-out fit's own jackknife variance there (a
//!   fit on a table seen from above alone hardly determines its scale, and that noise is not a
//!   pull). An object that the other objects pull the same way (a clutter of similar objects)
//!   has no pull of its own: the scale carries to the next one. The RMS over the objects.
//! - **parameter noise** ([`jackknife_relative_sd`]): the fit's slope over the K-fold refits of
//!   the cross-validation, as a grouped jackknife.
//!
//! [`DepthErrorModel::height_sigma`]: crate::DepthErrorModel::height_sigma

use std::collections::BTreeMap;
use std::ops::Range;

use ndarray::{Array2, ArrayView2};

use crate::align::{AlignmentModel, Method, Sample, SampleSet};
use crate::image::{ImageSize, MetricDepth, components_8, is_valid_depth};
use crate::normalise::AlignSpace;

/// Grid step of the support plane's fit, pixels.
pub const PLANE_GRID_PX: usize = 8;
/// Share of the grid's pixels each pass of the support plane's fit keeps.
pub const PLANE_KEEP: f64 = 0.6;
/// Passes of the trimmed plane fit after the first least squares.
pub const PLANE_PASSES: usize = 4;
/// A plane is a support plane when at least this share of the grid lies within
/// [`PLANE_INLIER_REL`] of it.
pub const PLANE_MIN_INLIERS: f64 = 0.3;
/// Relative depth tolerance of the support plane's inliers (a depth model's bumps of 2 % stay
/// inside).
pub const PLANE_INLIER_REL: f64 = 0.03;
/// A sample or a pixel stands on an object when its truth is this much in front of the support
/// plane, metres (the sensor's own noise on a table is a few millimetres).
pub const OBJECT_HEIGHT_M: f64 = 0.015;
/// Grid step of the object regions, pixels (8-connected regions of the truth above the plane).
pub const OBJECT_GRID_PX: usize = 4;
/// Folds of the left-out fits' jackknife ([`object_scale_pull`]) and of the parameter noise.
pub const FOLDS: usize = 5;
/// [`object_scale_pull`] leaves out at most this many objects, those with the most samples (each
/// costs 1 + [`FOLDS`] refits; an LWLR refit about 0.01 ms on 100 samples, its few nodes solved on
/// the calling thread).
pub const MAX_OBJECTS: usize = 4;

/// A support plane in inverse depth over pixels: `1/z = a·u + b·v + c` (1/m; u, v pixels).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SupportPlane {
    /// Slope per column, 1/(m·px).
    pub a: f64,
    /// Slope per row, 1/(m·px).
    pub b: f64,
    /// Inverse depth at pixel (0, 0), 1/m.
    pub c: f64,
}

impl SupportPlane {
    /// The plane's depth along the ray of pixel `(u, v)`, metres; `None` where the plane lies
    /// behind the camera or at infinity along it.
    pub fn depth_at(&self, u: f64, v: f64) -> Option<f64> {
        let w = self.a * u + self.b * v + self.c;
        (w > 0.0 && w.is_finite()).then(|| 1.0 / w)
    }

    /// How far a point of depth `z_m` on the ray of `(u, v)` stands in front of the plane,
    /// metres (negative behind it; `None` where the plane has no depth there).
    pub fn height(&self, u: f64, v: f64, z_m: f64) -> Option<f64> {
        self.depth_at(u, v).map(|zp| zp - z_m)
    }
}

/// The support plane of `depth` (metres; NaN or ≤ 0: no depth), module documentation; `None`
/// without one (too few pixels, or too few on the best plane).
pub fn support_plane(depth: ArrayView2<'_, f32>) -> Option<SupportPlane> {
    let (h, w) = depth.dim();
    // pixel coordinates scaled to ~[0, 1] keep the 3×3 normal equations well conditioned
    let scale = w.max(h).max(1) as f64;
    let pts: Vec<[f64; 3]> = (0..h)
        .step_by(PLANE_GRID_PX)
        .flat_map(|v| (0..w).step_by(PLANE_GRID_PX).map(move |u| (u, v)))
        .filter_map(|(u, v)| {
            let z = depth[[v, u]];
            is_valid_depth(z).then(|| [u as f64 / scale, v as f64 / scale, 1.0 / f64::from(z)])
        })
        .collect();
    if pts.len() < 10 {
        return None;
    }
    let solve = |sel: &mut dyn Iterator<Item = &[f64; 3]>| -> Option<[f64; 3]> {
        let mut m = nalgebra::Matrix3::<f64>::zeros();
        let mut r = nalgebra::Vector3::<f64>::zeros();
        for p in sel {
            let f = nalgebra::Vector3::new(p[0], p[1], 1.0);
            m += f * f.transpose();
            r += f * p[2];
        }
        let x = m.cholesky()?.solve(&r);
        Some([x[0], x[1], x[2]])
    };
    let rel_residual =
        |p: &[f64; 3], q: &[f64; 3]| ((p[2] - (q[0] * p[0] + q[1] * p[1] + q[2])) / p[2]).abs();
    let mut plane = solve(&mut pts.iter())?;
    let keep = ((pts.len() as f64 * PLANE_KEEP) as usize).clamp(3, pts.len());
    let mut ranked: Vec<(f64, usize)> = Vec::with_capacity(pts.len());
    for _ in 0..PLANE_PASSES {
        ranked.clear();
        ranked.extend(
            pts.iter()
                .enumerate()
                .map(|(i, p)| (rel_residual(p, &plane), i)),
        );
        ranked.select_nth_unstable_by(keep - 1, |x, y| x.0.total_cmp(&y.0));
        plane = solve(&mut ranked[..keep].iter().map(|&(_, i)| &pts[i]))?;
    }
    let inliers = pts
        .iter()
        .filter(|p| rel_residual(p, &plane) <= PLANE_INLIER_REL)
        .count();
    (inliers as f64 >= PLANE_MIN_INLIERS * pts.len() as f64).then_some(SupportPlane {
        a: plane[0] / scale,
        b: plane[1] / scale,
        c: plane[2],
    })
}

/// The height of every pixel of `depth` above its support plane ([`support_plane`]), metres:
/// `max(0, z_plane − z)`, 0 where `depth` or the plane has no depth; `None` without a support
/// plane.
pub fn height_above_plane(depth: ArrayView2<'_, f32>) -> Option<Array2<f32>> {
    let (h, w) = depth.dim();
    height_above_plane_in(depth, 0, 0, w, h)
}

/// [`height_above_plane`] of the region of `depth` of `width × height` pixels from pixel `(u0,
/// v0)` (clipped to the map): the plane fitted on the whole map, the heights of the region only.
pub fn height_above_plane_in(
    depth: ArrayView2<'_, f32>,
    u0: usize,
    v0: usize,
    width: usize,
    height: usize,
) -> Option<Array2<f32>> {
    let plane = support_plane(depth)?;
    let (h, w) = depth.dim();
    let (u0, v0) = (u0.min(w), v0.min(h));
    let region = depth.slice(ndarray::s![
        v0..(v0 + height).min(h),
        u0..(u0 + width).min(w)
    ]);
    Some(plane.heights(region, u0, v0))
}

impl SupportPlane {
    /// The heights above the plane of `region`, a part of a depth map whose first pixel is
    /// `(u0, v0)` of the map: `max(0, z_plane − z)` metres, 0 where there is no depth.
    pub fn heights(&self, region: ArrayView2<'_, f32>, u0: usize, v0: usize) -> Array2<f32> {
        Array2::from_shape_fn(region.dim(), |(v, u)| {
            let z = region[[v, u]];
            if !is_valid_depth(z) {
                return 0.0;
            }
            self.height((u0 + u) as f64, (v0 + v) as f64, f64::from(z))
                .map_or(0.0, |h| h.max(0.0) as f32)
        })
    }
}

/// The slopes of `model`'s target (depth in metres, or 1/depth in inverse space) per unit of
/// normalised prediction at `samples`' pixels and predictions (the fits are linear in the
/// prediction at a pixel: a unit step is exact; LWLR's local scales without its full-size maps).
pub(crate) fn slopes(model: &AlignmentModel, samples: &[Sample]) -> Vec<f64> {
    if let AlignmentModel::Lwlr(m) = model {
        let points: Vec<(f64, f64)> = samples.iter().map(|s| (s.u, s.v)).collect();
        return m.scales_at(&points);
    }
    samples
        .iter()
        .map(|s| model.predict_at(s.u, s.v, s.pred + 1.0) - model.predict_at(s.u, s.v, s.pred))
        .collect()
}

/// `method` refitted on `set` for its slopes only (LWLR without its full-size maps); `None` for
/// the methods [`object_scale_pull`] does not refit and where the fit fails.
fn refit(method: &Method, set: &SampleSet) -> Option<AlignmentModel> {
    if set.samples.len() < method.min_samples() {
        return None;
    }
    match method {
        Method::Lwlr(config) => crate::align::lwlr::fit_unmapped(set, config)
            .ok()
            .map(AlignmentModel::Lwlr),
        Method::Gssa | Method::Ssra(_) => method.fit(set).ok().map(|(m, _)| m),
        _ => None,
    }
}

/// Grouped-jackknife standard deviation of the relative slope, RMS over the points: `folds[k][p]`
/// the slope of refit k at point p, `reference[p]` the slope of the fit on every sample
/// there; the variance at a point is `(K − 1)/K · Σ_k (r_k − r̄)²` with `r_k = folds[k][p] /
/// reference[p] − 1`. Points with a non-finite ratio are left out; `None` with fewer than two
/// folds or no point.
pub fn jackknife_relative_sd(reference: &[f64], folds: &[Vec<f64>]) -> Option<f64> {
    let k = folds.len();
    if k < 2 {
        return None;
    }
    let (mut sum, mut n) = (0.0, 0usize);
    for (p, &r0) in reference.iter().enumerate() {
        let rel: Vec<f64> = folds.iter().map(|f| f[p] / r0 - 1.0).collect();
        if rel.iter().any(|r| !r.is_finite()) {
            continue;
        }
        let mean = rel.iter().sum::<f64>() / k as f64;
        sum += (k as f64 - 1.0) / k as f64 * rel.iter().map(|r| (r - mean).powi(2)).sum::<f64>();
        n += 1;
    }
    (n > 0).then(|| (sum / n as f64).sqrt())
}

/// The object each sample of `samples` (depth space: targets in metres) stands on: the indices
/// of the samples above `truth`'s support plane, grouped by the 8-connected regions of the truth
/// above the plane on a grid every [`OBJECT_GRID_PX`] pixels (a sample off the grid's regions is
/// an object of its own). Empty without a support plane.
pub fn object_groups(samples: &[Sample], truth: &MetricDepth) -> Vec<Vec<usize>> {
    let t = truth.depth_m.view();
    let Some(plane) = support_plane(t) else {
        return Vec::new();
    };
    let stands =
        |u: f64, v: f64, z: f64| plane.height(u, v, z).is_some_and(|h| h > OBJECT_HEIGHT_M);
    let above: Vec<usize> = (0..samples.len())
        .filter(|&i| stands(samples[i].u, samples[i].v, samples[i].target))
        .collect();
    if above.is_empty() {
        return Vec::new();
    }
    let (h, w) = t.dim();
    let g = OBJECT_GRID_PX;
    let (gh, gw) = (h.div_ceil(g), w.div_ceil(g));
    let above_grid: Vec<bool> = (0..gh * gw)
        .map(|k| {
            let (v, u) = ((k / gw) * g, (k % gw) * g);
            let z = t[[v, u]];
            is_valid_depth(z) && stands(u as f64, v as f64, f64::from(z))
        })
        .collect();
    // labels 1..=regions, 0 off every region
    let (label, counts) = components_8(&above_grid, ImageSize::new(gw, gh));
    let regions = counts.len();
    let mut groups: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for &i in &above {
        let s = &samples[i];
        let (gv, gu) = (
            ((s.v / g as f64).max(0.0) as usize).min(gh - 1),
            ((s.u / g as f64).max(0.0) as usize).min(gw - 1),
        );
        // the region of one of the four grid nodes around the sample
        let l = [(gv, gu), (gv, gu + 1), (gv + 1, gu), (gv + 1, gu + 1)]
            .into_iter()
            .filter(|&(nv, nu)| nv < gh && nu < gw)
            .map(|(nv, nu)| label[nv * gw + nu] as usize)
            .find(|&l| l != 0);
        groups
            .entry(l.unwrap_or(regions + 1 + i))
            .or_default()
            .push(i);
    }
    groups.into_values().collect()
}

/// The object pull of a calibration (module documentation): `method` (GSSA, SSRA or LWLR; 0
/// for the others) refitted on `samples` (depth space, as a
/// [`Calibration`](crate::pipeline::Calibration) stores them) without each object of
/// [`object_groups`] in turn (the [`MAX_OBJECTS`] with the most samples), in `space`; `full` the
/// fit on every sample; `frames`: each calibration frame's range in `samples` and its ground
/// truth, whose objects its samples stand on. 0 without a support plane or an object sample,
/// and for objects whose left-out fits fail.
pub fn object_scale_pull(
    method: &Method,
    full: &AlignmentModel,
    space: AlignSpace,
    samples: &SampleSet,
    frames: &[(Range<usize>, &MetricDepth)],
) -> f64 {
    let all = &samples.samples;
    let fit_without = |object: &[usize], fold: Option<usize>| -> Option<AlignmentModel> {
        let kept = (0..all.len())
            .filter(|i| !object.contains(i))
            .enumerate()
            .filter(|&(j, _)| fold.is_none_or(|k| j % FOLDS != k))
            .map(|(_, i)| all[i])
            .collect();
        let set = SampleSet {
            space: samples.space,
            image_size: samples.image_size,
            samples: kept,
        };
        refit(method, &set.in_space(space))
    };
    // each frame's objects, by that frame's ground truth (a range outside the samples: none)
    let mut objects: Vec<Vec<usize>> = frames
        .iter()
        .filter_map(|(range, truth)| Some((range.start, all.get(range.clone())?, truth)))
        .flat_map(|(start, on_frame, truth)| {
            object_groups(on_frame, truth)
                .into_iter()
                .map(move |o| o.into_iter().map(|i| start + i).collect())
        })
        .collect();
    // the objects with the most samples first (a stable order: ties by their first sample)
    objects.sort_by_key(|o| std::cmp::Reverse(o.len()));
    let (mut sum, mut n) = (0.0, 0usize);
    for object in objects.into_iter().take(MAX_OBJECTS) {
        let on_it: Vec<Sample> = object.iter().map(|&i| all[i]).collect();
        let Some(without) = fit_without(&object, None) else {
            continue;
        };
        let reference = slopes(&without, &on_it);
        let pull2 = slopes(full, &on_it)
            .iter()
            .zip(&reference)
            .map(|(f, r)| (f / r - 1.0).powi(2))
            .sum::<f64>()
            / on_it.len() as f64;
        let folds: Vec<Vec<f64>> = (0..FOLDS)
            .filter_map(|k| fit_without(&object, Some(k)))
            .map(|m| slopes(&m, &on_it))
            .collect();
        let Some(noise) = jackknife_relative_sd(&reference, &folds) else {
            continue;
        };
        // a left-out fit with no slope left (a prediction that does not follow depth) makes
        // the ratio meaningless: the object's pull is then the cap
        let pull = (pull2 - noise * noise).max(0.0).sqrt();
        let pull = if pull.is_finite() {
            pull.min(MAX_HEIGHT_SIGMA)
        } else {
            MAX_HEIGHT_SIGMA
        };
        sum += pull * pull;
        n += 1;
    }
    if n == 0 { 0.0 } else { (sum / n as f64).sqrt() }
}

/// The largest σ of the heights' relative error a calibration states: 1 says that its heights
/// are not known at all (a depth model whose output does not follow depth pulls without bound).
pub const MAX_HEIGHT_SIGMA: f64 = 1.0;

/// The σ of the heights' relative error of a calibration ([`DepthErrorModel::height_sigma`]):
/// the object pull and the parameter noise `slope_sd` in quadrature, at most
/// [`MAX_HEIGHT_SIGMA`] (also for a non-finite input).
///
/// [`DepthErrorModel::height_sigma`]: crate::DepthErrorModel::height_sigma
pub fn height_sigma(pull: f64, slope_sd: f64) -> f64 {
    let s = pull.hypot(slope_sd);
    if s.is_finite() {
        s.min(MAX_HEIGHT_SIGMA)
    } else {
        MAX_HEIGHT_SIGMA
    }
}
