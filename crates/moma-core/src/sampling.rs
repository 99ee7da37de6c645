//! Seeded choice of the n calibration pixels (docs/method.md §2).
//!

use ndarray::Array2;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};
use crate::image::{Mask, MetricDepth, is_valid_depth};

/// How calibration pixels are chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum SamplingStrategy {
    /// MOMA's protocol: uniform without replacement over valid ground-truth pixels.
    #[default]
    Random,
    /// BoostingDepth's: √n × √n grid nodes, each snapped to the nearest valid pixel.
    Grid,
}

impl SamplingStrategy {
    /// Both strategies.
    pub const ALL: [SamplingStrategy; 2] = [SamplingStrategy::Random, SamplingStrategy::Grid];

    /// The command-line and file name (`random`, `grid`).
    pub const fn name(self) -> &'static str {
        match self {
            Self::Random => "random",
            Self::Grid => "grid",
        }
    }
}

impl std::fmt::Display for SamplingStrategy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for SamplingStrategy {
    type Err = CoreError;
    fn from_str(s: &str) -> Result<Self> {
        crate::names::parse(s, &Self::ALL, Self::name, "sampling strategy")
    }
}

/// Sampling settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct SamplingConfig {
    /// Strategy.
    pub strategy: SamplingStrategy,
    /// Number of samples n (default 100).
    pub n: usize,
    /// Seed of every random choice.
    pub seed: u64,
    /// Keep samples more than this many pixels (Chebyshev distance) away from every depth
    /// discontinuity of the ground truth ([`depth_edges`]): pixels at object boundaries, where
    /// depth sensors return "flying pixels" between the object and its background and depth
    /// models blur the boundary over a few pixels, so that one sample there can tilt a global
    /// fit. 0 (default): off, MOMA's protocol (any valid pixel).
    #[serde(default)]
    pub edge_margin_px: u32,
}

impl Default for SamplingConfig {
    fn default() -> Self {
        Self {
            strategy: SamplingStrategy::Random,
            n: 100,
            seed: 0,
            edge_margin_px: 0,
        }
    }
}

/// Jump in ground-truth depth between 4-adjacent pixels, relative to the nearer of the two,
/// above which [`depth_edges`] marks a depth discontinuity: 3 %. Between adjacent pixels a
/// continuous surface changes depth by about `z / (f · tan α)` (α the angle between the viewing
/// ray and the surface, `f` the focal length in pixels), so at f ≈ 600 px only surfaces seen
/// within about 3° of grazing exceed it (tan α < 1/18), while the boundary of a 2 cm high object
/// on a table 0.7 m away (2.9 %) is close to the limit and anything taller exceeds it. The
/// per-frame re-alignment's anchor store uses the same constant (on its 3×3 half-resolution
/// neighbours).
pub const EDGE_JUMP_REL: f32 = 0.03;

/// Largest number of calibration samples accepted (`n`): 10 000, 100 times MOMA's ~100 and 3
/// times the largest count of the ablations (3000). A bound on user input: the calibration's
/// cross-validation (leave-one-out without the samples within 80 px, exact refits for LWLR)
/// grows as n², so 10 000 samples of a 640×480 frame take about 1 s (gssa) to 45 s (auto) on
/// the 2-core build machine, and 100 000 took more than 100 s and 5 GB for gssa alone. Larger
/// values are refused with [`CoreError::InvalidParameter`].
pub const MAX_SAMPLES: usize = 10_000;

/// A pixel position: `u` = column, `v` = row (pixels).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Pixel {
    /// Column.
    pub u: u32,
    /// Row.
    pub v: u32,
}

/// Chooses up to `config.n` distinct eligible pixels (below). Returns fewer only when fewer
/// eligible pixels exist (the fit then decides whether that is enough).
///
/// A pixel is *eligible* when its ground truth is valid ([`crate::is_valid_depth`]), it lies
/// inside `restrict` (when given) and, with `config.edge_margin_px = r > 0`, no pixel of
/// [`depth_edges`] lies within Chebyshev distance `r` of it (its `(2r + 1)²` window).
///
/// - [`SamplingStrategy::Random`]: `min(n, eligible)` pixels uniformly without replacement, drawn
///   with `ChaCha8Rng::seed_from_u64(seed)` via `rand::seq::index::sample` over the eligible pixels
///   in row-major order. Deterministic for a seed; the output is in draw order.
/// - [`SamplingStrategy::Grid`] (BoostingDepth): `k = ⌊√n⌋` (at least 1) nodes per axis, placed at
///   the centres of a `k × k` partition of the image: node `(i, j)` sits at
///   `u_i = (i + ½)·W/k − ½`, `v_j = (j + ½)·H/k − ½` (pixels; evenly spread, symmetric about
///   the image centre). Each node is snapped to the nearest eligible pixel (Euclidean distance;
///   ties go to the smaller row, then smaller column). Nodes that snap to the same pixel are
///   kept once, so the result can hold fewer than `k²` pixels; order is row-major over nodes.
///   The seed is not used.
///
/// # Errors
/// No valid pixel (or none outside the edge margin, [`CoreError::NoValidPixels`] naming it); size
/// mismatch between `gt` and `restrict`; `n == 0` or `n >` [`MAX_SAMPLES`].
///
/// # Example
/// ```
/// use moma_core::sampling::{sample_pixels, SamplingConfig};
/// use moma_core::MetricDepth;
/// let gt = MetricDepth::new(ndarray::Array2::from_elem((4, 5), 1.0f32));
/// let px = sample_pixels(&gt, &SamplingConfig { n: 3, ..Default::default() }, None).unwrap();
/// assert_eq!(px.len(), 3);
/// ```
pub fn sample_pixels(
    gt: &MetricDepth,
    config: &SamplingConfig,
    restrict: Option<&Mask>,
) -> Result<Vec<Pixel>> {
    if config.n == 0 {
        return Err(CoreError::InvalidParameter(
            "number of calibration samples n must be at least 1".into(),
        ));
    }
    if config.n > MAX_SAMPLES {
        return Err(CoreError::InvalidParameter(format!(
            "number of calibration samples n = {} exceeds the limit of {MAX_SAMPLES} (the \
             calibration's cross-validation grows as n²; MOMA needs about 100)",
            config.n
        )));
    }
    let size = gt.size();
    if let Some(r) = restrict {
        size.expect_eq("sampling mask", r.size())?;
    }
    let mut eligible = eligible_mask(gt, restrict);
    if config.edge_margin_px > 0 && eligible.iter().any(|&b| b) {
        let near_edge = near_depth_edges(gt, config.edge_margin_px);
        eligible.zip_mut_with(&near_edge, |e, &near| *e &= !near);
        if !eligible.iter().any(|&b| b) {
            return Err(CoreError::NoValidPixels(format!(
                "no valid ground-truth pixel (inside the sampling mask, if any) lies more than \
                 the edge margin of {} px from a depth discontinuity; lower the edge margin",
                config.edge_margin_px
            )));
        }
    }
    match config.strategy {
        SamplingStrategy::Random => sample_random(&eligible, config.n, config.seed),
        SamplingStrategy::Grid => sample_grid(&eligible, config.n),
    }
}

fn eligible_mask(gt: &MetricDepth, restrict: Option<&Mask>) -> Array2<bool> {
    match restrict {
        Some(r) => ndarray::Zip::from(&gt.depth_m)
            .and(r.data())
            .map_collect(|&z, &m| m && is_valid_depth(z)),
        None => gt.depth_m.mapv(is_valid_depth),
    }
}

/// Depth discontinuities of `gt`: every invalid pixel ([`is_valid_depth`]), and every valid
/// pixel with a 4-neighbour that is invalid or differs from it by more than [`EDGE_JUMP_REL`]
/// times the nearer depth (both sides of a boundary are marked). The image border is not a
/// discontinuity.
pub fn depth_edges(gt: &MetricDepth) -> Array2<bool> {
    let (h, w) = gt.depth_m.dim();
    let edges = depth_edges_flat(gt);
    Array2::from_shape_fn((h, w), |(v, u)| edges[v * w + u])
}

/// The pixels within `r_px` (Chebyshev distance, pixels) of a depth discontinuity of `gt`
/// ([`depth_edges`]): the band that calibration sampling keeps clear
/// ([`SamplingConfig::edge_margin_px`]) and where `moma grasp-eval` reports the error model's
/// coverage "near depth edges". A slanted surface is no edge however steep its depth runs over
/// the pixels, as long as neighbours differ by at most [`EDGE_JUMP_REL`].
pub fn near_depth_edges(gt: &MetricDepth, r_px: u32) -> Array2<bool> {
    let (h, w) = gt.depth_m.dim();
    let near = dilate(&depth_edges_flat(gt), h, w, r_px as usize);
    Array2::from_shape_fn((h, w), |(v, u)| near[v * w + u])
}

/// [`depth_edges`] in row-major order: one pass over horizontal and one over vertical
/// neighbour pairs, on contiguous rows.
fn depth_edges_flat(gt: &MetricDepth) -> Vec<bool> {
    let (h, w) = gt.depth_m.dim();
    let z = gt.depth_m.as_standard_layout();
    let copied: Vec<f32>;
    let zs: &[f32] = match z.as_slice() {
        Some(s) => s,
        None => {
            copied = z.iter().copied().collect();
            &copied
        }
    };
    let mut edges: Vec<bool> = zs.iter().map(|&a| !is_valid_depth(a)).collect();
    // a pair differs when exactly one side is valid, or both are and they jump
    let differ = |a: f32, b: f32| match (is_valid_depth(a), is_valid_depth(b)) {
        (true, true) => (a - b).abs() > EDGE_JUMP_REL * a.min(b),
        (va, vb) => va != vb,
    };
    for v in 0..h {
        let row = v * w;
        for u in 1..w {
            if differ(zs[row + u - 1], zs[row + u]) {
                edges[row + u - 1] = true;
                edges[row + u] = true;
            }
        }
    }
    for v in 1..h {
        let (above, row) = ((v - 1) * w, v * w);
        for u in 0..w {
            if differ(zs[above + u], zs[row + u]) {
                edges[above + u] = true;
                edges[row + u] = true;
            }
        }
    }
    edges
}

/// Binary dilation of the row-major `h × w` `mask` by the `(2r + 1)²` square: separable, a
/// running count along each row, then running per-column counts over a window of rows, so
/// O(H·W) whatever `r` and on contiguous rows (a morphology crate would add a dependency for
/// one box filter).
fn dilate(mask: &[bool], h: usize, w: usize, r: usize) -> Vec<bool> {
    // a window wider than the image covers it all: also keeps `u + r` from overflowing
    let r = r.min(h.max(w));
    // rows: window [u - r, u + r] ∩ [0, w) of each row
    let mut rows = vec![false; h * w];
    for v in 0..h {
        let (line, out) = (&mask[v * w..(v + 1) * w], &mut rows[v * w..(v + 1) * w]);
        let mut count = line[..r.min(w)].iter().filter(|&&b| b).count();
        for u in 0..w {
            if let Some(&add) = line.get(u + r) {
                count += usize::from(add);
            }
            out[u] = count > 0;
            if u >= r {
                count -= usize::from(line[u - r]);
            }
        }
    }
    // columns: per-column counts over the rows [v - r, v + r] ∩ [0, h)
    let mut counts = vec![0u32; w];
    let add = |counts: &mut [u32], v: usize, sign: bool| {
        for (c, &b) in counts.iter_mut().zip(&rows[v * w..(v + 1) * w]) {
            if b {
                *c = if sign { *c + 1 } else { *c - 1 };
            }
        }
    };
    for v in 0..r.min(h) {
        add(&mut counts, v, true);
    }
    let mut out = vec![false; h * w];
    for v in 0..h {
        if v + r < h {
            add(&mut counts, v + r, true);
        }
        for (o, &c) in out[v * w..(v + 1) * w].iter_mut().zip(&counts) {
            *o = c > 0;
        }
        if v >= r {
            add(&mut counts, v - r, false);
        }
    }
    out
}

fn no_valid() -> CoreError {
    CoreError::NoValidPixels(
        "ground truth holds no valid depth (inside the sampling mask, if any)".into(),
    )
}

fn sample_random(eligible: &Array2<bool>, n: usize, seed: u64) -> Result<Vec<Pixel>> {
    let valid: Vec<Pixel> = eligible
        .indexed_iter()
        .filter(|(_, ok)| **ok)
        .map(|((v, u), _)| Pixel {
            u: u as u32,
            v: v as u32,
        })
        .collect();
    if valid.is_empty() {
        return Err(no_valid());
    }
    if n >= valid.len() {
        return Ok(valid);
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    Ok(rand::seq::index::sample(&mut rng, valid.len(), n)
        .into_iter()
        .map(|i| valid[i])
        .collect())
}

fn sample_grid(eligible: &Array2<bool>, n: usize) -> Result<Vec<Pixel>> {
    let (h, w) = eligible.dim();
    if !eligible.iter().any(|&b| b) {
        return Err(no_valid());
    }
    let k = ((n as f64).sqrt().floor() as usize).max(1);
    // k ≤ √MAX_SAMPLES (checked by the caller), so k·k cannot overflow.
    let mut out: Vec<Pixel> = Vec::with_capacity((k * k).min(eligible.len()));
    let mut seen = std::collections::HashSet::with_capacity(out.capacity());
    for j in 0..k {
        let vn = (j as f64 + 0.5) * h as f64 / k as f64 - 0.5;
        for i in 0..k {
            let un = (i as f64 + 0.5) * w as f64 / k as f64 - 0.5;
            if let Some(p) = nearest_eligible(eligible, un, vn)
                && seen.insert(p)
            {
                out.push(p);
            }
        }
    }
    Ok(out)
}

/// Nearest eligible pixel to the real position `(un, vn)`, searching square rings of growing
/// Chebyshev radius around the closest pixel until no closer pixel can exist.
fn nearest_eligible(eligible: &Array2<bool>, un: f64, vn: f64) -> Option<Pixel> {
    let (h, w) = eligible.dim();
    let cu = (un.round().max(0.0) as usize).min(w - 1) as i64;
    let cv = (vn.round().max(0.0) as usize).min(h - 1) as i64;
    let mut best: Option<(f64, i64, i64)> = None;
    let max_r = w.max(h) as i64;
    for r in 0..=max_r {
        // any pixel on ring r is at least (r - 0.5) away from (un, vn) (|un - cu| <= 0.5)
        if let Some((d2, _, _)) = best {
            let lower = (r as f64 - 0.5).max(0.0);
            if lower * lower > d2 {
                break;
            }
        }
        let (v0, v1) = (cv - r, cv + r);
        let (u0, u1) = (cu - r, cu + r);
        for v in v0.max(0)..=v1.min(h as i64 - 1) {
            let on_edge_row = v == v0 || v == v1;
            let mut visit = |u: i64| {
                if u < 0 || u >= w as i64 || !eligible[[v as usize, u as usize]] {
                    return;
                }
                let d2 = (u as f64 - un).powi(2) + (v as f64 - vn).powi(2);
                let better = match best {
                    None => true,
                    Some((bd, bv, bu)) => d2 < bd || (d2 == bd && (v, u) < (bv, bu)),
                };
                if better {
                    best = Some((d2, v, u));
                }
            };
            if on_edge_row {
                for u in u0.max(0)..=u1.min(w as i64 - 1) {
                    visit(u);
                }
            } else {
                visit(u0);
                if u1 != u0 {
                    visit(u1);
                }
            }
        }
    }
    best.map(|(_, v, u)| Pixel {
        u: u as u32,
        v: v as u32,
    })
}

/// [`sample_reach`] measures from every `REACH_STEP_PX`-th pixel of every `REACH_STEP_PX`-th
/// row, by a brute-force scan of the samples: exact distances, grid pixels × samples of them
/// (1.4 million for 100 samples on 1280 × 720), and a 90th percentile within a step of the full
/// map's. Calibration runs it once.
const REACH_STEP_PX: usize = 8;

/// [`SampleReach::is_partial`]'s bound: samples whose 90th-percentile distance exceeds this
/// many times that of as many samples spread uniformly leave part of the image beyond their
/// reach. The shared sets' random samples measure 1.06–1.22 times it; samples drawn in the left
/// half of the image 5.6 times (docs/grasping.md, "σ away from the samples").
pub const PARTIAL_REACH_RATIO: f64 = 2.0;

/// How far calibration samples reach over an image ([`sample_reach`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SampleReach {
    /// 90th percentile, over the pixels with depth, of the distance to the nearest sample,
    /// pixels.
    pub p90_px: f64,
    /// The same for as many samples placed uniformly at random over those pixels (a Poisson
    /// process of density n / area: `√(ln 10 / π · area / n)`), pixels.
    pub uniform_p90_px: f64,
    /// Samples counted (distinct pixels or not).
    pub samples: usize,
}

impl SampleReach {
    /// Whether the samples leave part of the image beyond their reach: [`Self::p90_px`] more than
    /// [`PARTIAL_REACH_RATIO`] times [`Self::uniform_p90_px`]. There the alignment extrapolates:
    /// the calibration then fits the error model's distance part
    /// ([`crate::error_model::DepthErrorModel::sample_distance_gain`]), whose growth the
    /// calibration frame's own extrapolation sets.
    pub fn is_partial(&self) -> bool {
        self.p90_px > PARTIAL_REACH_RATIO * self.uniform_p90_px
    }

    /// The warning `moma calibrate` and Python's `calibrate` give when the reach
    /// [`Self::is_partial`] (`None` otherwise); `mask_option` names how the caller takes a
    /// sample mask (`--mask`, `mask=`). With the calibration's error `model`, it says how far
    /// the model's flat σ grows between the samples and [`Self::p90_px`] away from them.
    pub fn warning(
        &self,
        mask_option: &str,
        model: Option<&crate::error_model::DepthErrorModel>,
    ) -> Option<String> {
        if !self.is_partial() {
            return None;
        }
        let growth = match model {
            Some(m) if m.sample_distance_gain > 0.0 => format!(
                "; the error model's flat σ (at {:.2} m) grows from {:.1} mm at the samples to \
                 {:.1} mm {:.0} px away, as this frame's own error did",
                m.depth_ref_m,
                1e3 * m.flat_sigma_at_distance_m(0.0),
                1e3 * m.flat_sigma_at_distance_m(self.p90_px),
                self.p90_px
            ),
            _ => String::new(),
        };
        Some(format!(
            "the {} calibration samples reach only part of the image: 90 % of the pixels with \
             depth (for a sparse ground truth, of the region it spans) lie within {:.0} px of \
             one, where as many samples spread evenly would reach \
             them within {:.0} px. Beyond them the alignment extrapolates{growth}; σ is still too \
             narrow on objects far from the samples (docs/grasping.md, \"σ away from the \
             samples\"): draw the samples ({mask_option}) over where the objects will be",
            self.samples, self.p90_px, self.uniform_p90_px
        ))
    }
}

/// [`sample_reach`] of a calibration's `samples` over the pixels where any of its frames'
/// ground `truths` has depth (the frames share one camera, so their samples one image).
pub fn sample_reach_over(
    samples: &crate::align::SampleSet,
    truths: &[&MetricDepth],
) -> Option<SampleReach> {
    let first = truths.first()?;
    let mut valid = first.depth_m.mapv(is_valid_depth);
    for t in &truths[1..] {
        if t.depth_m.dim() == valid.dim() {
            ndarray::Zip::from(&mut valid)
                .and(&t.depth_m)
                .for_each(|v, &z| *v |= is_valid_depth(z));
        }
    }
    sample_reach(&samples.pixels_uv(), &valid)
}

/// How far the samples at pixels `uv` (column u, row v) reach over the pixels where `valid`
/// is true (a calibration frame's ground truth with depth): the 90th percentile of the
/// distance to the nearest sample, against as many samples spread uniformly. `None` without
/// samples or without a valid pixel.
pub fn sample_reach(uv: &[(f64, f64)], valid: &Array2<bool>) -> Option<SampleReach> {
    // the valid pixels' count and bounding box, a row at a time
    let (mut count, mut v0, mut v1, mut u0, mut u1) = (0usize, usize::MAX, 0, usize::MAX, 0);
    for (v, row) in valid.rows().into_iter().enumerate() {
        let n = row.iter().filter(|&&b| b).count();
        if n > 0 {
            count += n;
            (v0, v1) = (v0.min(v), v);
            u0 = u0.min(row.iter().position(|&b| b).unwrap_or(usize::MAX));
            u1 = u1.max(row.iter().rposition(|&b| b).unwrap_or(0));
        }
    }
    if uv.is_empty() || count == 0 {
        return None;
    }
    // A sparse ground truth (a few hundred measured points, a LiDAR's rows: under 30 % of the
    // pixels of their bounding box) covers that box although few of its pixels have depth:
    // the reach is then measured over the box, and the uniform spread compared with is over
    // its area. Measured over the valid pixels alone, samples among those very points looked
    // as if they reached only part of the image. A dense ground truth is measured as before.
    let box_area = (v1 - v0 + 1) * (u1 - u0 + 1);
    let sparse = 10 * count < 3 * box_area;
    let area = if sparse { box_area } else { count };
    let measured = |u: usize, v: usize| {
        if sparse {
            (u0..=u1).contains(&u) && (v0..=v1).contains(&v)
        } else {
            valid[[v, u]]
        }
    };
    // squared distance from pixel (u, v) to the nearest sample (f32: pixel coordinates and
    // their squares are exact; a loop the compiler vectorises)
    let (su, sv): (Vec<f32>, Vec<f32>) = uv.iter().map(|&(u, v)| (u as f32, v as f32)).unzip();
    let nearest = |(u, v): (usize, usize)| {
        let (u, v) = (u as f32, v as f32);
        f64::from(
            su.iter()
                .zip(&sv)
                .map(|(&a, &b)| (u - a) * (u - a) + (v - b) * (v - b))
                .fold(f32::INFINITY, f32::min),
        )
    };
    let (h, w) = valid.dim();
    let mut d2: Vec<f64> = (0..h)
        .step_by(REACH_STEP_PX)
        .flat_map(|v| (0..w).step_by(REACH_STEP_PX).map(move |u| (u, v)))
        .filter(|&(u, v)| measured(u, v))
        .map(nearest)
        .collect();
    if d2.is_empty() {
        // valid pixels, all off the grid: measure on each of them
        d2 = valid
            .indexed_iter()
            .filter(|(_, b)| **b)
            .map(|((v, u), _)| nearest((u, v)))
            .collect();
    }
    let k = ((d2.len() as f64 * 0.9).ceil() as usize).clamp(1, d2.len()) - 1;
    let (_, p90, _) = d2.select_nth_unstable_by(k, f64::total_cmp);
    Some(SampleReach {
        p90_px: p90.sqrt(),
        uniform_p90_px: (std::f64::consts::LN_10 / std::f64::consts::PI * area as f64
            / uv.len() as f64)
            .sqrt(),
        samples: uv.len(),
    })
}

/// The distance (pixels) from every pixel of a `height × width` image to the nearest of the
/// samples at `uv` (column u, row v; each rounded to its pixel, those outside the image
/// clamped to its border): the map the error model's distance part reads
/// ([`crate::error_model::DepthErrorModel::sample_distance_gain`]). Every pixel is `+∞` without
/// a sample.
///
/// Written here rather than taken from a crate: an exact Euclidean distance transform
/// (Felzenszwalb & Huttenlocher 2012: along columns the distance to the nearest sample of the
/// column by two sweeps, then along rows the lower envelope of parabolas) in O(pixels), about a
/// millisecond for 640 × 480, where the brute force over 100 samples is 30 million distances;
/// none of the workspace's crates has one.
pub fn sample_distance_map(height: usize, width: usize, uv: &[(f64, f64)]) -> Array2<f32> {
    let mut out = Array2::<f32>::from_elem((height, width), f32::INFINITY);
    if height == 0 || width == 0 {
        return out;
    }
    // 1. along columns: the distance (rows) to the nearest sample of the same column, by a
    // sweep down and one up over whole rows (contiguous, for all columns at once)
    let mut g = vec![f64::INFINITY; height * width];
    for &(u, v) in uv {
        if !(u.is_finite() && v.is_finite()) {
            continue;
        }
        let u = u.round().clamp(0.0, (width - 1) as f64) as usize;
        let v = v.round().clamp(0.0, (height - 1) as f64) as usize;
        g[v * width + u] = 0.0;
    }
    for v in 1..height {
        let (above, row) = g[(v - 1) * width..(v + 1) * width].split_at_mut(width);
        for (x, &a) in row.iter_mut().zip(above.iter()) {
            *x = x.min(a + 1.0);
        }
    }
    for v in (0..height - 1).rev() {
        let (row, below) = g[v * width..(v + 2) * width].split_at_mut(width);
        for (x, &b) in row.iter_mut().zip(below.iter()) {
            *x = x.min(b + 1.0);
        }
    }
    // 2. along rows: the lower envelope of the parabolas (u − p)² + g(p)²
    let (mut f, mut d2) = (vec![0.0f64; width], vec![0.0f64; width]);
    let (mut hull, mut bounds) = (vec![0usize; width], vec![0.0f64; width + 1]);
    for (row_g, mut row_out) in g.chunks_exact(width).zip(out.rows_mut()) {
        for (a, &b) in f.iter_mut().zip(row_g) {
            *a = b * b;
        }
        squared_distance_1d(&f, &mut d2, &mut hull, &mut bounds);
        for (o, &x) in row_out.iter_mut().zip(&d2) {
            *o = (x as f32).sqrt();
        }
    }
    out
}

/// One pass of the distance transform: `out[q] = min_p (q − p)² + f[p]` (`f` may hold +∞),
/// the lower envelope of the parabolas rooted at the finite `f[p]`; `hull` and `bounds` are
/// scratch of at least `f.len()` and `f.len() + 1` entries.
fn squared_distance_1d(f: &[f64], out: &mut [f64], hull: &mut [usize], bounds: &mut [f64]) {
    // where the parabolas rooted at p and q (p < q) cross
    let cross = |p: usize, q: usize| {
        ((f[q] + (q * q) as f64) - (f[p] + (p * p) as f64)) / (2.0 * (q - p) as f64)
    };
    let Some(first) = f.iter().position(|x| x.is_finite()) else {
        out.fill(f64::INFINITY);
        return;
    };
    // hull[..=k]: the parabolas of the envelope, left to right; parabola hull[j] is lowest on
    // bounds[j]..bounds[j + 1]
    let mut k = 0;
    hull[0] = first;
    bounds[0] = f64::NEG_INFINITY;
    bounds[1] = f64::INFINITY;
    for (q, fq) in f.iter().enumerate().skip(first + 1) {
        if !fq.is_finite() {
            continue;
        }
        let mut s = cross(hull[k], q);
        // q's parabola hides hull[k]'s wholly (never the first's, whose bound is −∞)
        while s <= bounds[k] {
            k -= 1;
            s = cross(hull[k], q);
        }
        k += 1;
        hull[k] = q;
        bounds[k] = s;
        bounds[k + 1] = f64::INFINITY;
    }
    let mut j = 0;
    for (q, o) in out.iter_mut().enumerate() {
        while bounds[j + 1] < q as f64 {
            j += 1;
        }
        let p = hull[j];
        *o = (q as f64 - p as f64).powi(2) + f[p];
    }
}
