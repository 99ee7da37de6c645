//! A model of the error of aligned depth, fitted from the calibration itself, and the per-pixel
//! σ map and random depth draws it gives (docs/grasping.md, "Planning for the depth's error").
//!
//! # The model
//! The true depth of a pixel is modelled as the aligned depth `z` plus independent parts
//! (metres):
//! - **relief**: `c · hp(z)`, where `hp = z − box(z)` is the aligned depth's relief against a
//!   wide box blur (radius [`DepthErrorModel::relief_radius_px`]) and `c ~ N(relief_bias,
//!   relief_sigma²)` one number per frame. Depth models flatten small objects on a table: on the
//!   calibration frame the truth's relief is larger than the aligned one, `relief_bias > 0`.
//! - **flat error** of σ `σ_flat(z) = sigma_flat_m · (z / depth_ref_m)^depth_exponent` (the
//!   exponent is 2 for a fit in inverse space, whose error in 1/z is even over depth, 0 in depth
//!   space), split into an offset shared by the frame and three Gaussian fields with correlation
//!   lengths [`DepthErrorModel::scales_px`] (fine, medium, coarse), by
//!   [`DepthErrorModel::variance_shares`];
//! - **edges**: aligned silhouettes are ramps spread over a few pixels where the truth is a
//!   step. In a `(2r+1)²` window (r = [`DepthErrorModel::edge_radius_px`]) `relief` is the depth
//!   range and `step` the move that snaps the pixel to the window's near or far side (whichever
//!   half of the range it lies in). The truth takes `a · step`, `a ~ N(edge_sharpening,
//!   edge_sharpening_sigma²)` per frame, plus noise of σ `edge_gain · relief`.
//! - **height**: `−k · h`, h the aligned depth's height above its support plane
//!   ([`crate::height::height_above_plane`]: the depth a pixel stands in front of the dominant
//!   plane along its ray, 0 without one) and `k ~ N(0, height_sigma²)` one number per frame: a
//!   relative error of every height, where the calibration's scale at an object rests on the
//!   calibration frame's own objects ([`crate::height`]).
//! - **distance to the samples**: where the calibration samples reach only part of the image,
//!   the alignment extrapolates beyond them, and the flat error's level grows with the distance
//!   d (pixels) to the nearest sample: `σ_flat(z, d) = (z / depth_ref_m)^p · √(sigma_flat_m² +
//!   (sample_distance_gain · d)²)`, `sigma_flat_m` then the level at the samples. The map of d
//!   ([`DepthErrorModel::sample_distance_px`]) comes from the calibration's samples.
//!
//! The per-pixel σ ([`DepthErrorModel::sigma_map`]) is the RMS of all parts, the relief bias
//! included: `σ² = σ_flat(z, d)² + (relief_bias² + relief_sigma²)·hp² + (edge_sharpening² +
//! edge_sharpening_sigma²)·step² + (edge_gain·relief)² + (height_sigma·h)²`.
//!
//! # Where the numbers come from
//! Only from calibration data ([`DepthErrorModel::fit`]): the dense residuals of each
//! calibration frame (the calibration's result on the frame against its ground truth), grown by
//! the fit's optimism at its samples: the ratio `Σ held_out² / Σ in_sample²` over the
//! calibration samples, each residual once from a cross-validation fold that did not see the
//! sample and once from the fit that did ([`HeldOutResidual`]; about 1 + 2p/n for a least-squares
//! fit of p parameters on n samples), never beyond the held-out mean square (the former floor):
//! where the truth is the samples alone, or a fit is nearly exact at a few samples, that is the
//! level. (Until
//! 2026-12-08 the held-out residuals' mean square was a floor of `σ_flat`: one sample at a
//! silhouette, 85 mm off in and out of the fit, lifted graspnet6dof-table's SSRA σ_flat from
//! its 3.9 mm dense level to 10.4 mm; docs/grasping.md, "The fit's optimism".)
//! 1. `relief_bias` and `edge_sharpening`: least squares of `truth − aligned = c·hp + a·step`
//!    over the pixels with `|hp| ≤` [`MAX_RELIEF_M`] (a within [0, 1]); `relief_sigma =
//!    |relief_bias|` (one frame cannot tell how the factor varies between frames; a zero
//!    correction stays within one σ). A factor outside [[`MIN_RELIEF_FACTOR`],
//!    [`MAX_RELIEF_FACTOR`]] is no depth model's flattening: the model then has no relief part
//!    (c = 0, a fitted alone).
//!
//!    1b. The relief range [`DepthErrorModel::relief_max_m`]: tall objects (a bottle, a box on
//!    its end) stand 0.1–0.3 m out of the table, and a depth model flattens them too. Bands of
//!    larger |hp| (0.1–0.2 m, 0.2–0.4 m, … up to [`MAX_RELIEF_EXTENDED_M`]) join the range while
//!    the truth follows the same factor in them (its own factor within
//!    [`RELIEF_BAND_FACTOR_RATIO`] of `c`, explaining ≥ [`RELIEF_BAND_MIN_EXPLAINED`] of the
//!    band's squared residuals, and lowering its absolute residual to ≤
//!    [`RELIEF_BAND_MAX_ABS_RATIO`]); with a wider range, `c` is refitted over all of it (a
//!    kept).
//!
//!    1c. The relief radius [`DepthErrorModel::relief_radius_px`]: steps 1 and 1b run once for
//!    each radius of [`RELIEF_RADIUS_SHARES`] (3–7.5 % of the image width) on every fourth row
//!    and column of the fit's grid, and the radius whose first-order expected truth (`aligned
//!    + c·hp + a·step`) is nearest the calibration frames' truth there, by mean squared
//!    difference over the pixels with both depths (the least squares of step 1 extended to the
//!    radius), is kept; steps 1, 1b, 2 and 3 then run on the whole grid with it. How wide a
//!    structure a depth model flattens is its own; against a blur of another width the fitted
//!    factor is diluted. A radius smaller than 7.5 % is kept only with a flattening factor
//!    (c > 0): at a few pixels' scale the aligned depth's noise dominates its relief, and least
//!    squares then finds a negative factor that smooths the noise and flattens the objects with
//!    it (the `moma demo` scene: c = −0.25 at 19 px).
//! 2. The rest `r = truth − aligned − relief_bias·hp − edge_sharpening·step`, divided by `(z / depth_ref_m)^p`
//!    (`depth_ref_m` the median calibration depth): `σ_flat²` its mean square over flat pixels;
//!    the field variances from its semivariogram at lags 2–64 px on every second row and column
//!    (non-negative least squares of `γ(L) = Σ v_k · min(1, L / s_k)`); the offset share its
//!    mean squared over `σ_flat²`, or, when larger, the share the fields leave (variance that
//!    varies over more than 64 px moves a gripper's footprint as a whole); the fields share the
//!    rest in the semivariogram's proportions.
//! 3. `edge_gain`: least squares of `r² − σ_flat(z)²` on `relief²` over the other pixels
//!    (`edge_sharpening_sigma` is half of `edge_sharpening`).
//! 4. `height_sigma` is not fitted here but by the calibration, which has the samples and can
//!    refit ([`crate::height`]: the pull of each calibration object on the fit's scale at its
//!    own samples, and the cross-validation folds' spread of that scale); 0 for models fitted
//!    here alone.
//! 5. `sample_distance_gain`, only with a map of the distance to the nearest sample
//!    ([`DepthErrorModel::fit_with_sample_distance`]; the calibration gives one when its
//!    samples reach only part of the image, [`crate::sampling::SampleReach::is_partial`]): least
//!    squares of the rest's square on `σ0² + gain²·d²` over the flat pixels of step 2, both
//!    terms non-negative. `σ0²` replaces the flat mean square of step 2 in `sigma_flat_m` (the
//!    optimism, measured at the samples, grows it; `sigma_dense_m` keeps the
//!    whole frame's); the variance shares keep the whole frame's proportions, and step 3
//!    subtracts each pixel's own flat σ. Spread samples get no
//!    such part: over their image the share of true errors within ±1σ stays level with the
//!    distance (docs/grasping.md, "σ away from the samples").
//!
//! With per-frame re-alignment on static anchors, the frame's own error on the unchanged
//! background sets `σ_flat` for that frame: the RMSE against the calibration frame's ground
//! truth at anchors that no fit used, whatever the correction was fitted to, taken to the reference depth by
//! the model's depth law ([`DepthErrorModel::for_frame_on_background`]; the short-range fields
//! keep the calibration's level). Reports written before that RMSE existed fall back to the
//! held-out RMSE of the correction's own target: onto the calibration's own output the frame's
//! drift, added to the calibration frames' own dense σ, `sigma_dense_m`
//! ([`DepthErrorModel::with_frame_drift`]); onto the ground truth the frame's error, replacing
//! `σ_flat` ([`DepthErrorModel::for_frame`]; at least a quarter of the calibration's).
//!
//! # Expected truth
//! [`DepthErrorModel::expected_truth_map`] is the model's mean of the truth given an aligned
//! depth: the mean relief correction (`hp` clamped to the range the factor is fitted on), the
//! mean edge share, and optionally the short-range bumps averaged out. Grasps are planned on
//! it, and drawn around it with [`DepthErrorModel::deviations`] (the model without those means).
//!
//! A flattening (`relief_bias` c > 0) is undone as the fixed point of `z = aligned + c0 ·
//! hp(z)`, `c0 = c / (1 + c)`, from [`RELIEF_FIXED_POINT_ITERATIONS`] steps started at the
//! aligned depth: a depth model that flattens linearly, `aligned = truth − c0 · hp(truth)`, has
//! `hp(aligned) ≈ (1 − c0) · hp(truth)` on small structures (so the fitted `c = c0 / (1 − c0)`
//! to first order), but not beside a large object, where the first-order correction
//! `c · hp(aligned)` raises the rims of its top and lowers the table around it. The relief is
//! clamped at the range on the aligned depth's scale, `(1 − c0) · hp(z)`. An exaggeration (c <
//! 0) keeps the first-order correction.
//!
//! # Draws
//! [`DepthErrorModel::draw_into`] adds one seeded sample of all parts to a depth map (a
//! plausible true scene): the relief factor and the offset are single N(0, 1) numbers, each
//! field is N(0, 1) on a grid every `s_k` pixels, bilinear between, divided per pixel by the
//! norm of its interpolation weights (so every pixel has variance 1), the edge field at 2 px
//! (a pixel near a silhouette moves to its window's near or far side where the field passes
//! ±θ, `P(N(0, 1) > θ) = 2 g²`: silhouettes that move, never surfaces in mid-air; the variance
//! at mid-ramp is the σ map's `(edge_gain · relief)²`), the step share one number per draw (clamped to [−1, 1]: around the expected truth,
//! [`DepthErrorModel::deviations`], it is drawn around 0), the height factor one number drawn
//! after all the others (a model without a height part draws what it drew before). The
//! distance part draws the offset and the fields at unit level and scales them together at each
//! pixel by `σ_flat(z, d)` (the error's shape is the frame's, its level grows away from the
//! samples).
//! Pixels without depth stay without depth; a draw never leaves a pixel at ≤ 0 m (it keeps the
//! original there).

use std::sync::Arc;

use ndarray::{Array2, ArrayView2, ArrayViewMut2};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};
use crate::image::{ImageSize, MetricDepth, is_valid_depth};

/// Relief below which a pixel counts as flat (metres): 5 mm, or 1.5 × the median relief of the
/// calibration frames when that is larger (a steeply seen table has a relief of its own in every
/// window; only what stands out of it is an edge).
pub const FLAT_RELIEF_M: f32 = 0.005;

/// Largest relief |hp| that counts as a small object's (metres): larger ones are scene
/// structure (walls, far background) and stay out of the relief factor's fit.
pub const MAX_RELIEF_M: f64 = 0.1;

/// Largest relief range the relief factor may be extended to (metres): bands of |hp| doubling
/// from [`MAX_RELIEF_M`] (0.1–0.2, 0.2–0.4, … , 0.8–1.6 m) join the range while the truth
/// keeps the factor in them ([`RELIEF_BAND_FACTOR_RATIO`], [`RELIEF_BAND_MIN_EXPLAINED`]).
pub const MAX_RELIEF_EXTENDED_M: f64 = 16.0 * MAX_RELIEF_M;

/// A relief band joins the range when its own factor is within this ratio of the small-object
/// factor (either way: 0.5 to 2 times it).
pub const RELIEF_BAND_FACTOR_RATIO: f64 = 2.0;

/// … and when the relief correction explains at least this share of the band's squared
/// residuals (`(Σxh)² / (Σh² Σx²)`, x = truth − aligned − edge part). Chosen on the shared sets
/// over three simulator seeds (docs/grasping.md, "Tall objects: the relief range").
pub const RELIEF_BAND_MIN_EXPLAINED: f64 = 0.05;

/// … and when the correction by `c` lowers the band's mean absolute residual to at most this
/// share of it. Least squares alone follows a few large residuals: on the REAL Depth Anything 3
/// frames of zed-da3-office the bands' factors look like a flattening (5–12 % of the squared
/// residuals explained) while the absolute residual does not fall (ratios 0.97–1.05), and
/// extending the range there raised the MAE by 6–8 %; on the simulated shared sets the accepted
/// bands' ratios are 0.41–0.83.
pub const RELIEF_BAND_MAX_ABS_RATIO: f64 = 0.9;

/// The relief factors a depth model's flattening (or exaggeration) can have: the truth's relief
/// between 0.5 and 2 times the aligned one's (`c = 1/k − 1` for a relief kept at k). A fitted
/// factor outside is not a relief error (REAL Depth Anything 3 frames with a stereo reference
/// gave 2.9–11.9, stored clamped at 10, and a correction by it doubled their MAE): the model
/// then has none.
pub const MIN_RELIEF_FACTOR: f64 = -0.5;
/// See [`MIN_RELIEF_FACTOR`].
pub const MAX_RELIEF_FACTOR: f64 = 1.0;

/// The relief blur radii [`DepthErrorModel::fit`] chooses from, as shares of the image width
/// (19, 29, 38 and 48 px at 640): the one whose expected truth is nearest the calibration
/// frames' truth (mean squared difference, fit step 1c) is kept. How wide a structure a depth
/// model flattens is the model's own (the blur it effectively applies), and a factor fitted
/// against a blur of the wrong width is diluted: on the simulated m2t2-table (SSRA, simulator
/// seed 1) the factor is 0.38 at 3 % of the width and 0.02 at 7.5 % (the fixed radius before),
/// and the held-out frames' MAE inside the object masks 14.2 against 19.5 mm (docs/grasping.md,
/// "The relief radius and its fixed point").
pub const RELIEF_RADIUS_SHARES: [f64; 4] = [0.03, 0.045, 0.06, 0.075];
/// The radius every fit may keep whatever its factor's sign (the only one before fit step 1c);
/// a smaller one is kept only with a flattening factor (module documentation, step 1c).
const DEFAULT_RELIEF_RADIUS_SHARE: f64 = 0.075;

/// Iterations of the relief fixed point of [`DepthErrorModel::expected_truth_map`]: the
/// correction's gain per iteration is at most 1.22 · c / (1 + c) (≤ 0.61 for the largest
/// factor, 1; the box filter's transfer function dips to −0.22), so three leave at most a
/// quarter of the first step's error on the largest factor and 1 % on a typical 0.25.
pub const RELIEF_FIXED_POINT_ITERATIONS: usize = 3;

/// Correlation lengths of the fine, medium and coarse fields, pixels (of a
/// [`REFERENCE_WIDTH_PX`]-wide image for a uniform model).
pub const FIELD_SCALES_PX: [f64; 3] = [2.0, 8.0, 32.0];

/// Image width (pixels) [`FIELD_SCALES_PX`] are set for in a uniform model
/// ([`DepthErrorModel::uniform_for_width`]).
pub const REFERENCE_WIDTH_PX: f64 = 640.0;

fn default_relief_max_m() -> f64 {
    MAX_RELIEF_M
}

/// The fit reads every `FIT_STRIDE`-th row and column (the windowed maps are computed at full
/// resolution first): a quarter of the pixels is plenty for a few numbers, and keeps the fit
/// within a few milliseconds.
const FIT_STRIDE: usize = 2;

/// The relief radius is chosen (fit step 1c) on every `RADIUS_CHOICE_STEP`-th row and column
/// of the fit's grid.
const RADIUS_CHOICE_STEP: usize = 4;

/// Lags of the residual semivariogram on the fit's grid (× [`FIT_STRIDE`] pixels: 2–64 px).
const LAGS: [usize; 6] = [1, 2, 4, 8, 16, 32];

/// Correlation length of the edge field, pixels.
const EDGE_SCALE_PX: f64 = 2.0;

/// The smallest variance share of a short-range field that [`DepthErrorModel::expected_truth`]
/// smooths out.
const SHORT_SHARE_MIN: f64 = 0.01;

/// The smallest share of the calibration's flat σ that a frame's own residual can set
/// ([`DepthErrorModel::for_frame`], [`DepthErrorModel::for_frame_on_background`]).
pub const FRAME_SIGMA_FLOOR: f64 = 0.25;

/// The error model of a calibration's aligned depth (module documentation). Metres.
///
/// Not `Copy`: a model may carry its calibration's map of the distance to the nearest sample
/// ([`DepthErrorModel::sample_distance_px`], shared, cheap to clone).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DepthErrorModel {
    /// σ of the flat error at `depth_ref_m` (offset and fields together), metres.
    pub sigma_flat_m: f64,
    /// The calibration frames' own part of `sigma_flat_m`: σ of their dense flat residual
    /// alone, without the fit's optimism at its samples (fit step 2), metres at `depth_ref_m`. A frame
    /// re-aligned onto the calibration's own output keeps this error and adds its re-alignment
    /// residual ([`DepthErrorModel::with_frame_drift`]). `None` in calibration files before
    /// version 7 (`sigma_flat_m` stands in for it) and in models not fitted on frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma_dense_m: Option<f64>,
    /// Reference depth of `sigma_flat_m`, metres.
    pub depth_ref_m: f64,
    /// Exponent p of the flat σ's growth with depth, `(z / depth_ref_m)^p` (0 or 2).
    pub depth_exponent: f64,
    /// Shares of the flat variance: offset, fine, medium and coarse field (sum 1).
    pub variance_shares: [f64; 4],
    /// Correlation lengths of the fine, medium and coarse fields, pixels.
    pub scales_px: [f64; 3],
    /// Mean of the relief factor c (truth − aligned = c·hp).
    pub relief_bias: f64,
    /// σ of the relief factor.
    pub relief_sigma: f64,
    /// Radius of the box blur that defines the relief hp, pixels.
    pub relief_radius_px: u32,
    /// Largest relief |hp| the relief factor was fitted on and is applied to, metres
    /// ([`MAX_RELIEF_M`] in calibration files before version 6; fit step 1b).
    #[serde(default = "default_relief_max_m")]
    pub relief_max_m: f64,
    /// Mean share `a` of the step that the truth takes near a depth edge (module
    /// documentation: `a · step(u, v)`), in [0, 1].
    pub edge_sharpening: f64,
    /// σ of that share between frames.
    pub edge_sharpening_sigma: f64,
    /// σ of the edge part per metre of relief (dimensionless, ≥ 0).
    pub edge_gain: f64,
    /// Radius of the relief window, pixels.
    pub edge_radius_px: u32,
    /// σ of a per-frame relative error of the heights above the support plane (dimensionless):
    /// truth − aligned = −k · h, `k ~ N(0, height_sigma²)`, h the aligned depth's height above
    /// its support plane ([`crate::height::height_above_plane`]). Set by the calibration
    /// ([`crate::height`]: how far its scale at an object rests on the calibration frame's own
    /// objects), not by [`DepthErrorModel::fit`]; 0 (absent) in calibration files before
    /// version 8.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub height_sigma: f64,
    /// σ of the flat error added per pixel of distance to the nearest calibration sample,
    /// metres at `depth_ref_m` per pixel, in quadrature: the flat σ at depth z and distance d
    /// (pixels) is `(z / depth_ref_m)^p · √(sigma_flat_m² + (gain · d)²)`. Where the samples
    /// cover only part of the image the alignment extrapolates beyond them (module
    /// documentation, fit step 5); fitted only then ([`crate::sampling::SampleReach::is_partial`]),
    /// 0 otherwise, and absent (0) in calibration files before version 9. It needs the distance
    /// map [`Self::sample_distance_px`]: without one the part is left out.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub sample_distance_gain: f64,
    /// The distance (pixels) from each pixel of the calibration's image to its nearest sample
    /// ([`crate::sampling::sample_distance_map`]), which [`Self::sample_distance_gain`] reads.
    /// Not stored in the file: the calibration attaches it from its samples
    /// ([`crate::pipeline::Calibration::frame_error_model`]) when the gain is not 0.
    #[serde(skip)]
    pub sample_distance_px: Option<Arc<Array2<f32>>>,
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

impl Default for DepthErrorModel {
    /// A model with no error at all (σ = 0 everywhere; draws equal the input).
    fn default() -> Self {
        Self {
            sigma_flat_m: 0.0,
            sigma_dense_m: None,
            depth_ref_m: 1.0,
            depth_exponent: 0.0,
            variance_shares: [0.0, 0.0, 0.0, 1.0],
            scales_px: FIELD_SCALES_PX,
            relief_bias: 0.0,
            relief_sigma: 0.0,
            relief_radius_px: 48,
            relief_max_m: MAX_RELIEF_M,
            edge_sharpening: 0.0,
            edge_sharpening_sigma: 0.0,
            edge_gain: 0.0,
            edge_radius_px: 3,
            height_sigma: 0.0,
            sample_distance_gain: 0.0,
            sample_distance_px: None,
        }
    }
}

/// What [`DepthErrorModel::fit`] reads of one frame: every [`FIT_STRIDE`]-th row and column of
/// the depths and of the windowed maps (computed at full resolution).
struct FitGrid {
    aligned: Array2<f32>,
    truth: Array2<f32>,
    relief: Array2<f32>,
    step: Array2<f32>,
    hp: Array2<f32>,
}

/// Upper bounds of the relief bands of fit step 1b, metres: [`MAX_RELIEF_M`] (the factor's own
/// fit), then doubling up to [`MAX_RELIEF_EXTENDED_M`].
const RELIEF_BAND_BOUNDS_M: [f64; 5] = [
    MAX_RELIEF_M,
    2.0 * MAX_RELIEF_M,
    4.0 * MAX_RELIEF_M,
    8.0 * MAX_RELIEF_M,
    MAX_RELIEF_EXTENDED_M,
];

/// Sums over one relief band's pixels (those of the fit grid with both depths), with `x =
/// truth − aligned − a·step` (metres).
#[derive(Debug, Clone, Copy, Default)]
struct BandSums {
    /// Σ x·hp, Σ hp², Σ x²
    sxh: f64,
    shh: f64,
    sxx: f64,
    /// Σ |x| and Σ |x − c·hp|: the absolute residual without and with the relief correction
    abs: f64,
    abs_corrected: f64,
    n: usize,
}

impl BandSums {
    /// The sums of the bands of [`RELIEF_BAND_BOUNDS_M`] beyond the first (band k: `bound[k−1]
    /// < |hp| ≤ bound[k]`) over `large`: the `(truth − aligned, hp, step)` of the grid's pixels
    /// with both depths and `bound[0] < |hp| ≤ bound[last]`, collected by the joint fit's pass.
    /// Band 0 (the factor's own fit) is left empty.
    fn per_band(large: &[(f32, f32, f32)], a: f64, c: f64) -> [Self; RELIEF_BAND_BOUNDS_M.len()] {
        let mut bands = [Self::default(); RELIEF_BAND_BOUNDS_M.len()];
        for &(x, h, st) in large {
            let h = f64::from(h);
            let Some(k) = RELIEF_BAND_BOUNDS_M.iter().position(|&hi| h.abs() <= hi) else {
                continue;
            };
            let b = &mut bands[k];
            let x = f64::from(x) - a * f64::from(st);
            b.sxh += x * h;
            b.shh += h * h;
            b.sxx += x * x;
            b.abs += x.abs();
            b.abs_corrected += (x - c * h).abs();
            b.n += 1;
        }
        bands
    }
}

/// The relief range of the factor `c` fitted on `|hp| ≤` [`MAX_RELIEF_M`] (module
/// documentation, fit step 1b): bands of larger relief join while each is large enough (at
/// least 100 grid pixels and 0.5 % of the grid), its own factor is within
/// [`RELIEF_BAND_FACTOR_RATIO`] of `c`, the correction explains at least
/// [`RELIEF_BAND_MIN_EXPLAINED`] of its squared residuals and lowers its absolute residual to
/// at most [`RELIEF_BAND_MAX_ABS_RATIO`]. Returns `c` refitted over the whole
/// range (the edge share `a` kept) and the range, metres. A tall object that the depth model
/// flattens as it flattens small ones is then corrected over its whole height; a wall or far
/// background whose error is not a relief factor (as in real models' predictions,
/// docs/grasping.md) stops the range at the first band that does not follow it. `large`: as
/// in [`BandSums::per_band`]; `grid_px`: the fit grids' pixel count; `small`: `Σ x·hp` and
/// `Σ hp²` over `|hp| ≤` [`MAX_RELIEF_M`] (from the joint fit's normal equations).
fn extend_relief_range(
    large: &[(f32, f32, f32)],
    grid_px: usize,
    c: f64,
    a: f64,
    small: (f64, f64),
) -> (f64, f64) {
    if c <= 0.0 {
        // no flattening measured: nothing to extend
        return (c, MAX_RELIEF_M);
    }
    let mut bands = BandSums::per_band(large, a, c);
    (bands[0].sxh, bands[0].shh) = small;
    let min_band_px = 100.max(grid_px / 200);
    let follows = |band: &BandSums| {
        if band.n < min_band_px || band.shh <= 0.0 || band.sxx <= 0.0 || band.abs <= 0.0 {
            return false;
        }
        let band_c = band.sxh / band.shh;
        let explained = band.sxh * band.sxh / (band.shh * band.sxx);
        band_c >= c / RELIEF_BAND_FACTOR_RATIO
            && band_c <= c * RELIEF_BAND_FACTOR_RATIO
            && explained >= RELIEF_BAND_MIN_EXPLAINED
            && band.abs_corrected <= RELIEF_BAND_MAX_ABS_RATIO * band.abs
    };
    let joined = bands[1..].iter().take_while(|b| follows(b)).count();
    if joined == 0 {
        return (c, MAX_RELIEF_M);
    }
    let (sxh, shh) = bands[..=joined]
        .iter()
        .fold((0.0, 0.0), |(sxh, shh), b| (sxh + b.sxh, shh + b.shh));
    let c = if shh > 0.0 { sxh / shh } else { c };
    (c, RELIEF_BAND_BOUNDS_M[joined])
}

/// Fit steps 1 and 1b on the grids' relief `hp` (one radius).
#[derive(Debug, Clone, Copy)]
struct ReliefFit {
    /// The relief factor c (clamped to ±10).
    factor: f64,
    /// The edge step share a, in [0, 1].
    edge_share: f64,
    /// The relief range, metres.
    range_m: f64,
}

impl ReliefFit {
    /// Steps 1 and 1b (module documentation) over the grids' pixels with both depths.
    fn of(prepared: &[FitGrid]) -> Self {
        // 1. the relief factor c and the edge step share a, jointly: least squares of
        // truth − aligned = c·hp + a·step over the pixels of small-object relief
        let mut normal_eq = [0.0f64; 5]; // Σhh, Σhs, Σss, Σxh, Σxs
        // the pixels of larger relief, for the relief range (step 1b)
        let mut large: Vec<(f32, f32, f32)> = Vec::new();
        for g in prepared {
            for (a, t, h, st) in g.pixels_with_both_depths() {
                let relief = f64::from(h.abs());
                if relief <= MAX_RELIEF_M {
                    let (x, h, st) = (f64::from(t - a), f64::from(h), f64::from(st));
                    normal_eq[0] += h * h;
                    normal_eq[1] += h * st;
                    normal_eq[2] += st * st;
                    normal_eq[3] += x * h;
                    normal_eq[4] += x * st;
                } else if relief <= MAX_RELIEF_EXTENDED_M {
                    large.push((t - a, h, st));
                }
            }
        }
        let [shh, shs, sss, sxh, sxs] = normal_eq;
        let alone = |sxy: f64, syy: f64| if syy > 0.0 { sxy / syy } else { 0.0 };
        let det = shh * sss - shs * shs;
        let (mut c, mut a) = if det > 1e-12 * (shh * sss).max(f64::MIN_POSITIVE) {
            ((sxh * sss - sxs * shs) / det, (sxs * shh - sxh * shs) / det)
        } else {
            (alone(sxh, shh), 0.0)
        };
        if !(0.0..=1.0).contains(&a) {
            // the share of a step is in [0, 1]: at a bound, c alone on what is left
            a = a.clamp(0.0, 1.0);
            c = alone(sxh - a * shs, shh);
        }
        if !(MIN_RELIEF_FACTOR..=MAX_RELIEF_FACTOR).contains(&c) {
            // not a depth model's flattening or exaggeration (a noisy reference, scene
            // structure): no relief correction, the edge share alone
            c = 0.0;
            a = alone(sxs, sss).clamp(0.0, 1.0);
        }
        // 1b. the relief range: wider than MAX_RELIEF_M where the truth keeps the same factor
        // over |hp| ≤ MAX_RELIEF_M: Σ(x − a·step)·hp = Σxh − a·Σhs, and Σhh
        let grid_px = prepared.iter().map(|g| g.hp.len()).sum();
        let (c, relief_max_m) = extend_relief_range(&large, grid_px, c, a, (sxh - a * shs, shh));
        Self {
            factor: c.clamp(-10.0, 10.0),
            edge_share: a,
            range_m: relief_max_m,
        }
    }

    /// The mean squared difference, m², between the truth and the first-order expected truth
    /// (`aligned + c·hp + a·step`, the relief clamped at the range, as
    /// [`DepthErrorModel::expected_truth_map`] before its fixed point) over the grids' pixels
    /// with both depths (`f64::INFINITY` without one).
    fn grid_mse(&self, prepared: &[FitGrid]) -> f64 {
        let (c, a, rmax) = (
            self.factor as f32,
            self.edge_share as f32,
            self.range_m as f32,
        );
        let (mut sum, mut n) = (0.0f64, 0usize);
        for g in prepared {
            for (z, t, h, st) in g.pixels_with_both_depths() {
                let mut e = add_relief(z, h, c, rmax);
                if a > 0.0 {
                    e = add_edge_share(e, st, a);
                }
                sum += f64::from(t - e).powi(2);
                n += 1;
            }
        }
        if n == 0 {
            f64::INFINITY
        } else {
            sum / n as f64
        }
    }
}

/// The values of one of the fit's grids (a [`FitGrid`]'s maps, the rests), row by row. Every
/// such map is built in standard layout (`to_owned` of a view, `map_collect` of standard-layout
/// inputs), so this never fails; the slices iterate several times faster than the arrays'
/// element iterators (the relief fit and the rest's pixels: 4.6 → 4.4 ms of the fit,
/// criterion side by side).
fn grid_slice(a: &Array2<f32>) -> &[f32] {
    a.as_slice()
        .expect("the error model's grids are built in standard layout")
}

impl FitGrid {
    /// The grid of `frame`: its depths and the filters' outputs on the fit's grid only (the
    /// full maps' values there), without the relief hp.
    fn of(frame: &ResidualFrame<'_>, edge_radius_px: u32) -> Self {
        let edges = EdgeMaps::of_strided(frame.aligned_m, edge_radius_px, FIT_STRIDE);
        let grid = ndarray::s![..;FIT_STRIDE, ..;FIT_STRIDE];
        Self {
            aligned: frame.aligned_m.slice(grid).to_owned(),
            truth: frame.truth_m.slice(grid).to_owned(),
            relief: edges.relief,
            step: edges.step,
            hp: Array2::zeros((0, 0)),
        }
    }

    /// Every `step`-th row and column of the grid's depths and edge maps, without the relief
    /// hp.
    fn subsampled(&self, step: usize) -> Self {
        let step = step.max(1) as isize;
        let every = |a: &Array2<f32>| a.slice(ndarray::s![..;step, ..;step]).to_owned();
        Self {
            aligned: every(&self.aligned),
            truth: every(&self.truth),
            relief: every(&self.relief),
            step: every(&self.step),
            hp: Array2::zeros((0, 0)),
        }
    }

    /// `(aligned, truth, hp, step)` of the grid's pixels where both depths are valid.
    fn pixels_with_both_depths(&self) -> impl Iterator<Item = (f32, f32, f32, f32)> + '_ {
        grid_slice(&self.aligned)
            .iter()
            .zip(grid_slice(&self.truth))
            .zip(grid_slice(&self.hp))
            .zip(grid_slice(&self.step))
            .filter(|(((a, t), _), _)| is_valid_depth(**a) && is_valid_depth(**t))
            .map(|(((&a, &t), &h), &st)| (a, t, h, st))
    }
}

/// One calibration sample's residual (truth − aligned, metres) held out of the fit (a
/// cross-validation fold's refit without it) and in it (the calibration's own fit), with its
/// true depth: the pair is what the fit's having seen the sample is worth there
/// ([`DepthErrorModel::fit`], step 2).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeldOutResidual {
    /// Truth − the fold's refit, metres.
    pub held_out_m: f64,
    /// Truth − the calibration's fit (which saw the sample), metres.
    pub in_sample_m: f64,
    /// The sample's true depth, metres.
    pub depth_m: f64,
}

/// One calibration frame's residuals for [`DepthErrorModel::fit`].
#[derive(Debug, Clone, Copy)]
pub struct ResidualFrame<'a> {
    /// The calibration's aligned depth of the frame, metres (NaN: no depth).
    pub aligned_m: ArrayView2<'a, f32>,
    /// The frame's ground truth, metres (NaN or ≤ 0: no depth).
    pub truth_m: ArrayView2<'a, f32>,
}

impl DepthErrorModel {
    /// A uniform model: σ = `sigma_m` everywhere, as a coarse field (no offset, relief or edge
    /// part); for planning on a depth map that has no calibration
    /// (`moma grasp --depth … --sigma-m S`).
    ///
    /// # Errors
    /// `sigma_m` not finite or outside [0, 10] m.
    pub fn uniform(sigma_m: f64) -> Result<Self> {
        let m = Self {
            sigma_flat_m: sigma_m,
            ..Self::default()
        };
        m.validate()?;
        Ok(m)
    }

    /// [`Self::uniform`] for an image `width_px` wide: the field's correlation lengths
    /// ([`FIELD_SCALES_PX`], set for 640 px) scaled by `width_px / 640`, so that the error
    /// spans the same share of the view at any resolution (at 1280 × 720 the fixed 32 px made a
    /// box's top fluctuate twice as fast, and its suction grasps' success probabilities fell
    /// from 0.88 to 0.41 for the same σ). 640 px gives [`Self::uniform`] exactly.
    ///
    /// # Errors
    /// As [`Self::uniform`].
    pub fn uniform_for_width(sigma_m: f64, width_px: usize) -> Result<Self> {
        let mut m = Self::uniform(sigma_m)?;
        let k = width_px as f64 / REFERENCE_WIDTH_PX;
        m.scales_px = FIELD_SCALES_PX.map(|s| (s * k).clamp(1.0, 4096.0));
        Ok(m)
    }

    /// Checks the fields (a model read from a file).
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] naming the field.
    pub fn validate(&self) -> Result<()> {
        let bad = |what: &str, v: f64, rule: &str| {
            Err(CoreError::InvalidParameter(format!(
                "depth error model: {what} = {v} must be {rule}"
            )))
        };
        let within = |v: f64, lo: f64, hi: f64| v.is_finite() && (lo..=hi).contains(&v);
        if !within(self.sigma_flat_m, 0.0, 10.0) {
            return bad("sigma_flat_m", self.sigma_flat_m, "finite, in [0, 10] m");
        }
        if let Some(d) = self.sigma_dense_m
            && !within(d, 0.0, 10.0)
        {
            return bad("sigma_dense_m", d, "finite, in [0, 10] m");
        }
        if !within(self.depth_ref_m, 1e-3, 1e3) {
            return bad("depth_ref_m", self.depth_ref_m, "in [0.001, 1000] m");
        }
        if !within(self.depth_exponent, 0.0, 4.0) {
            return bad("depth_exponent", self.depth_exponent, "in [0, 4]");
        }
        let sum: f64 = self.variance_shares.iter().sum();
        if self.variance_shares.iter().any(|&s| !within(s, 0.0, 1.0)) || (sum - 1.0).abs() > 1e-6 {
            return bad("the variance shares' sum", sum, "1, each share in [0, 1]");
        }
        if let Some(&s) = self.scales_px.iter().find(|&&s| !within(s, 1.0, 4096.0)) {
            return bad("a field scale", s, "in [1, 4096] px");
        }
        if !within(self.relief_bias, -10.0, 10.0) {
            return bad("relief_bias", self.relief_bias, "finite, in [-10, 10]");
        }
        if !within(self.relief_sigma, 0.0, 10.0) {
            return bad("relief_sigma", self.relief_sigma, "finite, in [0, 10]");
        }
        if !within(self.edge_sharpening, 0.0, 1.0) {
            return bad("edge_sharpening", self.edge_sharpening, "in [0, 1]");
        }
        if !within(self.edge_sharpening_sigma, 0.0, 1.0) {
            return bad(
                "edge_sharpening_sigma",
                self.edge_sharpening_sigma,
                "in [0, 1]",
            );
        }
        if !within(self.edge_gain, 0.0, 10.0) {
            return bad("edge_gain", self.edge_gain, "finite, in [0, 10]");
        }
        if !within(self.relief_max_m, 0.0, 10.0) {
            return bad("relief_max_m", self.relief_max_m, "finite, in [0, 10] m");
        }
        if !within(self.height_sigma, 0.0, 10.0) {
            return bad("height_sigma", self.height_sigma, "finite, in [0, 10]");
        }
        if !within(self.sample_distance_gain, 0.0, 1.0) {
            return bad(
                "sample_distance_gain",
                self.sample_distance_gain,
                "finite, in [0, 1] m per pixel",
            );
        }
        if self.edge_radius_px > 64 || self.relief_radius_px > 1024 {
            return bad(
                "edge_radius_px / relief_radius_px",
                self.edge_radius_px.max(self.relief_radius_px) as f64,
                "at most 64 / 1024 px",
            );
        }
        Ok(())
    }

    /// Fits the model (module documentation) from the calibration frames' dense residuals and
    /// the calibration samples' residuals held out of the fit and in it (`held_out`, may be
    /// empty: the ratio of their sums of squares is the fit's optimism, which grows the dense
    /// level up to their held-out mean square at most; non-finite residuals are left out).
    /// `depth_exponent` is 2 for a fit in inverse space, 0 in depth space.
    ///
    /// # Errors
    /// A frame whose aligned depth and truth differ in size; no flat pixel with both depths.
    pub fn fit(
        frames: &[ResidualFrame<'_>],
        held_out: &[HeldOutResidual],
        depth_exponent: f64,
    ) -> Result<Self> {
        Self::fit_with_sample_distance(frames, held_out, depth_exponent, None)
    }

    /// [`DepthErrorModel::fit`] with the distance part (fit step 5) when `sample_distance_px`
    /// is given: the distance (pixels) from each pixel of the frames' image to the nearest
    /// calibration sample ([`crate::sampling::sample_distance_map`]). The calibration gives it
    /// only when its samples reach part of the image
    /// ([`crate::sampling::SampleReach::is_partial`]); the model returned carries it
    /// ([`DepthErrorModel::sample_distance_px`]).
    ///
    /// # Errors
    /// As [`DepthErrorModel::fit`]; a distance map of another size than the frames.
    pub fn fit_with_sample_distance(
        frames: &[ResidualFrame<'_>],
        held_out: &[HeldOutResidual],
        depth_exponent: f64,
        sample_distance_px: Option<ArrayView2<'_, f32>>,
    ) -> Result<Self> {
        if let Some(d) = sample_distance_px
            && let Some((k, f)) = frames
                .iter()
                .enumerate()
                .find(|(_, f)| ImageSize::of(&f.aligned_m) != ImageSize::of(&d))
        {
            return Err(CoreError::InvalidParameter(format!(
                "depth error model: sample distance map {} but calibration frame {k} {}",
                ImageSize::of(&d),
                ImageSize::of(&f.aligned_m)
            )));
        }
        // the distance on the fit's grid
        let grid_distance = sample_distance_px.map(|d| {
            d.slice(ndarray::s![..;FIT_STRIDE, ..;FIT_STRIDE])
                .to_owned()
        });
        let mut m = Self {
            depth_exponent,
            ..Self::default()
        };
        let mut prepared = Vec::with_capacity(frames.len());
        let mut depths: Vec<f32> = Vec::new();
        for (k, f) in frames.iter().enumerate() {
            let size = ImageSize::of(&f.aligned_m);
            if ImageSize::of(&f.truth_m) != size {
                return Err(CoreError::InvalidParameter(format!(
                    "depth error model: calibration frame {k}: aligned depth {size} but ground \
                     truth {}",
                    ImageSize::of(&f.truth_m)
                )));
            }
            // the relief hp per radius below
            let sub = FitGrid::of(f, m.edge_radius_px);
            // the reference depth: the median of the grid's pixels with both depths
            depths.extend(
                grid_slice(&sub.aligned)
                    .iter()
                    .zip(grid_slice(&sub.truth))
                    .filter(|(a, t)| is_valid_depth(**a) && is_valid_depth(**t))
                    .map(|(a, _)| *a),
            );
            prepared.push(sub);
        }
        if depths.is_empty() {
            return Err(no_pixels());
        }
        // the flat threshold (FLAT_RELIEF_M's documentation), from every fourth relief value
        let mut reliefs: Vec<f32> = prepared
            .iter()
            .flat_map(|g| grid_slice(&g.relief).iter().copied().step_by(4))
            .filter(|r| r.is_finite())
            .collect();
        let flat_relief = if reliefs.is_empty() {
            FLAT_RELIEF_M
        } else {
            let k = reliefs.len() / 2;
            FLAT_RELIEF_M.max(1.5 * *reliefs.select_nth_unstable_by(k, f32::total_cmp).1)
        };
        let mid = depths.len() / 2;
        m.depth_ref_m =
            f64::from(*depths.select_nth_unstable_by(mid, f32::total_cmp).1).clamp(1e-3, 1e3);
        // 1c. steps 1 and 1b for every relief radius on every RADIUS_CHOICE_STEP-th pixel of
        // the fit's grid (a sixteenth of its pixels: the fit stays within its 5 ms); the radius
        // whose expected truth is nearest the truth there (mean square) is kept, and steps 1
        // and 1b run again on the whole grid with it
        let box_sums: Vec<BoxSums> = frames.iter().map(|f| BoxSums::of(f.aligned_m)).collect();
        let mut coarse: Vec<FitGrid> = prepared
            .iter()
            .map(|g| g.subsampled(RADIUS_CHOICE_STEP))
            .collect();
        let mut best_share = (f64::INFINITY, RELIEF_RADIUS_SHARES[0]);
        for share in RELIEF_RADIUS_SHARES {
            for ((g, f), sums) in coarse.iter_mut().zip(frames).zip(&box_sums) {
                let radius = relief_radius_for(ImageSize::of(&f.aligned_m), share);
                g.hp = sums.high_pass_strided(f.aligned_m, radius, RADIUS_CHOICE_STEP * FIT_STRIDE);
            }
            let fit = ReliefFit::of(&coarse);
            if fit.factor <= 0.0 && share != DEFAULT_RELIEF_RADIUS_SHARE {
                continue;
            }
            let mse = fit.grid_mse(&coarse);
            // the first (smallest) radius wins a tie
            if mse < best_share.0 {
                best_share = (mse, share);
            }
        }
        drop(coarse);
        let mut radius = 0;
        for ((g, f), sums) in prepared.iter_mut().zip(frames).zip(&box_sums) {
            radius = relief_radius_for(ImageSize::of(&f.aligned_m), best_share.1);
            g.hp = sums.high_pass_strided(f.aligned_m, radius, FIT_STRIDE);
        }
        drop(box_sums);
        let fit = ReliefFit::of(&prepared);
        m.relief_radius_px = radius;
        m.relief_max_m = fit.range_m;
        m.relief_bias = fit.factor;
        m.relief_sigma = m.relief_bias.abs();
        m.edge_sharpening = fit.edge_share;
        m.edge_sharpening_sigma = 0.5 * fit.edge_share;
        // 2. the normalised rest: flat mean square, offset, semivariogram
        let (mut sum_sq, mut sum, mut n_flat) = (0.0f64, 0.0f64, 0usize);
        let mut gamma = [(0.0f64, 0usize); LAGS.len()];
        let mut rests = Vec::with_capacity(frames.len());
        for g in &prepared {
            let relief = &g.relief;
            let rest = ndarray::Zip::from(&g.aligned)
                .and(&g.truth)
                .and(&g.hp)
                .and(&g.step)
                .map_collect(|&a, &t, &h, &st| {
                    if !(is_valid_depth(a) && is_valid_depth(t)) {
                        return f32::NAN;
                    }
                    let h = if h.is_finite() { h } else { 0.0 };
                    let explained =
                        m.relief_bias * f64::from(h) + m.edge_sharpening * f64::from(st);
                    ((f64::from(t - a) - explained) / m.depth_scale(a)) as f32
                });
            // the rest where it is flat, NaN elsewhere, row-major: one test per neighbour
            let (h, w) = rest.dim();
            let fl: Vec<f32> = ndarray::Zip::from(&rest)
                .and(relief)
                .map_collect(|&x, &r| {
                    if x.is_finite() && r < flat_relief {
                        x
                    } else {
                        f32::NAN
                    }
                })
                .into_iter()
                .collect();
            for v in 0..h {
                let row = &fl[v * w..(v + 1) * w];
                for (u, &xf) in row.iter().enumerate() {
                    if xf.is_nan() {
                        continue;
                    }
                    let x = f64::from(xf);
                    sum_sq += x * x;
                    sum += x;
                    n_flat += 1;
                    // the same order of additions as a pixel-by-pixel scan: right, then down
                    for (g, &lag) in gamma.iter_mut().zip(&LAGS) {
                        if let Some(&y) = row.get(u + lag)
                            && !y.is_nan()
                        {
                            g.0 += (x - f64::from(y)).powi(2);
                            g.1 += 1;
                        }
                        if v + lag < h {
                            let y = fl[(v + lag) * w + u];
                            if !y.is_nan() {
                                g.0 += (x - f64::from(y)).powi(2);
                                g.1 += 1;
                            }
                        }
                    }
                }
            }
            rests.push(rest);
        }
        if n_flat == 0 {
            return Err(no_pixels());
        }
        let dense = sum_sq / n_flat as f64;
        // 5. the distance part: the rest's mean square over flat pixels as `σ0² + gain²·d²`
        let near = match grid_distance
            .as_ref()
            .and_then(|d| distance_part(&rests, &prepared, d, flat_relief))
        {
            Some((near, gain)) => {
                m.sample_distance_gain = gain.min(1.0);
                near
            }
            None => dense,
        };
        // the fit's optimism: by how much the samples' squared residuals grow when the fit has
        // not seen them, as a ratio (an outlier, or a sample at a silhouette, weighs on both
        // sums alike; least squares with p parameters on n samples gives about 1 + 2p/n),
        // never beyond the held-out mean square itself (a fit nearly exact at a few samples
        // has a ratio without bound, and a truth of the samples alone has the samples' own
        // level as its dense one: the held-out mean square is then the level); non-finite
        // residuals are left out
        let (mut held_sq, mut in_sq, mut n_held) = (0.0f64, 0.0f64, 0usize);
        for r in held_out {
            let scale = m.depth_scale(r.depth_m as f32);
            let (h, i) = (r.held_out_m / scale, r.in_sample_m / scale);
            if h.is_finite() && i.is_finite() {
                held_sq += h * h;
                in_sq += i * i;
                n_held += 1;
            }
        }
        let optimistic = |level: f64| -> f64 {
            if n_held == 0 {
                return level;
            }
            let held_ms = held_sq / n_held as f64;
            let ratio = if in_sq > 0.0 {
                (held_sq / in_sq).max(1.0)
            } else {
                f64::INFINITY
            };
            (level * ratio).min(level.max(held_ms))
        };
        let total = optimistic(dense);
        // with a distance part, the flat σ is its level at the samples (the optimism is
        // measured there); the variance shares below keep the whole frame's proportions
        m.sigma_flat_m = optimistic(near).sqrt().min(10.0);
        // the whole frame's dense level: what a re-aligned frame's background σ is compared
        // with (its anchors lie near and far from the samples alike)
        m.sigma_dense_m = Some(dense.sqrt().min(10.0));
        if total > 0.0 {
            let mean = sum / n_flat as f64;
            let offset = (mean * mean / total).clamp(0.0, 1.0);
            let semi: Vec<(f64, f64)> = LAGS
                .iter()
                .zip(&gamma)
                .filter(|(_, g)| g.1 > 0)
                .map(|(&l, g)| ((l * FIT_STRIDE) as f64, 0.5 * g.0 / g.1 as f64))
                .collect();
            let v = field_variances(&semi, &m.scales_px);
            let fields: f64 = v.iter().sum();
            // The semivariogram saturates at the fields' variance within its longest lag
            // (64 px). What it has not reached there varies over longer distances than any
            // field: over a gripper's footprint it moves the surface as a whole, so it joins
            // the offset. Spread over the fields in proportion (as before), it made the coarse
            // field several times too rough at the scale of a suction cup: m2t2-table's
            // draws broke seals that the truth keeps (docs/grasping.md).
            let offset = offset.max(1.0 - fields / total).clamp(0.0, 1.0);
            // the fields share what the offset leaves, in the semivariogram's proportions
            let rest_share = 1.0 - offset;
            m.variance_shares = if fields > 0.0 {
                [
                    offset,
                    rest_share * v[0] / fields,
                    rest_share * v[1] / fields,
                    rest_share * v[2] / fields,
                ]
            } else {
                [offset, 0.0, 0.0, rest_share]
            };
        }
        // 3. edge noise: (rest·scale)² − σ_flat(z)² = g²·relief², through the origin, g ≥ 0
        // (with a distance part, σ_flat at each pixel's distance)
        let edge_pixels = || {
            prepared.iter().zip(&rests).flat_map(|(g, rest)| {
                grid_slice(rest)
                    .iter()
                    .zip(grid_slice(&g.relief))
                    .zip(grid_slice(&g.aligned))
                    .enumerate()
                    .filter(|(_, ((x, r), _))| x.is_finite() && **r >= flat_relief)
                    .map(|(i, ((&x, &r), &a))| (i, f64::from(x), f64::from(r), a))
            })
        };
        let (mut num, mut den) = (0.0f64, 0.0f64);
        for (i, x, r, a) in edge_pixels() {
            let s = m.depth_scale(a);
            let e2 = (x * s).powi(2);
            let r2 = r * r;
            let level = match &grid_distance {
                Some(d) => m.flat_level(grid_slice(d).get(i).copied()),
                None => m.sigma_flat_m,
            };
            num += r2 * (e2 - (level * s).powi(2));
            den += r2 * r2;
        }
        m.edge_gain = if den > 0.0 {
            (num / den).max(0.0).sqrt().min(10.0)
        } else {
            0.0
        };
        if m.sample_distance_gain > 0.0 {
            m.sample_distance_px = sample_distance_px.map(|d| Arc::new(d.to_owned()));
        }
        m.validate()?;
        Ok(m)
    }

    /// The flat σ at the reference depth `depth_ref_m` of a pixel `distance_px` (pixels) from
    /// the nearest calibration sample, metres: `√(sigma_flat_m² + (sample_distance_gain · d)²)`
    /// (`sigma_flat_m` without a distance part).
    pub fn flat_sigma_at_distance_m(&self, distance_px: f64) -> f64 {
        self.flat_level(Some(distance_px as f32))
    }

    /// The flat σ's level at a pixel `distance_px` from the nearest calibration sample, metres
    /// at the reference depth: `√(sigma_flat_m² + (sample_distance_gain · d)²)`;
    /// `sigma_flat_m` without a distance (`None`, or a non-finite one: no sample at all).
    fn flat_level(&self, distance_px: Option<f32>) -> f64 {
        match distance_px {
            Some(d) if self.sample_distance_gain > 0.0 && d.is_finite() => self
                .sigma_flat_m
                .hypot(self.sample_distance_gain * f64::from(d)),
            _ => self.sigma_flat_m,
        }
    }

    /// The distance map when the model has a distance part and one of `size` (the map it is
    /// applied to); `None` otherwise.
    fn distance_map(&self, size: ImageSize) -> Option<&Arc<Array2<f32>>> {
        self.sample_distance_px
            .as_ref()
            .filter(|d| self.sample_distance_gain > 0.0 && ImageSize::of(&d.view()) == size)
    }

    /// `(z / depth_ref_m)^depth_exponent` (1 for an invalid z).
    fn depth_scale(&self, z: f32) -> f64 {
        if self.depth_exponent == 0.0 || !is_valid_depth(z) {
            1.0
        } else if self.depth_exponent == 2.0 {
            // the exponent every fit in inverse space has: no powf per pixel
            let r = f64::from(z) / self.depth_ref_m;
            r * r
        } else {
            (f64::from(z) / self.depth_ref_m).powf(self.depth_exponent)
        }
    }

    /// The model of one frame: `sigma_flat_m` set to the frame's own background residual
    /// against the **truth** (metres at the reference depth, e.g. the held-out anchor RMSE
    /// after re-alignment onto the calibration frame's ground truth), which measures this
    /// frame's flat error where the calibration frame's only predicts it: larger when the frame
    /// drifted, smaller when re-alignment removed what the one-shot fit left. Never below
    /// [`FRAME_SIGMA_FLOOR`] of the calibration's σ (a few anchors can happen to agree), nor
    /// above 10 m. A residual against the calibration's own output is
    /// [`DepthErrorModel::with_frame_drift`]'s.
    pub fn for_frame(&self, frame_residual_m: Option<f64>) -> Self {
        match frame_residual_m {
            Some(r) if r.is_finite() => Self {
                sigma_flat_m: r.max(FRAME_SIGMA_FLOOR * self.sigma_flat_m).min(10.0),
                ..self.clone()
            },
            _ => self.clone(),
        }
    }

    /// The model of one frame re-aligned onto the calibration's **own output** (the default
    /// anchor target): `drift_residual_m` (metres, e.g. the held-out anchor RMSE after the
    /// correction) measures what the re-alignment left of the frame's change since
    /// calibration, not the calibration's own error, which every such frame keeps. The flat σ
    /// is then both, `hypot(σ_dense, drift)`, with σ_dense the calibration frames' own
    /// residual ([`DepthErrorModel::sigma_dense_m`]; `sigma_flat_m` for older files). The
    /// fit's optimism in `sigma_flat_m` is left out: it stands for what the calibration frame's
    /// residuals do not show, which the drift now measures. (Taking the drift
    /// alone, as [`DepthErrorModel::for_frame`] does for a residual against the truth, gave on
    /// the simulated shared sets 37.5 % of GSSA's re-aligned errors within ±1σ on
    /// gqcnn-primesense; docs/grasping.md, "The re-aligned frame's σ".) Without a finite
    /// residual, the calibration's model unchanged; never above 10 m.
    ///
    /// The drift's variance joins the **offset** share: the fine, medium and coarse fields keep
    /// the variance they have in σ_dense (in metres), and their shares shrink by
    /// `σ_dense² / σ_flat²`. The short-range part of a frame's error is the depth model's
    /// per-frame roughness, which the calibration frame already shows at its own level; what
    /// the anchors add is how this frame as a whole differs from it. Spread over the
    /// calibration's shares instead, a drift of a few millimetres on a nearly exact
    /// calibration (whose shares then describe round-off) became short-range noise, and the
    /// suction planner's guards against noise then cost 13 points of the ground truth's
    /// success rate on an exact prediction (docs/grasping.md, "What limits the deployed
    /// configuration").
    pub fn with_frame_drift(&self, drift_residual_m: Option<f64>) -> Self {
        match drift_residual_m {
            Some(r) if r.is_finite() => {
                let dense = self.sigma_dense_m.unwrap_or(self.sigma_flat_m);
                self.with_flat_sigma_keeping_fields(dense, dense.hypot(r.max(0.0)).min(10.0))
            }
            _ => self.clone(),
        }
    }

    /// The model of one re-aligned frame from its own error on the unchanged background: the
    /// RMSE against the calibration frame's ground truth at anchors no fit used, `rmse_m` in metres
    /// and `inverse_rmse_per_m` in inverse depth (1/m; `RealignReport::held_out_truth_rmse_m`
    /// and `held_out_truth_inverse_rmse_per_m`). The flat σ at the reference depth is
    /// `inverse_rmse · depth_ref²` for a model whose σ grows as z² (an error δ in inverse depth
    /// is δ·z² metres at depth z, so anchors at every depth measure the same quantity), and
    /// `rmse_m` for a constant one (and for another exponent, where it is the anchors' own
    /// depth's σ, an approximation).
    ///
    /// The fine, medium and coarse fields keep the variance they have in the calibration
    /// frames' dense residual σ_dense (metres), and the rest of the measured variance is the
    /// offset: the short-range roughness is the depth model's, which ~60 held-out anchors do
    /// not resolve and which the calibration frame shows at its own level (when the measured σ
    /// is below what the fields alone hold, or below [`FRAME_SIGMA_FLOOR`] of σ_dense, those
    /// floors are the flat σ). Never above 10 m; a non-finite residual leaves the model
    /// unchanged.
    ///
    /// Why the truth and not the correction's target: with the default target (the
    /// calibration's own output) the held-out RMSE measures the frame's change since
    /// calibration, and `hypot(σ_dense, that RMSE)` ([`DepthErrorModel::with_frame_drift`])
    /// counted the calibration frame's error twice where re-alignment had removed part of it:
    /// 13 of the 18 re-aligned σ-coverage rows of the shared sets were outside 55–80 % /
    /// ≥ 90 %, eleven of them too wide; with this model, 6 (docs/grasping.md, "The re-aligned
    /// frame's σ against the truth").
    pub fn for_frame_on_background(&self, rmse_m: f64, inverse_rmse_per_m: Option<f64>) -> Self {
        let at_ref = match inverse_rmse_per_m {
            Some(i) if self.depth_exponent == 2.0 => i * self.depth_ref_m * self.depth_ref_m,
            _ => rmse_m,
        };
        if !at_ref.is_finite() {
            return self.clone();
        }
        let dense = self.sigma_dense_m.unwrap_or(self.sigma_flat_m);
        let dense2 = dense * dense;
        let fields2 = dense2 * self.variance_shares[1..].iter().sum::<f64>();
        let floor2 = (FRAME_SIGMA_FLOOR * dense).powi(2);
        let sigma_flat_m = (at_ref.max(0.0).powi(2).max(fields2).max(floor2))
            .sqrt()
            .min(10.0);
        self.with_flat_sigma_keeping_fields(dense, sigma_flat_m)
    }

    /// The model with flat σ `sigma_flat_m` (metres at the reference depth) whose fine, medium
    /// and coarse fields keep the variance, in metres², they have at σ `dense_m`; the offset
    /// takes the rest (the rule of [`DepthErrorModel::with_frame_drift`] and
    /// [`DepthErrorModel::for_frame_on_background`]). Where the fields alone would exceed the
    /// new σ (only at the 10 m clamp or by rounding), they keep their proportions and the
    /// offset is 0.
    fn with_flat_sigma_keeping_fields(&self, dense_m: f64, sigma_flat_m: f64) -> Self {
        let mut variance_shares = self.variance_shares;
        if sigma_flat_m > 0.0 {
            let kept = dense_m * dense_m / (sigma_flat_m * sigma_flat_m);
            for share in &mut variance_shares[1..] {
                *share = (*share * kept).min(1.0);
            }
            let fields: f64 = variance_shares[1..].iter().sum();
            if fields > 1.0 {
                for share in &mut variance_shares[1..] {
                    *share /= fields;
                }
            }
            variance_shares[0] = (1.0 - variance_shares[1..].iter().sum::<f64>()).max(0.0);
        }
        Self {
            sigma_flat_m,
            variance_shares,
            ..self.clone()
        }
    }

    /// The model without the fine and medium fields (their variance dropped; the offset, the
    /// coarse field, relief and edges kept in metres): what moves or tilts a whole patch.
    /// Robust grasp quality draws from it around a planning depth that already holds one
    /// realisation of the short-range bumps.
    pub fn long_range(&self) -> Self {
        let [offset, _, _, coarse] = self.variance_shares;
        let kept = offset + coarse;
        Self {
            sigma_flat_m: self.sigma_flat_m * kept.max(0.0).sqrt(),
            // the distance part grows every share alike
            sample_distance_gain: self.sample_distance_gain * kept.max(0.0).sqrt(),
            variance_shares: if kept > 0.0 {
                [offset / kept, 0.0, 0.0, coarse / kept]
            } else {
                [0.0, 0.0, 0.0, 1.0]
            },
            ..self.clone()
        }
    }

    /// The expected truth under this model, inside `roi`, of an aligned depth that holds one
    /// realisation of the short-range (fine and medium field) error: `depth_m` averaged over a
    /// window of the largest short-range field's correlation length, separably (along rows, then
    /// columns), each average over the valid pixels within `3 σ_short(z) + 2 mm` of the centre's
    /// depth so that depth edges stay where they are. Outside `roi`, and everywhere without
    /// short-range error, the depth is returned unchanged.
    ///
    /// The truth is smooth where the depth model's output is rough: robust suction quality draws
    /// around this, since its seal test reads the surface at a few pixels' scale.
    pub fn expected_truth(&self, depth_m: ArrayView2<'_, f32>, roi: Roi) -> Array2<f32> {
        let mut out = depth_m.to_owned();
        let [_, fine, medium, _] = self.variance_shares;
        let r = if medium > SHORT_SHARE_MIN {
            self.scales_px[1]
        } else if fine > SHORT_SHARE_MIN {
            self.scales_px[0]
        } else {
            return out;
        }
        .round()
        .max(1.0) as usize;
        let (h, w) = depth_m.dim();
        let (u0, u1) = (roi.u0.min(w), (roi.u0 + roi.width).min(w));
        let (v0, v1) = (roi.v0.min(h), (roi.v0 + roi.height).min(h));
        if u0 >= u1 || v0 >= v1 {
            return out;
        }
        let short_sigma = self.sigma_flat_m * (fine + medium).max(0.0).sqrt();
        let tol = |z: f32| (3.0 * short_sigma * self.depth_scale(z) + 0.002) as f32;
        // plain row-major slices: a view sliced per pixel cost more than the sums themselves
        // (half of a robust suction plan's time in a profile)
        let owned: Vec<f32>;
        let src: &[f32] = match depth_m.as_slice() {
            Some(s) => s,
            None => {
                owned = depth_m.iter().copied().collect();
                &owned
            }
        };
        // Each output is the mean of the valid values within `tol(z0)` of its own `z0` over the
        // window (`z0` itself included), summed in window order. The sums run one window
        // offset at a time over a whole row of pixels (branch-free, so they vectorise across
        // pixels), each pixel's sum still in window order: the same bits as a pixel-by-pixel scan.
        let rw = u1 - u0;
        let (mut sum, mut n, mut centre, mut t) = (
            vec![0.0f32; rw],
            vec![0u32; rw],
            vec![0.0f32; rw],
            vec![0.0f32; rw],
        );
        #[inline(always)]
        fn accumulate(sum: &mut [f32], n: &mut [u32], centre: &[f32], t: &[f32], values: &[f32]) {
            for (((s, k), (&z0, &tz)), &z) in sum
                .iter_mut()
                .zip(n.iter_mut())
                .zip(centre.iter().zip(t))
                .zip(values)
            {
                // `is_valid_depth` is branch-free: the loop still vectorises
                let ok = is_valid_depth(z) & ((z - z0).abs() <= tz);
                *s += if ok { z } else { 0.0 };
                *k += u32::from(ok);
            }
        }
        let finish = |sum: &[f32], n: &[u32], centre: &[f32], dst: &mut [f32]| {
            for (((d, &s), &k), &z0) in dst.iter_mut().zip(sum).zip(n).zip(centre) {
                *d = if is_valid_depth(z0) && k > 0 {
                    s / k as f32
                } else {
                    z0
                };
            }
        };
        // along rows, on the roi's columns and r rows above and below it (what the column pass
        // reads); `rows` is row-major, (rv1 − rv0) × rw
        let (rv0, rv1) = (v0.saturating_sub(r), (v1 + r).min(h));
        let mut rows = vec![0.0f32; (rv1 - rv0) * rw];
        for v in rv0..rv1 {
            let line = &src[v * w..(v + 1) * w];
            centre.copy_from_slice(&line[u0..u1]);
            for (tz, &z0) in t.iter_mut().zip(&centre) {
                *tz = tol(z0);
            }
            sum.fill(0.0);
            n.fill(0);
            // window offset d = k − r for pixel u reads u + d; the pixels whose window holds
            // that column are a contiguous run
            for k in 0..=2 * r {
                let lo = r.saturating_sub(k).max(u0); // first u with u + k − r ≥ 0
                let hi = (w + r).saturating_sub(k).min(u1); // u + k − r < w
                if lo >= hi {
                    continue;
                }
                let (a, b) = (lo - u0, hi - u0);
                let vals = &line[lo + k - r..hi + k - r];
                accumulate(&mut sum[a..b], &mut n[a..b], &centre[a..b], &t[a..b], vals);
            }
            let dst = &mut rows[(v - rv0) * rw..(v - rv0 + 1) * rw];
            finish(&sum, &n, &centre, dst);
        }
        // along columns, inside the roi
        let mut column_out = vec![0.0f32; rw];
        for v in v0..v1 {
            let (a, b) = (v.saturating_sub(r).max(rv0), (v + r + 1).min(rv1));
            centre.copy_from_slice(&rows[(v - rv0) * rw..(v - rv0 + 1) * rw]);
            for (tz, &z0) in t.iter_mut().zip(&centre) {
                *tz = tol(z0);
            }
            sum.fill(0.0);
            n.fill(0);
            for vv in a..b {
                let vals = &rows[(vv - rv0) * rw..(vv - rv0 + 1) * rw];
                accumulate(&mut sum, &mut n, &centre, &t, vals);
            }
            finish(&sum, &n, &centre, &mut column_out);
            for (u, &z) in (u0..u1).zip(&column_out) {
                out[[v, u]] = z;
            }
        }
        out
    }

    /// The expected truth of the whole map `depth_m` under this model, the depth a grasp is
    /// planned on (Dex-Net plans on the mean estimate and draws the deviations around it): the
    /// mean relief correction `relief_bias · hp` with `hp` clamped to ±[`Self::relief_max_m`]
    /// (the range the factor is fitted on: never extrapolated), the mean edge share
    /// `edge_sharpening · step` (silhouettes pulled from ramps towards steps), then, with
    /// `smooth`, the short-range bumps averaged out ([`Self::expected_truth`]). A model without
    /// those parts returns the depth unchanged.
    pub fn expected_truth_map(&self, depth_m: ArrayView2<'_, f32>, smooth: bool) -> Array2<f32> {
        let mut out = depth_m.to_owned();
        if self.relief_bias > 0.0 {
            // a flattening: the fixed point of z = depth + c0 · hp(z), c0 = c / (1 + c) (module
            // documentation, "Expected truth"), the relief clamped at the range on the aligned
            // depth's scale, (1 − c0) · hp(z)
            let c = self.relief_bias as f32;
            let c0 = c / (1.0 + c);
            let rmax = self.relief_max_m as f32;
            let (h, w) = depth_m.dim();
            let d0 = row_major(depth_m);
            // one set of buffers for every iteration
            let mut z = d0.to_vec();
            let mut hp = vec![0.0f32; h * w];
            let mut sums = BoxSums::of_slice(&z, h, w);
            for k in 0..RELIEF_FIXED_POINT_ITERATIONS {
                if k > 0 {
                    sums.refill(&z);
                }
                sums.high_pass_into(&z, self.relief_radius_px as usize, &mut hp);
                for ((v, &d), &hh) in z.iter_mut().zip(d0.iter()).zip(&hp) {
                    *v = add_relief(d, (1.0 - c0) * hh, c, rmax);
                }
            }
            if let Ok(z) = Array2::from_shape_vec((h, w), z) {
                out = z;
            }
        } else if self.relief_bias != 0.0 {
            // an exaggeration: the first-order correction (the fixed point need not converge)
            let hp = high_pass(depth_m, self.relief_radius_px);
            let c = self.relief_bias as f32;
            let rmax = self.relief_max_m as f32;
            ndarray::Zip::from(&mut out)
                .and(&hp)
                .for_each(|z, &h| *z = add_relief(*z, h, c, rmax));
        }
        if self.edge_sharpening > 0.0 {
            let edges = EdgeMaps::of(depth_m, self.edge_radius_px);
            let a = self.edge_sharpening as f32;
            ndarray::Zip::from(&mut out)
                .and(&edges.step)
                .for_each(|z, &st| *z = add_edge_share(*z, st, a));
        }
        if smooth {
            let (h, w) = out.dim();
            out = self.expected_truth(out.view(), Roi::full(w, h));
        }
        out
    }

    /// The model of the deviations of the truth from [`Self::expected_truth_map`]: the relief
    /// factor's mean set to 0 (its σ kept) and the edge share left out (the edge noise
    /// `edge_gain` kept), everything else unchanged.
    pub fn deviations(&self) -> Self {
        Self {
            relief_bias: 0.0,
            edge_sharpening: 0.0,
            ..self.clone()
        }
    }

    /// σ of the flat error at depth `z_m` (metres): `sigma_flat_m · (z / depth_ref_m)^p`, the
    /// offset and the fields together (no relief or edge part).
    pub fn flat_sigma_m(&self, z_m: f32) -> f64 {
        self.sigma_flat_m * self.depth_scale(z_m)
    }

    /// The RMS (metres) of the flat error's variation within a patch of radius `radius_px`
    /// pixels at depth `z_m`: the fields' semivariogram at that lag, `σ_flat(z)·√(Σ_k share_k ·
    /// min(1, radius_px / s_k))`. What is left of the error at larger distances (the offset, and
    /// the fields' parts longer than the patch) moves the patch as a whole and tilts nothing.
    pub fn noise_within_m(&self, z_m: f32, radius_px: f64) -> f64 {
        let shares: f64 = self.variance_shares[1..]
            .iter()
            .zip(&self.scales_px)
            .map(|(&v, &s)| v * (radius_px / s.max(1e-9)).min(1.0))
            .sum();
        self.sigma_flat_m * self.depth_scale(z_m) * shares.max(0.0).sqrt()
    }

    /// The per-pixel σ (metres) of the error of `depth` (NaN where `depth` has no depth).
    pub fn sigma_map(&self, depth: &MetricDepth) -> Array2<f32> {
        let d = depth.depth_m.view();
        let edges = EdgeMaps::of(d, self.edge_radius_px);
        let hp = self.relief_part(d);
        let c2 = (self.relief_bias.powi(2) + self.relief_sigma.powi(2)) as f32;
        let a2 = (self.edge_sharpening.powi(2) + self.edge_sharpening_sigma.powi(2)) as f32;
        let g = self.edge_gain as f32;
        let height = self.height_part(d, Roi::full(d.ncols(), d.nrows()));
        let k = self.height_sigma as f32;
        let distance = self.distance_map(depth.size());
        Array2::from_shape_fn(d.raw_dim(), |(v, u)| {
            let z = d[[v, u]];
            if !is_valid_depth(z) {
                return f32::NAN;
            }
            let level = match distance {
                Some(dist) => self.flat_level(Some(dist[[v, u]])),
                None => self.sigma_flat_m,
            };
            let s = (level * self.depth_scale(z)) as f32;
            let h = hp.as_ref().map_or(0.0, |hp| hp[[v, u]]);
            let st = edges.step[[v, u]];
            let above = height.as_ref().map_or(0.0, |a| a[[v, u]]);
            (s * s
                + c2 * h * h
                + a2 * st * st
                + (g * edges.relief[[v, u]]).powi(2)
                + (k * above).powi(2))
            .sqrt()
        })
    }

    /// The height above the support plane of `d` (the plane of the whole map) in `roi` when
    /// the model has a height part (`None` without one, or without a support plane in `d`).
    fn height_part(&self, d: ArrayView2<'_, f32>, roi: Roi) -> Option<Array2<f32>> {
        (self.height_sigma > 0.0)
            .then(|| crate::height::height_above_plane_in(d, roi.u0, roi.v0, roi.width, roi.height))
            .flatten()
    }

    /// The relief hp of `d` when the model has a relief part (NaN-free: 0 where undefined).
    fn relief_part(&self, d: ArrayView2<'_, f32>) -> Option<Array2<f32>> {
        (self.relief_bias != 0.0 || self.relief_sigma != 0.0).then(|| {
            high_pass(d, self.relief_radius_px).mapv(|h| if h.is_finite() { h } else { 0.0 })
        })
    }

    /// Adds draw number `draw` (seeded by `seed`) of the error to `depth` in place: a plausible
    /// true scene (module documentation). With σ = 0 everywhere the depth is unchanged; a pixel
    /// whose drawn depth is not positive becomes NaN (no depth).
    pub fn draw_into(&self, depth: &mut ArrayViewMut2<'_, f32>, seed: u64, draw: u64) {
        let (h, w) = depth.dim();
        let drawn = Draws::new(self, depth.view(), Roi::full(w, h)).draw(seed, draw);
        depth.assign(&drawn);
    }

    /// A new depth map: `depth` plus draw number `draw` ([`DepthErrorModel::draw_into`]).
    pub fn draw(&self, depth: &MetricDepth, seed: u64, draw: u64) -> MetricDepth {
        let (h, w) = depth.depth_m.dim();
        MetricDepth::new(Draws::new(self, depth.depth_m.view(), Roi::full(w, h)).draw(seed, draw))
    }
}

/// A rectangle of an image, pixels: columns `u0..u0 + width`, rows `v0..v0 + height`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Roi {
    /// First column.
    pub u0: usize,
    /// First row.
    pub v0: usize,
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
}

impl Roi {
    /// The whole `width × height` image.
    pub const fn full(width: usize, height: usize) -> Self {
        Self {
            u0: 0,
            v0: 0,
            width,
            height,
        }
    }
}

/// Depth draws of one region of a depth map: the relief maps the model needs are computed once
/// (on the region grown by their window radii, so that they equal the whole map's there), and
/// each draw fills only the region (the draws of a grasp need only the region around it).
/// Draw `k` of seed `s` over the whole map equals [`DepthErrorModel::draw`].
pub struct Draws<'a> {
    model: DepthErrorModel,
    depth: ArrayView2<'a, f32>,
    roi: Roi,
    /// Where the relief maps start in the map (they cover the grown region).
    pad_u0: usize,
    pad_v0: usize,
    edges: EdgeMaps,
    hp: Option<Array2<f32>>,
    /// The height above the support plane of the region (`roi` sized).
    height: Option<Array2<f32>>,
    /// The distance map of the model's distance part (the whole map's size), when it has one.
    distance: Option<Arc<Array2<f32>>>,
    /// Where the edge field moves a pixel to a side ([`snap_edge`]): `P(N(0, 1) > θ) = 2 g²`.
    edge_theta: f32,
}

impl<'a> Draws<'a> {
    /// Prepares draws of `model` around `depth` (metres) inside `roi` (clipped to the map).
    pub fn new(model: &DepthErrorModel, depth: ArrayView2<'a, f32>, roi: Roi) -> Self {
        let (h_all, w_all) = depth.dim();
        let (u0, v0) = (roi.u0.min(w_all), roi.v0.min(h_all));
        let roi = Roi {
            u0,
            v0,
            width: roi.width.min(w_all - u0),
            height: roi.height.min(h_all - v0),
        };
        let pad =
            model
                .edge_radius_px
                .max(if model.relief_bias != 0.0 || model.relief_sigma != 0.0 {
                    model.relief_radius_px
                } else {
                    0
                }) as usize;
        let (pu0, pv0) = (u0.saturating_sub(pad), v0.saturating_sub(pad));
        let (pu1, pv1) = (
            (u0 + roi.width + pad).min(w_all),
            (v0 + roi.height + pad).min(h_all),
        );
        let grown = depth.slice(ndarray::s![pv0..pv1, pu0..pu1]);
        Self {
            model: model.clone(),
            depth,
            roi,
            pad_u0: pu0,
            pad_v0: pv0,
            edges: EdgeMaps::of(grown, model.edge_radius_px),
            hp: model.relief_part(grown),
            height: model.height_part(depth, roi),
            distance: model.distance_map(ImageSize::of(&depth)).cloned(),
            edge_theta: upper_normal_quantile((2.0 * model.edge_gain * model.edge_gain).min(0.5))
                as f32,
        }
    }

    /// The region the draws cover (clipped to the map).
    pub fn roi(&self) -> Roi {
        self.roi
    }

    /// Draw number `draw` (seeded by `seed`): the drawn depth of the region's pixels,
    /// `roi.height × roi.width`.
    pub fn draw(&self, seed: u64, draw: u64) -> Array2<f32> {
        let m = &self.model;
        let Roi {
            u0,
            v0,
            width: w,
            height: h,
        } = self.roi;
        let mut out = self
            .depth
            .slice(ndarray::s![v0..v0 + h, u0..u0 + w])
            .to_owned();
        if w == 0 || h == 0 {
            return out;
        }
        // offsets of the region inside the relief maps
        let (du, dv) = (u0 - self.pad_u0, v0 - self.pad_v0);
        let mut rng = ChaCha8Rng::seed_from_u64(
            seed ^ draw.wrapping_add(1).wrapping_mul(0x9E37_79B9_7F4A_7C15),
        );
        let c = (m.relief_bias + m.relief_sigma * f64::from(normal(&mut rng))) as f32;
        let sharpen = (m.edge_sharpening + m.edge_sharpening_sigma * f64::from(normal(&mut rng)))
            .clamp(-1.0, 1.0) as f32;
        let shares = m.variance_shares;
        // with a distance part the flat error is drawn at unit level and scaled per pixel by
        // its level there (below), which holds where the level at the samples is 0
        let level = if self.distance.is_some() {
            1.0
        } else {
            m.sigma_flat_m
        };
        let offset = (shares[0].sqrt() * level) as f32 * normal(&mut rng);
        let fields: Vec<(f32, SmoothField)> = m
            .scales_px
            .iter()
            .zip(&shares[1..])
            .filter(|(_, s)| **s > 0.0)
            .map(|(&scale, &s)| {
                (
                    (s.sqrt() * level) as f32,
                    SmoothField::new(w, h, scale, &mut rng),
                )
            })
            .collect();
        let edges = SmoothField::new(w, h, EDGE_SCALE_PX, &mut rng);
        // drawn last, and only with a height part: the other parts' draws stay as they were
        let k_height = if self.height.is_some() {
            (m.height_sigma * f64::from(normal(&mut rng))) as f32
        } else {
            0.0
        };
        let mut edge_row = vec![0.0f32; w];
        let inv_ref2 = (1.0 / (m.depth_ref_m * m.depth_ref_m)) as f32;
        let mut flat = vec![0.0f32; w];
        let mut rest = vec![0.0f32; w];
        for v in 0..h {
            let vf = v + dv;
            flat.fill(offset);
            for (s, f) in &fields {
                f.add_row(v, &mut flat, |_| *s);
            }
            rest.fill(0.0);
            let (relief, step) = (self.edges.relief.row(vf), self.edges.step.row(vf));
            // the edge noise as silhouettes that move
            if m.edge_gain > 0.0 {
                edge_row.fill(0.0);
                edges.add_row(v, &mut edge_row, |_| 1.0);
                let row = out.row(v);
                for (u, r) in rest.iter_mut().enumerate() {
                    let (z, e) = (row[u], edge_row[u]);
                    *r += snap_edge(z, relief[u + du], step[u + du], e, self.edge_theta);
                }
            }
            if sharpen != 0.0 {
                for (u, r) in rest.iter_mut().enumerate() {
                    *r += sharpen * step[u + du];
                }
            }
            if let Some(hp) = &self.hp {
                let hp = hp.row(vf);
                for (u, r) in rest.iter_mut().enumerate() {
                    *r += c * hp[u + du];
                }
            }
            if let Some(height) = &self.height {
                for (r, a) in rest.iter_mut().zip(height.row(v)) {
                    *r -= k_height * a;
                }
            }
            if let Some(dist) = &self.distance {
                // the distance part: the flat error's level grows away from the samples
                for (f, &d) in flat.iter_mut().zip(dist.row(v + v0).iter().skip(u0)) {
                    *f *= m.flat_level(Some(d)) as f32;
                }
            }
            for (u, z) in out.row_mut(v).iter_mut().enumerate() {
                if !is_valid_depth(*z) {
                    continue;
                }
                // (z / z_ref)^p: the exponents fitted are 0 and 2
                let scale = if m.depth_exponent == 0.0 {
                    1.0
                } else if m.depth_exponent == 2.0 {
                    *z * *z * inv_ref2
                } else {
                    m.depth_scale(*z) as f32
                };
                // a draw that puts the surface at or behind the camera (σ of the order of the
                // depth) has no depth there: kept as the exact depth, it made a huge σ look
                // safer than a large one (success probabilities rose again with σ)
                let t = *z + flat[u] * scale + rest[u];
                *z = if is_valid_depth(t) { t } else { f32::NAN };
            }
        }
        out
    }
}

/// Fit step 5: least squares of the normalised rest's square on `σ0² + gain²·d²` over the flat
/// pixels of the grids (`rests`, NaN where there is none; `d` the distance to the nearest
/// sample on the same grid), both terms non-negative (when one is not, the other alone).
/// Returns `(σ0², gain)`, metres² and metres per pixel at the reference depth; `None` without a
/// flat pixel at a finite distance (the caller keeps the flat mean square, no part).
fn distance_part(
    rests: &[Array2<f32>],
    prepared: &[FitGrid],
    d: &Array2<f32>,
    flat_relief: f32,
) -> Option<(f64, f64)> {
    // Σ1, Σd², Σd⁴, Σy, Σy·d² over y = rest²
    let (mut n, mut s2, mut s4, mut sy, mut syd) = (0.0f64, 0.0, 0.0, 0.0, 0.0);
    for (rest, g) in rests.iter().zip(prepared) {
        if rest.dim() != d.dim() {
            continue;
        }
        for ((&x, &r), &dist) in grid_slice(rest)
            .iter()
            .zip(grid_slice(&g.relief))
            .zip(grid_slice(d))
        {
            if !(x.is_finite() && r < flat_relief && dist.is_finite()) {
                continue;
            }
            let (y, d2) = (f64::from(x).powi(2), f64::from(dist).powi(2));
            n += 1.0;
            s2 += d2;
            s4 += d2 * d2;
            sy += y;
            syd += y * d2;
        }
    }
    if n == 0.0 {
        return None;
    }
    let det = n * s4 - s2 * s2;
    let (a, b) = if det > 1e-12 * (n * s4).max(f64::MIN_POSITIVE) {
        ((sy * s4 - s2 * syd) / det, (n * syd - s2 * sy) / det)
    } else {
        (sy / n, 0.0)
    };
    Some(if b <= 0.0 {
        (sy / n, 0.0)
    } else if a < 0.0 {
        (0.0, if s4 > 0.0 { (syd / s4).sqrt() } else { 0.0 })
    } else {
        (a, b.sqrt())
    })
}

fn no_pixels() -> CoreError {
    CoreError::NoValidPixels(
        "depth error model: no flat pixel with both an aligned and a ground-truth depth".into(),
    )
}

/// `z + c · clamp(h, ±rmax)`, the relief correction of one pixel (`h` its relief hp, metres),
/// where `z` is a valid depth, `h` finite and the result a valid depth; `z` otherwise. The one
/// rule of [`DepthErrorModel::expected_truth_map`] and of fit step 1c's criterion.
#[inline]
fn add_relief(z: f32, h: f32, c: f32, rmax: f32) -> f32 {
    if !(is_valid_depth(z) && h.is_finite()) {
        return z;
    }
    let t = z + c * h.clamp(-rmax, rmax);
    if is_valid_depth(t) { t } else { z }
}

/// `z + a · step`, the edge share of one pixel, where `z` and the result are valid depths; `z`
/// otherwise (as [`add_relief`]).
#[inline]
fn add_edge_share(z: f32, step: f32, a: f32) -> f32 {
    let t = z + a * step;
    if is_valid_depth(z) && is_valid_depth(t) {
        t
    } else {
        z
    }
}

/// The relief blur radius for an image: `share` of its width, at least 4 px.
fn relief_radius_for(size: ImageSize, share: f64) -> u32 {
    ((size.width as f64 * share).round() as u32).max(4)
}

/// Non-negative least squares of `γ(L) = Σ_k v_k · min(1, L / s_k)` over the semivariogram
/// points `(L, γ)`: every subset of the three fields solved unconstrained, the best feasible
/// kept (3 unknowns: 7 subsets).
fn field_variances(semi: &[(f64, f64)], scales: &[f64; 3]) -> [f64; 3] {
    let basis = |l: f64, k: usize| (l / scales[k]).min(1.0);
    let mut best = ([0.0; 3], f64::INFINITY);
    for subset in 1u32..8 {
        let idx: Vec<usize> = (0..3).filter(|k| subset & (1 << k) != 0).collect();
        let n = idx.len();
        // normal equations
        let mut a = [[0.0f64; 3]; 3];
        let mut b = [0.0f64; 3];
        for &(l, g) in semi {
            for (i, &ki) in idx.iter().enumerate() {
                b[i] += basis(l, ki) * g;
                for (j, &kj) in idx.iter().enumerate() {
                    a[i][j] += basis(l, ki) * basis(l, kj);
                }
            }
        }
        let Some(x) = solve(&a, &b, n) else { continue };
        if x[..n].iter().any(|&v| v < 0.0) {
            continue;
        }
        let mut v = [0.0; 3];
        for (i, &k) in idx.iter().enumerate() {
            v[k] = x[i];
        }
        let sse: f64 = semi
            .iter()
            .map(|&(l, g)| (g - (0..3).map(|k| v[k] * basis(l, k)).sum::<f64>()).powi(2))
            .sum();
        if sse < best.1 {
            best = (v, sse);
        }
    }
    best.0
}

/// The leading `n × n` system solved by LU (nalgebra); `None` when singular.
fn solve(a: &[[f64; 3]; 3], b: &[f64; 3], n: usize) -> Option<[f64; 3]> {
    let m = nalgebra::DMatrix::from_fn(n, n, |i, j| a[i][j]);
    let y = nalgebra::DVector::from_fn(n, |i, _| b[i]);
    let x = m.lu().solve(&y)?;
    let mut out = [0.0; 3];
    out[..n].copy_from_slice(x.as_slice());
    Some(out)
}

fn normal(rng: &mut ChaCha8Rng) -> f32 {
    let x: f64 = StandardNormal.sample(rng);
    x as f32
}

/// A unit-variance Gaussian field over a `w × h` region: N(0, 1) on a grid every `scale`
/// pixels, bilinear between, each pixel divided by the norm of its interpolation weights. That
/// norm factorises, `√((1−fx)² + fx²) · √((1−fy)² + fy²)`, so the weights are tabled once per
/// column and per row.
struct SmoothField {
    nodes: Array2<f32>,
    /// Per column: grid column `i` and the normalised weights of columns `i`, `i + 1`.
    cols: Vec<(usize, f32, f32)>,
    /// Per row: grid row `j` and the normalised weights of rows `j`, `j + 1`.
    rows: Vec<(usize, f32, f32)>,
}

impl SmoothField {
    fn new(w: usize, h: usize, scale: f64, rng: &mut ChaCha8Rng) -> Self {
        let scale = scale.max(1.0) as f32;
        let gw = (w as f32 / scale).ceil() as usize + 2;
        let gh = (h as f32 / scale).ceil() as usize + 2;
        let nodes = Array2::from_shape_fn((gh, gw), |_| normal(rng));
        let table = |n: usize| -> Vec<(usize, f32, f32)> {
            (0..n)
                .map(|x| {
                    let t = x as f32 / scale;
                    let i = t.floor() as usize;
                    let f = t - i as f32;
                    let norm = ((1.0 - f) * (1.0 - f) + f * f).sqrt();
                    (i, (1.0 - f) / norm, f / norm)
                })
                .collect()
        };
        Self {
            nodes,
            cols: table(w),
            rows: table(h),
        }
    }

    /// Adds `gain(u) · field(u, v)` to `row[u]` for every column `u` of row `v`.
    #[inline]
    fn add_row(&self, v: usize, row: &mut [f32], gain: impl Fn(usize) -> f32) {
        let (j, wy0, wy1) = self.rows[v];
        let (r0, r1) = (self.nodes.row(j), self.nodes.row(j + 1));
        for (u, (x, &(i, wx0, wx1))) in row.iter_mut().zip(&self.cols).enumerate() {
            let f = wy0 * (wx0 * r0[i] + wx1 * r0[i + 1]) + wy1 * (wx0 * r1[i] + wx1 * r1[i + 1]);
            *x += gain(u) * f;
        }
    }
}

/// `depth − box(depth)`: the depth's relief against the mean of the valid pixels in a
/// `(2r+1)²` box (integral images, so any radius costs the same); NaN where `depth` has no
/// depth.
pub fn high_pass(depth: ArrayView2<'_, f32>, r: u32) -> Array2<f32> {
    let (h, w) = depth.dim();
    let data = row_major(depth);
    let mut out = vec![0.0f32; h * w];
    BoxSums::of_slice(&data, h, w).high_pass_into(&data, r as usize, &mut out);
    Array2::from_shape_vec((h, w), out).unwrap_or_else(|_| high_pass_strided(depth, r, 1))
}

/// [`high_pass`] at every `stride`-th pixel of every `stride`-th row only (the full map sliced
/// `[..;stride, ..;stride]`, computed without the other pixels' outputs; the same values).
fn high_pass_strided(depth: ArrayView2<'_, f32>, r: u32, stride: usize) -> Array2<f32> {
    BoxSums::of(depth).high_pass_strided(depth, r, stride)
}

/// Integral images of a depth map's sum and count of valid pixels, `(h+1) × (w+1)`: the box
/// means of every radius from one pass ([`DepthErrorModel::fit`] tries several).
struct BoxSums {
    sum: Vec<f64>,
    cnt: Vec<u32>,
    h: usize,
    w: usize,
}

impl BoxSums {
    fn of(depth: ArrayView2<'_, f32>) -> Self {
        let (h, w) = depth.dim();
        Self::of_slice(&row_major(depth), h, w)
    }

    /// [`Self::of`] for the `h × w` map `data`, row-major.
    fn of_slice(data: &[f32], h: usize, w: usize) -> Self {
        let w1 = w + 1;
        let mut sums = Self {
            sum: vec![0.0f64; (h + 1) * w1],
            cnt: vec![0u32; (h + 1) * w1],
            h,
            w,
        };
        sums.refill(data);
        sums
    }

    /// The sums of another map of the same size, `data` (row-major), in place: no new
    /// allocation (the relief's fixed point takes them three times per frame).
    fn refill(&mut self, data: &[f32]) {
        let (h, w, w1) = (self.h, self.w, self.w + 1);
        for (v, row) in data.chunks_exact(w.max(1)).take(h).enumerate() {
            let (above, here) = self.sum.split_at_mut((v + 1) * w1);
            let (above_c, here_c) = self.cnt.split_at_mut((v + 1) * w1);
            let (above, above_c) = (&above[v * w1..], &above_c[v * w1..]);
            let (mut rs, mut rc) = (0.0f64, 0u32);
            for (u, &z) in row.iter().enumerate() {
                if is_valid_depth(z) {
                    rs += f64::from(z);
                    rc += 1;
                }
                here[u + 1] = above[u + 1] + rs;
                here_c[u + 1] = above_c[u + 1] + rc;
            }
        }
    }

    /// [`high_pass`] of `data` (row-major, the map these sums are of) into `out`: the
    /// arithmetic of [`Self::high_pass_strided`] at stride 1, bit for bit, row by row. Away
    /// from the left and right borders a window's columns are `u − r` and `u + r + 1` for
    /// every pixel, so that run is plain slices offset from each other and vectorises (the
    /// per-pixel closure with its clamped bounds did not; with the fixed point's three high
    /// passes it was the largest part of a robust suction plan's time).
    fn high_pass_into(&self, data: &[f32], r: usize, out: &mut [f32]) {
        let (h, w) = (self.h, self.w);
        // the interior: u − r ≥ 0 and u + r + 1 ≤ w
        let (lo, hi) = (r.min(w), w.saturating_sub(r).max(r.min(w)));
        for (v, (row, dst)) in data
            .chunks_exact(w.max(1))
            .zip(out.chunks_exact_mut(w.max(1)))
            .take(h)
            .enumerate()
        {
            let win = self.window_rows(v, r);
            for u in (0..lo).chain(hi..w) {
                dst[u] = win.high_pass_at(row[u], u);
            }
            let WindowRows { ts, bs, tc, bc, .. } = win;
            if hi > lo {
                let n = hi - lo;
                let (b1, t1, b0, t0) = (
                    &bs[lo + r + 1..][..n],
                    &ts[lo + r + 1..][..n],
                    &bs[lo - r..][..n],
                    &ts[lo - r..][..n],
                );
                let (cb1, ct1, cb0, ct0) = (
                    &bc[lo + r + 1..][..n],
                    &tc[lo + r + 1..][..n],
                    &bc[lo - r..][..n],
                    &tc[lo - r..][..n],
                );
                for i in 0..n {
                    let s = b1[i] - t1[i] - b0[i] + t0[i];
                    let c = cb1[i] + ct0[i] - ct1[i] - cb0[i];
                    dst[lo + i] = box_high_pass(row[lo + i], s, c);
                }
            }
        }
    }

    /// [`high_pass`] of `depth` (the map these sums are of) at every `stride`-th pixel of every
    /// `stride`-th row.
    fn high_pass_strided(&self, depth: ArrayView2<'_, f32>, r: u32, stride: usize) -> Array2<f32> {
        let (h, w) = (self.h, self.w);
        let r = r as usize;
        let stride = stride.max(1);
        let data = row_major(depth);
        let mut out = Array2::<f32>::zeros((h.div_ceil(stride), w.div_ceil(stride)));
        // row by row on slices (an indexed closure per pixel was a seventh of the error
        // model's fit)
        for (vs, dst) in out.rows_mut().into_iter().enumerate() {
            let v = vs * stride;
            let (win, row) = (self.window_rows(v, r), &data[v * w..][..w]);
            for (us, o) in dst.into_iter().enumerate() {
                *o = win.high_pass_at(row[us * stride], us * stride);
            }
        }
        out
    }

    /// The rows of the sums that bound the `(2r+1)`-row windows of row `v` (clipped to the map).
    fn window_rows(&self, v: usize, r: usize) -> WindowRows<'_> {
        let (h, w1) = (self.h, self.w + 1);
        let (v0, v1) = (v.saturating_sub(r), (v + r + 1).min(h));
        WindowRows {
            ts: &self.sum[v0 * w1..][..w1],
            bs: &self.sum[v1 * w1..][..w1],
            tc: &self.cnt[v0 * w1..][..w1],
            bc: &self.cnt[v1 * w1..][..w1],
            r,
            w: self.w,
        }
    }
}

/// The top and bottom rows of a [`BoxSums`] around one image row (sums `ts`, `bs`, counts `tc`,
/// `bc`), for windows of radius `r` on a map `w` pixels wide.
struct WindowRows<'a> {
    ts: &'a [f64],
    bs: &'a [f64],
    tc: &'a [u32],
    bc: &'a [u32],
    r: usize,
    w: usize,
}

impl WindowRows<'_> {
    /// [`box_high_pass`] of the depth `z` at column `u`, its window's columns clipped to the map.
    #[inline(always)]
    fn high_pass_at(&self, z: f32, u: usize) -> f32 {
        let (u0, u1) = (u.saturating_sub(self.r), (u + self.r + 1).min(self.w));
        let s = self.bs[u1] - self.ts[u1] - self.bs[u0] + self.ts[u0];
        let c = self.bc[u1] + self.tc[u0] - self.tc[u1] - self.bc[u0];
        box_high_pass(z, s, c)
    }
}

/// One pixel of the box high pass: `z` less the mean `s / c` of the valid depths of its window
/// (sum `s`, count `c`), NaN where `z` is not a depth. The one formula of every high pass.
#[inline(always)]
fn box_high_pass(z: f32, s: f64, c: u32) -> f32 {
    let hp = (f64::from(z) - s / f64::from(c.max(1))) as f32;
    if is_valid_depth(z) { hp } else { f32::NAN }
}

/// The values of `depth` row by row in one slice: borrowed when the view is already contiguous
/// and row-major, else copied once.
fn row_major(depth: ArrayView2<'_, f32>) -> std::borrow::Cow<'_, [f32]> {
    match depth.to_slice() {
        Some(d) => std::borrow::Cow::Borrowed(d),
        None => std::borrow::Cow::Owned(depth.iter().copied().collect()),
    }
}

/// `out` = `fill` × r, then `row` (invalid depth as `fill`), then `fill` × r.
fn pad(out: &mut Vec<f32>, row: &[f32], r: usize, fill: f32) {
    out.clear();
    out.resize(r, fill);
    out.extend(
        row.iter()
            .map(|&z| if is_valid_depth(z) { z } else { fill }),
    );
    out.resize(out.len() + r, fill);
}

/// The minimum (`MAX = false`) or maximum of every window of `2r + 1` values of `padded`:
/// `out[u]` over `padded[u..=u + 2r]`, for the `padded.len() − 2r` windows. By doubling: the
/// extremes of runs of 1, 2, 4, … values (one vectorised pass each), then two overlapping runs
/// per window; log₂(2r + 1) + 1 passes instead of 2r. No NaN may be in `padded` (a plain `<` is
/// `f32::min` then, and min and max are exact, so the result equals the direct one).
fn window_extreme<const MAX: bool>(
    padded: &[f32],
    r: usize,
    tmp: &mut Vec<f32>,
    out: &mut Vec<f32>,
) {
    let ext = |a: f32, b: f32| {
        if MAX {
            if b > a { b } else { a }
        } else if b < a {
            b
        } else {
            a
        }
    };
    let (n, l) = (padded.len(), 2 * r + 1);
    out.clear();
    if n < l {
        return;
    }
    // out holds the extremes of runs of p values: out[i] over padded[i..i + p]
    out.extend_from_slice(padded);
    let mut p = 1;
    while 2 * p <= l {
        tmp.clear();
        tmp.extend(out[..n - p].iter().zip(&out[p..]).map(|(&a, &b)| ext(a, b)));
        std::mem::swap(out, tmp);
        p *= 2;
    }
    // runs of p ≤ l < 2p: the window [u, u + l) is the union of [u, u + p) and [u + l − p, u + l)
    tmp.clear();
    tmp.extend(
        out[..n - l + 1]
            .iter()
            .zip(&out[l - p..])
            .map(|(&a, &b)| ext(a, b)),
    );
    std::mem::swap(out, tmp);
}

/// The smallest and largest valid depth in a `(2r+1)²` window around each pixel (+∞ / −∞
/// where the window holds none). Separable sliding min/max: rows, then columns, on contiguous
/// rows (the vertical pass combines whole rows, which the compiler vectorises).
fn window_min_max(depth: ArrayView2<'_, f32>, r: u32, stride: usize) -> (Array2<f32>, Array2<f32>) {
    let (h, w) = depth.dim();
    let r = r as usize;
    let stride = stride.max(1);
    // output columns u = 0, stride, …; output rows v = 0, stride, …
    let (hs, ws) = (h.div_ceil(stride), w.div_ceil(stride));
    let mut hmin = Array2::<f32>::from_elem((h, ws), f32::INFINITY);
    let mut hmax = Array2::<f32>::from_elem((h, ws), f32::NEG_INFINITY);
    let (mut mn, mut mx, mut wmn, mut wmx, mut tmp) = (
        Vec::with_capacity(w + 2 * r),
        Vec::with_capacity(w + 2 * r),
        Vec::with_capacity(w + 2 * r),
        Vec::with_capacity(w + 2 * r),
        Vec::with_capacity(w + 2 * r),
    );
    // contiguous rows, read as slices so that the passes vectorise
    let data = row_major(depth);
    for ((row, mut lo), mut hi) in data
        .chunks_exact(w.max(1))
        .zip(hmin.rows_mut())
        .zip(hmax.rows_mut())
    {
        // invalid depth becomes +∞ (min) / −∞ (max): it never wins; the row is padded with the
        // same on both sides, so that every window is whole ([`window_extreme`])
        pad(&mut mn, row, r, f32::INFINITY);
        pad(&mut mx, row, r, f32::NEG_INFINITY);
        window_extreme::<false>(&mn, r, &mut tmp, &mut wmn);
        window_extreme::<true>(&mx, r, &mut tmp, &mut wmx);
        for us in 0..ws {
            lo[us] = wmn[us * stride];
            hi[us] = wmx[us * stride];
        }
    }
    let mut lo = Array2::<f32>::from_elem((hs, ws), f32::INFINITY);
    let mut hi = Array2::<f32>::from_elem((hs, ws), f32::NEG_INFINITY);
    for vs in 0..hs {
        let v = vs * stride;
        let (mut out_lo, mut out_hi) = (lo.row_mut(vs), hi.row_mut(vs));
        let (out_lo, out_hi) = (
            out_lo.as_slice_mut().expect("a new array is contiguous"),
            out_hi.as_slice_mut().expect("a new array is contiguous"),
        );
        for y in v.saturating_sub(r)..(v + r + 1).min(h) {
            let (a, b) = (hmin.row(y), hmax.row(y));
            let (a, b) = (
                a.to_slice().expect("a new array is contiguous"),
                b.to_slice().expect("a new array is contiguous"),
            );
            for (o, &x) in out_lo.iter_mut().zip(a) {
                *o = if x < *o { x } else { *o };
            }
            for (o, &x) in out_hi.iter_mut().zip(b) {
                *o = if x > *o { x } else { *o };
            }
        }
    }
    (lo, hi)
}

/// The edge noise of a draw at a pixel of depth `z` whose window has depth range `range` and
/// step `step` ([`EdgeMaps`]): where the edge field `e` passes `θ` the pixel moves to the
/// window's far side, where it passes `−θ` to its near side, elsewhere it stays (metres). With
/// `P(e > θ) = 2 g²` its variance at mid-ramp is `g² · range²`, the σ map's edge part. A true
/// silhouette is a step a pixel or two off the aligned one, never a surface in mid-air: drawn
/// as a Gaussian value of σ `g · range`, the edge noise put points beside the objects that no
/// scene has, the fingers of a parallel jaw met them, and its success probabilities ran
/// against the truth (section "Edge noise as silhouettes that move" of docs/grasping.md).
/// A pixel exactly at its window's min or max (`step` 0) is not moved.
fn snap_edge(z: f32, range: f32, step: f32, e: f32, theta: f32) -> f32 {
    if range <= 0.0 || step == 0.0 || !is_valid_depth(z) {
        return 0.0;
    }
    let (near, far) = if step < 0.0 {
        (z + step, z + step + range)
    } else {
        (z + step - range, z + step)
    };
    if e > theta {
        far - z
    } else if e < -theta {
        near - z
    } else {
        0.0
    }
}

/// θ with P(N(0, 1) > θ) = `p` (0 < p ≤ 0.5), by bisection on erfc.
fn upper_normal_quantile(p: f64) -> f64 {
    if p <= 0.0 {
        return f64::INFINITY;
    }
    let (mut lo, mut hi) = (0.0f64, 40.0f64);
    for _ in 0..80 {
        let mid = 0.5 * (lo + hi);
        if 0.5 * libm::erfc(mid / std::f64::consts::SQRT_2) > p {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Near a depth edge, the relief and the step: `relief` = max − min of the valid depth in the
/// `(2r+1)²` window (0 with fewer than two distinct values), `step` = the move that snaps a
/// pixel to the near side (the window's min) when it lies nearer than the window's midpoint,
/// to the far side (its max) otherwise (0 where the pixel has no depth). Aligned silhouettes
/// are ramps spread over a few pixels; the truth there is a step.
pub(crate) struct EdgeMaps {
    pub(crate) relief: Array2<f32>,
    pub(crate) step: Array2<f32>,
}

impl EdgeMaps {
    pub(crate) fn of(depth: ArrayView2<'_, f32>, r: u32) -> Self {
        Self::of_strided(depth, r, 1)
    }

    /// [`EdgeMaps::of`] at every `stride`-th pixel of every `stride`-th row only (the full maps
    /// sliced `[..;stride, ..;stride]`, with the same values; the fit's grid).
    pub(crate) fn of_strided(depth: ArrayView2<'_, f32>, r: u32, stride: usize) -> Self {
        let (lo, hi) = window_min_max(depth, r, stride);
        let stride = stride.max(1);
        let depth = depth.slice(ndarray::s![..;stride, ..;stride]);
        let relief = ndarray::Zip::from(&lo)
            .and(&hi)
            .map_collect(|&a, &b| if b > a { b - a } else { 0.0 });
        let step = ndarray::Zip::from(&depth)
            .and(&lo)
            .and(&hi)
            .map_collect(|&z, &a, &b| {
                if !(is_valid_depth(z) && b > a) {
                    0.0
                } else if z < 0.5 * (a + b) {
                    a - z
                } else {
                    b - z
                }
            });
        Self { relief, step }
    }
}

#[cfg(test)]
mod uniform_width_tests {
    use super::*;

    /// Correlation of a uniform model's draws between pixels `lag` apart along rows, over
    /// `draws` draws on a flat `w × h` map at 1 m.
    fn row_correlation(m: &DepthErrorModel, w: usize, h: usize, lag: usize, draws: u64) -> f64 {
        let (mut sxy, mut sxx) = (0.0, 0.0);
        for d in 0..draws {
            let drawn = m.draw(&MetricDepth::new(Array2::from_elem((h, w), 1.0)), 7, d);
            let e = drawn.depth_m.mapv(|z| f64::from(z) - 1.0);
            for v in (0..h).step_by(4) {
                for u in (0..w - lag).step_by(3) {
                    sxy += e[[v, u]] * e[[v, u + lag]];
                    sxx += e[[v, u]] * e[[v, u]];
                }
            }
        }
        sxy / sxx
    }

    /// `moma grasp --sigma-m` at 1280 px draws the field that 640 px draws, twice as wide in
    /// pixels: the same correlation at twice the lag (the same share of the view), and the
    /// same σ; 640 px is `uniform` exactly.
    #[test]
    fn a_uniform_model_spans_the_same_share_of_the_view_at_any_width() {
        let sd = DepthErrorModel::uniform_for_width(0.005, 640).unwrap();
        assert_eq!(sd, DepthErrorModel::uniform(0.005).unwrap());
        let hd = DepthErrorModel::uniform_for_width(0.005, 1280).unwrap();
        assert_eq!(hd.scales_px, [4.0, 16.0, 64.0]);
        let (c_sd, c_hd) = (
            row_correlation(&sd, 320, 120, 24, 24),
            row_correlation(&hd, 640, 240, 48, 24),
        );
        // at the 640 px model's own lag the 1280 px draws correlate more: the field is wider
        let c_hd_short = row_correlation(&hd, 640, 240, 24, 24);
        assert!((c_sd - c_hd).abs() < 0.1, "{c_sd} vs {c_hd}");
        assert!(c_hd_short > c_sd + 0.1, "{c_hd_short} vs {c_sd}");
        assert_eq!(
            hd.sigma_map(&MetricDepth::new(Array2::from_elem((4, 4), 1.0)))[[0, 0]],
            0.005
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn step_scene(w: usize, h: usize) -> Array2<f32> {
        // a table at 1 m with a 50 mm box in the middle
        Array2::from_shape_fn((h, w), |(v, u)| {
            if (w / 3..2 * w / 3).contains(&u) && (h / 3..2 * h / 3).contains(&v) {
                0.95
            } else {
                1.0
            }
        })
    }

    /// The expected truth of a depth holding one realisation of the model's short-range field:
    /// closer to the truth than the rough depth (RMS), with the 50 mm box edge kept where it is,
    /// nothing changed outside the region asked for, and nothing without short-range error.
    #[test]
    fn expected_truth_smooths_the_short_range_field_and_keeps_edges() {
        let (w, h) = (120, 90);
        let truth = MetricDepth::new(step_scene(w, h));
        let m = DepthErrorModel {
            sigma_flat_m: 0.003,
            depth_ref_m: 1.0,
            variance_shares: [0.0, 0.0, 1.0, 0.0],
            ..DepthErrorModel::default()
        };
        let rms = |a: &Array2<f32>| {
            let n = a.len() as f64;
            (a.iter()
                .zip(truth.depth_m.iter())
                .map(|(x, t)| f64::from(x - t).powi(2))
                .sum::<f64>()
                / n)
                .sqrt()
        };
        for seed in 0..3 {
            let rough = m.draw(&truth, seed, 0).depth_m;
            let smooth = m.expected_truth(rough.view(), Roi::full(w, h));
            let (before, after) = (rms(&rough), rms(&smooth));
            assert!(
                before > 0.002,
                "seed {seed}: the premise, {before} m of noise"
            );
            assert!(
                after < 0.7 * before,
                "seed {seed}: RMS {before} → {after} m"
            );
            // the box's border pixels stay on the box (0.95 m), the table's next to them on it
            for u in w / 3 + 2..2 * w / 3 - 2 {
                let (top_in, top_out) = (smooth[[h / 3, u]], smooth[[h / 3 - 1, u]]);
                assert!(
                    (top_in - 0.95).abs() < 0.008,
                    "seed {seed}, u {u}: {top_in}"
                );
                assert!(
                    (top_out - 1.0).abs() < 0.008,
                    "seed {seed}, u {u}: {top_out}"
                );
            }
            // outside the region: unchanged
            let roi = Roi {
                u0: 10,
                v0: 20,
                width: 30,
                height: 40,
            };
            let part = m.expected_truth(rough.view(), roi);
            for ((v, u), z) in part.indexed_iter() {
                let inside = (20..60).contains(&v) && (10..40).contains(&u);
                if inside {
                    assert_eq!(*z, smooth[[v, u]], "({v}, {u}) inside the roi");
                } else {
                    assert_eq!(*z, rough[[v, u]], "({v}, {u}) outside the roi");
                }
            }
        }
        // no short-range field: the depth as it is
        let coarse = DepthErrorModel {
            variance_shares: [0.5, 0.0, 0.0, 0.5],
            ..m.clone()
        };
        let rough = m.draw(&truth, 0, 0).depth_m;
        assert_eq!(coarse.expected_truth(rough.view(), Roi::full(w, h)), rough);
    }

    /// The variation within a patch is the fields' semivariogram at the patch radius:
    /// `σ²·Σ share_k·min(1, r / s_k)` (closed form), scaled with depth as `σ_flat` is.
    #[test]
    fn noise_within_a_patch_is_the_semivariogram_at_its_radius() {
        let m = DepthErrorModel {
            sigma_flat_m: 0.004,
            depth_ref_m: 0.5,
            depth_exponent: 2.0,
            variance_shares: [0.1, 0.2, 0.3, 0.4],
            ..DepthErrorModel::default()
        };
        let expect = |r: f64| {
            0.004
                * (0.2 * (r / 2.0).min(1.0) + 0.3 * (r / 8.0).min(1.0) + 0.4 * (r / 32.0).min(1.0))
                    .sqrt()
        };
        for r in [1.0, 4.0, 16.0, 64.0] {
            assert!(
                (m.noise_within_m(0.5, r) - expect(r)).abs() < 1e-12,
                "r = {r}"
            );
            // twice as deep: σ_flat × 4 in inverse space
            assert!(
                (m.noise_within_m(1.0, r) - 4.0 * expect(r)).abs() < 1e-9,
                "r = {r}"
            );
        }
        // without the short-range fields: the offset's and coarse field's variance in metres
        let long = m.long_range();
        assert!((long.sigma_flat_m - 0.004 * 0.5f64.sqrt()).abs() < 1e-12);
        assert!((long.variance_shares[0] - 0.2).abs() < 1e-12);
        assert!((long.variance_shares[3] - 0.8).abs() < 1e-12);
        assert_eq!(
            (long.variance_shares[1], long.variance_shares[2]),
            (0.0, 0.0)
        );
        // the offset alone tilts nothing
        let offset_only = DepthErrorModel {
            variance_shares: [1.0, 0.0, 0.0, 0.0],
            ..m
        };
        assert_eq!(offset_only.noise_within_m(0.5, 50.0), 0.0);
    }

    #[test]
    fn relief_is_the_step_height_near_the_edge_and_zero_away() {
        let d = step_scene(60, 45);
        let r = EdgeMaps::of(d.view(), 3).relief;
        assert!((r[[22, 20]] - 0.05).abs() < 1e-6); // at the box's left edge (u = 20)
        assert_eq!(r[[22, 30]], 0.0); // inside
        assert_eq!(r[[2, 2]], 0.0); // table
    }

    /// The doubling window extremes equal the direct ones, for every radius and length (shorter
    /// than one window included).
    #[test]
    fn window_extremes_by_doubling_equal_the_direct_ones() {
        let xs: Vec<f32> = (0..41)
            .map(|i| ((i * 37 % 17) as f32 - 8.0) * 0.1)
            .collect();
        let (mut tmp, mut out) = (Vec::new(), Vec::new());
        for r in 0..9 {
            for n in [0, 1, 2 * r, 2 * r + 1, 2 * r + 2, 41] {
                let x = &xs[..n];
                window_extreme::<false>(x, r, &mut tmp, &mut out);
                let want: Vec<f32> = x
                    .windows(2 * r + 1)
                    .map(|w| w.iter().copied().fold(f32::INFINITY, f32::min))
                    .collect();
                assert_eq!(out, want, "min r {r} n {n}");
                window_extreme::<true>(x, r, &mut tmp, &mut out);
                let want: Vec<f32> = x
                    .windows(2 * r + 1)
                    .map(|w| w.iter().copied().fold(f32::NEG_INFINITY, f32::max))
                    .collect();
                assert_eq!(out, want, "max r {r} n {n}");
            }
        }
    }

    /// The row-wise high pass (interior run as offset slices) gives the per-pixel closure's
    /// bits: every radius from 0 to wider than the map, holes of every kind, thin maps.
    #[test]
    fn the_row_wise_high_pass_is_the_per_pixel_one_bit_for_bit() {
        for (h, w) in [(1usize, 1usize), (3, 100), (100, 3), (37, 51), (48, 64)] {
            let d = Array2::from_shape_fn((h, w), |(v, u)| match (u * 7 + v * 3) % 29 {
                0 => f32::NAN,
                1 => 0.0,
                2 => f32::INFINITY,
                3 => -0.5,
                _ => 0.6 + 0.3 * ((u as f32 / 4.0).sin() * (v as f32 / 6.0).cos()).abs(),
            });
            for r in [0u32, 1, 2, 5, 25, 60, 200] {
                let (fast, slow) = (high_pass(d.view(), r), high_pass_strided(d.view(), r, 1));
                assert_eq!(fast.dim(), slow.dim());
                for ((i, a), b) in fast.indexed_iter().zip(slow.iter()) {
                    assert_eq!(
                        a.to_bits(),
                        b.to_bits(),
                        "{h}x{w} r {r} at {i:?}: {a} vs {b}"
                    );
                }
            }
        }
    }

    /// The relief's fixed point with its buffers reused equals the iteration written out with
    /// a new high pass (per-pixel closure) and a new map each time, bit for bit.
    #[test]
    fn the_relief_fixed_point_reuses_buffers_without_changing_a_bit() {
        let d = Array2::from_shape_fn((61, 83), |(v, u)| {
            let bump = if (30..40).contains(&u) && (22..32).contains(&v) {
                -0.08
            } else {
                0.0
            };
            if (u * 5 + v * 11) % 41 == 0 {
                0.0
            } else {
                0.9 + 0.02 * (u as f32 / 7.0).sin() + bump
            }
        });
        let m = DepthErrorModel {
            relief_bias: 0.25,
            relief_radius_px: 9,
            relief_max_m: 0.05,
            edge_sharpening: 0.0,
            ..DepthErrorModel::uniform(0.004).expect("a valid σ")
        };
        let (c, rmax) = (0.25f32, 0.05f32);
        let c0 = c / (1.0 + c);
        let mut z = d.clone();
        for _ in 0..RELIEF_FIXED_POINT_ITERATIONS {
            let hp = high_pass_strided(z.view(), 9, 1);
            let mut next = d.clone();
            ndarray::Zip::from(&mut next)
                .and(&hp)
                .for_each(|v, &h| *v = add_relief(*v, (1.0 - c0) * h, c, rmax));
            z = next;
        }
        let got = m.expected_truth_map(d.view(), false);
        assert!(
            got.iter()
                .zip(z.iter())
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
        // and the correction is there: the box is pulled towards the camera
        assert!(got[[27, 35]] < d[[27, 35]] - 0.01, "{}", got[[27, 35]]);
    }

    /// The fit computes the filters on its grid only: the same values as the full maps there,
    /// for odd sizes, holes and strides 2 and 3.
    #[test]
    fn strided_filters_equal_the_full_maps_sliced() {
        let d = Array2::from_shape_fn((37, 51), |(v, u)| {
            if (u * 7 + v * 3) % 23 == 0 {
                f32::NAN
            } else {
                0.8 + 0.05 * ((u as f32 / 5.0).sin() + (v as f32 / 3.0).cos())
                    + if (10..30).contains(&u) && (8..20).contains(&v) {
                        -0.04
                    } else {
                        0.0
                    }
            }
        });
        // a view that is not row-major (transposed) gives what its row-major copy gives
        let t = d.t();
        let tc = t.as_standard_layout().into_owned();
        assert_eq!(EdgeMaps::of(t, 3).relief, EdgeMaps::of(tc.view(), 3).relief);
        let (a, b) = (high_pass(t, 5), high_pass(tc.view(), 5));
        assert!(
            a.iter()
                .zip(b.iter())
                .all(|(x, y)| x.to_bits() == y.to_bits())
        );
        for stride in [2usize, 3] {
            let grid = ndarray::s![..;stride, ..;stride];
            let full = EdgeMaps::of(d.view(), 3);
            // the window's range by brute force
            for (v, u) in [(0usize, 0usize), (9, 10), (19, 29), (36, 50), (12, 25)] {
                let vals: Vec<f32> = (v.saturating_sub(3)..(v + 4).min(37))
                    .flat_map(|y| (u.saturating_sub(3)..(u + 4).min(51)).map(move |x| (y, x)))
                    .map(|(y, x)| d[[y, x]])
                    .filter(|z| is_valid_depth(*z))
                    .collect();
                let lo = vals.iter().copied().fold(f32::INFINITY, f32::min);
                let hi = vals.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                assert_eq!(full.relief[[v, u]], if hi > lo { hi - lo } else { 0.0 });
            }
            let sub = EdgeMaps::of_strided(d.view(), 3, stride);
            assert_eq!(sub.relief, full.relief.slice(grid));
            assert_eq!(sub.step, full.step.slice(grid));
            let (hp, hps) = (
                high_pass(d.view(), 5),
                high_pass_strided(d.view(), 5, stride),
            );
            assert_eq!(hps.dim(), hp.slice(grid).dim());
            for (a, b) in hps.iter().zip(hp.slice(grid).iter()) {
                assert!(a.to_bits() == b.to_bits(), "{a} vs {b}");
            }
        }
    }

    #[test]
    fn high_pass_is_depth_minus_the_box_mean() {
        // a ramp: the box mean of a linear function is its value at the centre (inside)
        let d = Array2::from_shape_fn((20, 30), |(v, u)| 1.0 + 0.01 * u as f32 + 0.002 * v as f32);
        let hp = high_pass(d.view(), 3);
        assert!(hp[[10, 15]].abs() < 1e-5);
        // a spike of +10 mm on a flat 1 m: 10 mm · (1 − 1/49) at the spike
        let mut f = Array2::from_elem((20, 30), 1.0f32);
        f[[10, 15]] = 1.01;
        let hp = high_pass(f.view(), 3);
        assert!((hp[[10, 15]] - 0.01 * (1.0 - 1.0 / 49.0)).abs() < 1e-6);
        assert!((hp[[10, 12]] + 0.01 / 49.0).abs() < 1e-6);
        f[[0, 0]] = f32::NAN;
        assert!(high_pass(f.view(), 3)[[0, 0]].is_nan());
    }

    #[test]
    fn semivariogram_shares_are_recovered() {
        // γ(L) of 2 mm² at 2 px plus 3 mm² at 32 px, at the fit's lags
        let scales = FIELD_SCALES_PX;
        let semi: Vec<(f64, f64)> = LAGS
            .iter()
            .map(|&l| {
                let l = (l * FIT_STRIDE) as f64;
                (l, 2.0 * (l / 2.0).min(1.0) + 3.0 * (l / 32.0).min(1.0))
            })
            .collect();
        let v = field_variances(&semi, &scales);
        assert!(
            (v[0] - 2.0).abs() < 1e-9 && v[1].abs() < 1e-9 && (v[2] - 3.0).abs() < 1e-9,
            "{v:?}"
        );
    }

    #[test]
    fn fit_recovers_flat_sigma_offset_and_edge_gain() {
        // the aligned depth is a clean 50 mm step, so its relief is known in closed form (50 mm
        // within 3 px of the edge, 0 elsewhere); the truth is aligned − e with e = 4 mm offset
        // + ±2 mm of seeded random sign per 2 × 2 px block on flat pixels (uncorrelated beyond
        // a block: the finest scale) and ±√(σ_flat² + (0.4 · 50 mm)²) near the edge (no relief
        // compression: the offset alone leaves a small relief factor where hp has a mean)
        let (w, h) = (90usize, 60usize);
        let aligned = step_scene(w, h);
        let relief = EdgeMaps::of(aligned.view(), 3).relief;
        let e_edge = (20e-6f32 + (0.4f32 * 0.05).powi(2)).sqrt();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let signs: Array2<f32> = Array2::from_shape_fn((h / 2 + 1, w / 2 + 1), |_| {
            if rand::Rng::random::<bool>(&mut rng) {
                1.0
            } else {
                -1.0
            }
        });
        let truth = Array2::from_shape_fn((h, w), |(v, u)| {
            // 2 × 2 blocks: the fit reads every second row and column
            let sign = signs[[v / 2, u / 2]];
            let e = if relief[[v, u]] > 0.0 {
                sign * e_edge
            } else {
                0.004 + sign * 0.002
            };
            aligned[[v, u]] - e
        });
        // closed form on the fit's grid (every second row and column), flat pixels: mean
        // square (4 mm + 2 mm·s)² = 20 mm² + 16 mm²·mean(s), mean 4 mm + 2 mm·mean(s)
        let flat_signs: Vec<f64> = (0..h)
            .step_by(FIT_STRIDE)
            .flat_map(|v| (0..w).step_by(FIT_STRIDE).map(move |u| (v, u)))
            .filter(|&(v, u)| relief[[v, u]] == 0.0)
            .map(|(v, u)| f64::from(signs[[v / 2, u / 2]]))
            .collect();
        let mean_s = flat_signs.iter().sum::<f64>() / flat_signs.len() as f64;
        let total = 20e-6 + 16e-6 * mean_s;
        let offset_share = (0.004 + 0.002 * mean_s).powi(2) / total;
        let frame = ResidualFrame {
            aligned_m: aligned.view(),
            truth_m: truth.view(),
        };
        let m = DepthErrorModel::fit(&[frame], &[], 0.0).unwrap();
        assert!(
            (m.sigma_flat_m - total.sqrt()).abs() < 2e-5,
            "{m:?} {total}"
        );
        assert!(
            (m.variance_shares[0] - offset_share).abs() < 0.02,
            "{m:?} {offset_share}"
        );
        assert!(
            m.variance_shares[1] > 0.9 * (1.0 - offset_share),
            "the block noise is fine-scale: {m:?}"
        );
        assert!((m.edge_gain - 0.4).abs() < 0.01, "{m:?}");
        assert!(m.relief_bias.abs() < 0.1, "{m:?}");
        assert_eq!(m.depth_ref_m, 1.0);
        // held-out residuals 10 mm, in-sample 6 mm (both signs): σ_flat² grows by the fit's
        // optimism, 10² / 6² (closed form)
        let held = |h: f64, i: f64| HeldOutResidual {
            held_out_m: h,
            in_sample_m: i,
            depth_m: 1.0,
        };
        let m2 =
            DepthErrorModel::fit(&[frame], &[held(0.01, 0.006), held(-0.01, -0.006)], 0.0).unwrap();
        let want = m.sigma_flat_m * 0.01 / 0.006;
        assert!(
            (m2.sigma_flat_m - want).abs() < 1e-9,
            "{} {want}",
            m2.sigma_flat_m
        );
        // an outlier as far off in the fit as out of it adds nothing
        let m3 =
            DepthErrorModel::fit(&[frame], &[held(0.085, 0.085), held(0.0, 0.0)], 0.0).unwrap();
        assert!((m3.sigma_flat_m - m.sigma_flat_m).abs() < 1e-12);
        // no pixel with both depths: an error
        let none = Array2::from_elem((h, w), f32::NAN);
        let bad = ResidualFrame {
            aligned_m: none.view(),
            truth_m: truth.view(),
        };
        assert!(DepthErrorModel::fit(&[bad], &[], 0.0).is_err());
    }

    /// The model fitted on one calibration frame (no cross-validated residuals, depth space).
    fn fit_one(aligned: &Array2<f32>, truth: &Array2<f32>) -> DepthErrorModel {
        DepthErrorModel::fit(
            &[ResidualFrame {
                aligned_m: aligned.view(),
                truth_m: truth.view(),
            }],
            &[],
            0.0,
        )
        .unwrap()
    }

    /// Bumps of 20 mm on a 1 m table (every 40 px, 200 × 150 px): the truth, and the same
    /// bumps at 80 % of their height (a depth model's flattening).
    fn flattened_bumps() -> (Array2<f32>, Array2<f32>) {
        let (w, h) = (200usize, 150usize);
        let bump = |u: usize, v: usize| {
            let (x, y) = ((u % 40) as f32 - 20.0, (v % 40) as f32 - 20.0);
            0.02 * (-(x * x + y * y) / 50.0).exp()
        };
        let truth = Array2::from_shape_fn((h, w), |(v, u)| 1.0 - bump(u, v));
        let aligned = Array2::from_shape_fn((h, w), |(v, u)| 1.0 - 0.8 * bump(u, v));
        (truth, aligned)
    }

    #[test]
    fn fit_measures_relief_compression() {
        // truth: bumps of 20 mm on a 1 m table; aligned: the same bumps at 80 % height
        let (truth, aligned) = flattened_bumps();
        let frame = ResidualFrame {
            aligned_m: aligned.view(),
            truth_m: truth.view(),
        };
        let m = DepthErrorModel::fit(&[frame], &[], 0.0).unwrap();
        // truth − aligned = −0.2·bump and hp ≈ −0.8·bump + its box mean: c ≈ 0.25
        assert!((m.relief_bias - 0.25).abs() < 0.05, "{m:?}");
    }

    /// Mean over the in-image part of a (2r+1)² window, written plainly (rows, then columns).
    fn window_mean(z: &Array2<f32>, r: usize) -> Array2<f32> {
        let (h, w) = z.dim();
        let rows = Array2::from_shape_fn((h, w), |(v, u)| {
            let (lo, hi) = (u.saturating_sub(r), (u + r + 1).min(w));
            (lo..hi).map(|x| z[[v, x]]).sum::<f32>() / (hi - lo) as f32
        });
        Array2::from_shape_fn((h, w), |(v, u)| {
            let (lo, hi) = (v.saturating_sub(r), (v + r + 1).min(h));
            (lo..hi).map(|y| rows[[y, u]]).sum::<f32>() / (hi - lo) as f32
        })
    }

    /// A 1 m table (320 × 240 px) with the 20 mm bumps of [`flattened_bumps`] and four 0.25 m
    /// tall towers (24 × 24 px tops), and the depth model's view: relief against a 41 px window
    /// mean compressed to 80 %, the towers' included (`towers_flattened`), or the towers at
    /// their true height (only the bumps compressed).
    fn bumps_and_towers(towers_flattened: bool) -> (Array2<f32>, Array2<f32>, Vec<[usize; 2]>) {
        let (w, h) = (320usize, 240usize);
        let bump = |u: usize, v: usize| {
            let (x, y) = ((u % 40) as f32 - 20.0, (v % 40) as f32 - 20.0);
            0.02 * (-(x * x + y * y) / 50.0).exp()
        };
        let corners = vec![[40usize, 50usize], [40, 230], [150, 110], [170, 260]];
        let tower = |u: usize, v: usize| {
            corners
                .iter()
                .any(|&[v0, u0]| (v0..v0 + 24).contains(&v) && (u0..u0 + 24).contains(&u))
        };
        let bumps = Array2::from_shape_fn((h, w), |(v, u)| 1.0 - bump(u, v));
        let truth = Array2::from_shape_fn(
            (h, w),
            |(v, u)| {
                if tower(u, v) { 0.75 } else { bumps[[v, u]] }
            },
        );
        let compressed = |z: &Array2<f32>| {
            let mean = window_mean(z, 20);
            Array2::from_shape_fn(z.dim(), |(v, u)| {
                mean[[v, u]] + 0.8 * (z[[v, u]] - mean[[v, u]])
            })
        };
        let aligned = if towers_flattened {
            compressed(&truth)
        } else {
            let flat_bumps = compressed(&bumps);
            Array2::from_shape_fn((h, w), |(v, u)| {
                if tower(u, v) {
                    0.75
                } else {
                    flat_bumps[[v, u]]
                }
            })
        };
        (truth, aligned, corners)
    }

    /// The relief radius: a depth model that flattens relief against a window mean of radius
    /// 19 px (3 % of 640), 29 px (4.5 %) or 48 px (7.5 %) is fitted with that radius, among
    /// [`RELIEF_RADIUS_SHARES`], its factor (80 % kept: c = 0.25) is recovered, and its
    /// expected truth (the relief's fixed point) is the truth within 3 % of the aligned depth's
    /// error and half the first-order correction's. The scene: a 1 m table, 640 × 480 px, with square blocks 10–40 mm tall
    /// and 20–80 px wide.
    #[test]
    fn fit_chooses_the_relief_radius_the_depth_model_flattens_with() {
        let (w, h) = (640usize, 480usize);
        let truth = Array2::from_shape_fn((h, w), |(v, u)| {
            let (cu, cv) = (u / 80, v / 80);
            let half = 10 + 10 * ((cu + 2 * cv) % 4); // 10–40 px
            let (du, dv) = ((u % 80).abs_diff(40), (v % 80).abs_diff(40));
            if du < half && dv < half {
                1.0 - 0.01 * (1 + (cu + cv) % 4) as f32
            } else {
                1.0
            }
        });
        for (r0, share) in [(19usize, 0.03), (29, 0.045), (48, 0.075)] {
            let mean = window_mean(&truth, r0);
            let aligned = Array2::from_shape_fn((h, w), |(v, u)| {
                mean[[v, u]] + 0.8 * (truth[[v, u]] - mean[[v, u]])
            });
            let m = fit_one(&aligned, &truth);
            assert_eq!(
                m.relief_radius_px,
                relief_radius_for(
                    ImageSize {
                        width: w,
                        height: h
                    },
                    share
                ),
                "flattened against {r0} px: {m:?}"
            );
            assert_eq!(m.relief_radius_px as usize, r0);
            assert!((m.relief_bias - 0.25).abs() < 0.05, "{r0} px: {m:?}");
            // the expected truth undoes the flattening: the truth itself, an independent answer
            let mae = |d: &Array2<f32>| {
                d.iter()
                    .zip(truth.iter())
                    .map(|(x, t)| f64::from((x - t).abs()))
                    .sum::<f64>()
                    / d.len() as f64
            };
            let (before, after) = (
                mae(&aligned),
                mae(&m.expected_truth_map(aligned.view(), false)),
            );
            // the fixed point undoes a linear flattening better than the first-order
            // correction (which moves the table beside a block and the block's rims): measured
            // 1.25 / 1.66 / 2.12 mm aligned, 0.077 / 0.077 / 0.098 mm first order, 0.033 /
            // 0.034 / 0.029 mm fixed point (19 / 29 / 48 px)
            let hp = high_pass(aligned.view(), m.relief_radius_px);
            let first_order = &aligned + &hp.mapv(|h| h * m.relief_bias as f32);
            let first = mae(&first_order);
            assert!(
                after < 0.03 * before && after < 0.5 * first,
                "{r0} px: MAE {before} aligned, {first} first order, {after} m fixed point"
            );
        }
    }

    /// Fit step 1c's guard: an aligned depth that is the truth plus correlated noise (2 mm, a
    /// few pixels wide), no flattening at all, keeps the 7.5 % radius. At 19 px least squares
    /// finds a negative factor there (it smooths the noise and would flatten the blocks).
    #[test]
    fn noise_alone_does_not_choose_a_small_relief_radius() {
        let (w, h) = (640usize, 480usize);
        let truth = Array2::from_shape_fn((h, w), |(v, u)| {
            let (du, dv) = ((u % 80).abs_diff(40), (v % 80).abs_diff(40));
            if du < 25 && dv < 25 { 0.97f32 } else { 1.0 }
        });
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let white = Array2::from_shape_fn((h, w), |_| 0.004 * normal(&mut rng));
        let noise = window_mean(&white, 2);
        let aligned = &truth + &noise;
        let m = fit_one(&aligned, &truth);
        assert_eq!(m.relief_radius_px, 48, "{m:?}");
        // the premise: the smallest radius alone fits a negative factor
        let frame = [ResidualFrame {
            aligned_m: aligned.view(),
            truth_m: truth.view(),
        }];
        let grids: Vec<FitGrid> = frame
            .iter()
            .map(|f| FitGrid {
                hp: high_pass_strided(f.aligned_m, 19, FIT_STRIDE),
                ..FitGrid::of(f, m.edge_radius_px)
            })
            .collect();
        let small = ReliefFit::of(&grids);
        assert!(small.factor < 0.0, "{small:?}");
    }

    /// Fit step 1b: towers that the depth model flattens as it flattens the bumps extend the
    /// relief range, and their tops are corrected over their whole height (an independent
    /// expectation: the truth, ≥ 30 mm off in the aligned depth); towers it shows at their true
    /// height keep the range at [`MAX_RELIEF_M`].
    #[test]
    fn the_relief_range_extends_only_where_tall_objects_follow_the_factor() {
        let top_error = |depth: &Array2<f32>, truth: &Array2<f32>, corners: &[[usize; 2]]| {
            let mut errs: Vec<f32> = corners
                .iter()
                .flat_map(|&[v0, u0]| {
                    (v0 + 4..v0 + 20).flat_map(move |v| (u0 + 4..u0 + 20).map(move |u| (v, u)))
                })
                .map(|(v, u)| (depth[[v, u]] - truth[[v, u]]).abs())
                .collect();
            let k = errs.len() / 2;
            *errs.select_nth_unstable_by(k, f32::total_cmp).1
        };
        let (truth, aligned, corners) = bumps_and_towers(true);
        let m = fit_one(&aligned, &truth);
        assert!(m.relief_max_m >= 0.2, "{m:?}");
        assert!(m.relief_bias > 0.15 && m.relief_bias < 0.4, "{m:?}");
        let before = top_error(&aligned, &truth, &corners);
        assert!(
            before > 0.03,
            "the premise: tops 30 mm off or more ({before})"
        );
        let extended = top_error(
            &m.expected_truth_map(aligned.view(), false),
            &truth,
            &corners,
        );
        let clamped_model = DepthErrorModel {
            relief_max_m: MAX_RELIEF_M,
            ..m
        };
        let clamped = top_error(
            &clamped_model.expected_truth_map(aligned.view(), false),
            &truth,
            &corners,
        );
        // measured: 32.7 mm before, 1.7 mm over the extended range, 10.9 mm clamped at 0.1 m
        assert!(
            extended < 0.005 && extended < 0.5 * clamped,
            "tower tops off by {extended} m with the range {} m, {clamped} m with 0.1 m",
            m.relief_max_m
        );
        // towers at their true height: the tower band's own factor is ~0, the range stays 0.1 m
        let (truth, aligned, _) = bumps_and_towers(false);
        let m = fit_one(&aligned, &truth);
        assert_eq!(m.relief_max_m, MAX_RELIEF_M, "{m:?}");
    }

    /// Fit step 1: a factor within [MIN_RELIEF_FACTOR, MAX_RELIEF_FACTOR] is kept (bumps at
    /// 60 % of their height: c ≈ 1/0.6 − 1 = 0.67), one outside is no relief error and the
    /// model has no relief part (bumps at 20 %: c ≈ 4).
    #[test]
    fn a_relief_factor_beyond_any_flattening_is_dropped() {
        let (truth, _) = flattened_bumps();
        let kept_at = |k: f32| {
            let aligned = truth.mapv(|z| 1.0 - k * (1.0 - z));
            fit_one(&aligned, &truth)
        };
        let m = kept_at(0.6);
        assert!((m.relief_bias - 0.67).abs() < 0.15, "{m:?}");
        assert_eq!(m.relief_sigma, m.relief_bias);
        let m = kept_at(0.2);
        assert_eq!((m.relief_bias, m.relief_sigma), (0.0, 0.0), "{m:?}");
        assert_eq!(m.relief_max_m, MAX_RELIEF_M);
        m.validate().unwrap();
    }

    /// The row-at-a-time smoothing of [`DepthErrorModel::expected_truth`] equals a plain
    /// pixel-by-pixel scan (written here independently), bit for bit: holes, a step, the image
    /// border, a region of interest.
    #[test]
    fn expected_truth_equals_a_pixel_by_pixel_scan() {
        let (w, h) = (53usize, 41usize);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let depth = Array2::from_shape_fn((h, w), |(v, u)| {
            let noise: f32 = StandardNormal.sample(&mut rng);
            if (u * 7 + v * 3) % 23 == 0 {
                f32::NAN
            } else if u > 30 {
                0.9 + 0.003 * noise
            } else {
                1.0 + 0.003 * noise
            }
        });
        let m = DepthErrorModel {
            sigma_flat_m: 0.004,
            variance_shares: [0.0, 0.0, 0.6, 0.4],
            ..DepthErrorModel::default()
        };
        let r = m.scales_px[1].round() as usize;
        let t = |z: f32| (3.0 * 0.004 * 0.6f64.sqrt() + 0.002) as f32 + 0.0 * z;
        let mean = |z0: f32, vals: Vec<f32>| {
            let (mut s, mut n) = (0.0f32, 0u32);
            for z in vals {
                if z.is_finite() && z > 0.0 && (z - z0).abs() <= t(z0) {
                    s += z;
                    n += 1;
                }
            }
            if n == 0 { z0 } else { s / n as f32 }
        };
        for roi in [
            Roi::full(w, h),
            Roi {
                u0: 5,
                v0: 9,
                width: 30,
                height: 20,
            },
        ] {
            let rows = Array2::from_shape_fn((h, w), |(v, u)| {
                let z0 = depth[[v, u]];
                if !(z0.is_finite() && z0 > 0.0) {
                    return z0;
                }
                mean(
                    z0,
                    (u.saturating_sub(r)..(u + r + 1).min(w))
                        .map(|x| depth[[v, x]])
                        .collect(),
                )
            });
            let mut want = depth.clone();
            for v in roi.v0..roi.v0 + roi.height {
                for u in roi.u0..roi.u0 + roi.width {
                    let z0 = rows[[v, u]];
                    if z0.is_finite() && z0 > 0.0 {
                        want[[v, u]] = mean(
                            z0,
                            (v.saturating_sub(r)..(v + r + 1).min(h))
                                .map(|y| rows[[y, u]])
                                .collect(),
                        );
                    }
                }
            }
            let got = m.expected_truth(depth.view(), roi);
            for (a, b) in got.iter().zip(want.iter()) {
                assert!(
                    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()),
                    "{a} vs {b}"
                );
            }
        }
    }

    /// The expected truth of a flattened scene, with the model fitted on it: closer to the
    /// truth (the compression undone to within half of it), each part alone, and the clamp.
    #[test]
    fn expected_truth_map_undoes_the_mean_relief_and_edge_errors() {
        // the bumps of `fit_measures_relief_compression`, 20 mm tall, flattened to 80 %
        let (truth, aligned) = flattened_bumps();
        let m = fit_one(&aligned, &truth);
        // the least-squares factor lowers the RMS error (the flat table between the bumps moves
        // by c times the box mean of the bumps: the MAE barely changes), and the error on the
        // bumps' tops, what a gripper touches
        let rms = |a: &Array2<f32>| {
            (a.iter()
                .zip(truth.iter())
                .map(|(x, t)| (x - t).powi(2))
                .sum::<f32>()
                / a.len() as f32)
                .sqrt()
        };
        let expected = m.expected_truth_map(aligned.view(), false);
        let (before, after) = (rms(&aligned), rms(&expected));
        assert!(after < 0.6 * before, "RMS {before} → {after} m ({m:?})");
        let (top_before, top_after) = (
            (aligned[[20, 20]] - truth[[20, 20]]).abs(),
            (expected[[20, 20]] - truth[[20, 20]]).abs(),
        );
        assert!(
            top_after < 0.35 * top_before,
            "bump top {top_before} → {top_after} m"
        );
        // a model without means (and without short-range fields) changes nothing, bit for bit
        let none = DepthErrorModel::uniform(0.01).unwrap();
        assert_eq!(none.expected_truth_map(aligned.view(), true), aligned);
        assert_eq!(
            m.deviations().expected_truth_map(aligned.view(), false),
            aligned
        );
        // the deviations keep the σ of every part and drop the means
        let d = m.deviations();
        assert_eq!((d.relief_bias, d.edge_sharpening), (0.0, 0.0));
        assert_eq!(
            (d.relief_sigma, d.sigma_flat_m, d.edge_gain),
            (m.relief_sigma, m.sigma_flat_m, m.edge_gain)
        );
        // the relief correction never goes past the range it was fitted on: a 0.5 m tower
        // moves by at most relief_bias · MAX_RELIEF_M
        let (h, w) = aligned.dim();
        let tower = Array2::from_shape_fn((h, w), |(v, u)| {
            if (90..110).contains(&u) && (65..85).contains(&v) {
                0.5f32
            } else {
                1.0
            }
        });
        let strong = DepthErrorModel {
            relief_bias: 0.5,
            relief_radius_px: 30,
            ..DepthErrorModel::default()
        };
        let moved = strong.expected_truth_map(tower.view(), false);
        let most = moved
            .iter()
            .zip(tower.iter())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(
            f64::from(most) <= 0.5 * MAX_RELIEF_M + 1e-6,
            "moved {most} m"
        );
        assert!(
            f64::from(most) >= 0.5 * MAX_RELIEF_M - 1e-6,
            "the tower is clamped, not ignored"
        );
        // the edge share alone: a 6 px ramp with share 1 snaps to the step but for the ramp's
        // middle (the window's midpoint decides the side)
        let ramp = Array2::from_shape_fn((40, 100), |(_, u)| {
            0.96f32 + 0.04 * ((u as f32 - 46.5) / 6.0).clamp(0.0, 1.0)
        });
        let sharp = DepthErrorModel {
            edge_sharpening: 1.0,
            ..DepthErrorModel::default()
        }
        .expected_truth_map(ramp.view(), false);
        for u in [47usize, 48, 49] {
            assert!(
                (sharp[[20, u]] - 0.96).abs() < 1e-6,
                "u {u}: {}",
                sharp[[20, u]]
            );
        }
        for u in [50usize, 51, 52] {
            assert!(
                (sharp[[20, u]] - 1.0).abs() < 1e-6,
                "u {u}: {}",
                sharp[[20, u]]
            );
        }
    }

    /// Degenerate maps through the expected truth: no panic, pixels without depth stay without
    /// depth, and every output is a valid depth or the input's invalid value.
    #[test]
    fn expected_truth_map_of_degenerate_maps() {
        let m = DepthErrorModel {
            sigma_flat_m: 0.004,
            variance_shares: [0.0, 0.2, 0.4, 0.4],
            relief_bias: 0.2,
            relief_sigma: 0.2,
            relief_radius_px: 5,
            edge_sharpening: 0.6,
            edge_sharpening_sigma: 0.3,
            ..DepthErrorModel::default()
        };
        let maps = [
            Array2::from_elem((1, 1), 0.7f32),
            Array2::from_elem((2, 3), f32::NAN),
            Array2::from_shape_fn(
                (3, 2),
                |(v, u)| if (u + v) % 2 == 0 { 0.5 } else { f32::NAN },
            ),
            Array2::from_shape_fn((4, 9), |(_, u)| if u < 4 { 0.0 } else { f32::INFINITY }),
            Array2::from_shape_fn(
                (7, 5),
                |(v, u)| if v == 3 { -1.0 } else { 0.6 + 0.01 * u as f32 },
            ),
        ];
        for d in &maps {
            for smooth in [false, true] {
                let e = m.expected_truth_map(d.view(), smooth);
                assert_eq!(e.dim(), d.dim());
                for (a, b) in e.iter().zip(d.iter()) {
                    if is_valid_depth(*b) {
                        assert!(is_valid_depth(*a), "{b} became {a}");
                    } else {
                        assert!(a.to_bits() == b.to_bits(), "invalid {b} became {a}");
                    }
                }
            }
        }
    }

    /// Residual variance the semivariogram does not reach within its lags (a field varying over
    /// hundreds of pixels) moves a gripper's footprint as a whole: it joins the offset, and the
    /// noise within a cup-sized patch stays at the field's own variation there.
    #[test]
    fn long_range_residuals_are_an_offset_not_bumps() {
        // aligned: a flat table at 1 m; truth: aligned + 5 mm · sin(2π u / 600 px)
        let (w, h) = (600usize, 300usize);
        let aligned = Array2::from_elem((h, w), 1.0f32);
        let truth = Array2::from_shape_fn((h, w), |(_, u)| {
            1.0 + 0.005 * (std::f32::consts::TAU * u as f32 / 600.0).sin()
        });
        let m = fit_one(&aligned, &truth);
        // σ: 5 mm / √2
        assert!((m.sigma_flat_m - 0.005 / 2f64.sqrt()).abs() < 2e-4, "{m:?}");
        // within 10 px the sine changes by at most 5 mm · 2π · 10 / 600 = 0.52 mm
        let within = m.noise_within_m(1.0, 10.0);
        assert!(within < 0.001, "{within} m within 10 px ({m:?})");
        assert!(m.variance_shares[0] > 0.5, "{m:?}");
    }

    #[test]
    fn fit_measures_edge_ramps_against_steps() {
        // truth: a 40 mm step at u = 50; aligned: the same step as a 6 px ramp (no pixel at
        // the ramp's midpoint, which no rule could assign to a side)
        let (w, h) = (100usize, 40usize);
        let truth = Array2::from_shape_fn((h, w), |(_, u)| if u < 50 { 0.96f32 } else { 1.0 });
        let aligned = Array2::from_shape_fn((h, w), |(_, u)| {
            let t = ((u as f32 - 46.5) / 6.0).clamp(0.0, 1.0);
            0.96 + 0.04 * t
        });
        let frame = ResidualFrame {
            aligned_m: aligned.view(),
            truth_m: truth.view(),
        };
        let m = DepthErrorModel::fit(&[frame], &[], 0.0).unwrap();
        // snapping each ramp pixel to its side of the window's midpoint recovers the truth
        // but for the pixels whose window does not reach both plateaus: a close to 1
        assert!(m.edge_sharpening > 0.8, "{m:?}");
        // and a draw with the mean share turns the ramp back into (most of) the step
        let d = MetricDepth::new(aligned.clone());
        let sharp = DepthErrorModel {
            edge_sharpening: 1.0,
            ..DepthErrorModel::default()
        };
        let x = sharp.draw(&d, 0, 0);
        assert_eq!(x.depth_m[[20, 48]], 0.96);
        assert_eq!(x.depth_m[[20, 51]], 1.0);
    }

    #[test]
    fn draws_have_the_modelled_variance() {
        // over many draws, each pixel's sample variance matches σ(u, v)² (no relief part: its
        // bias is a mean, not a variance)
        let (w, h) = (48usize, 36usize);
        let d = MetricDepth::new(step_scene(w, h));
        let m = DepthErrorModel {
            sigma_flat_m: 0.006,
            variance_shares: [0.25, 0.25, 0.25, 0.25],
            scales_px: [2.0, 4.0, 8.0],
            edge_gain: 0.3,
            edge_radius_px: 2,
            ..DepthErrorModel::default()
        };
        let sigma = m.sigma_map(&d);
        let n = 3000;
        let mut s2 = Array2::<f64>::zeros((h, w));
        for k in 0..n {
            let x = m.draw(&d, 7, k);
            ndarray::Zip::from(&mut s2)
                .and(&x.depth_m)
                .and(&d.depth_m)
                .for_each(|s, &a, &b| *s += ((a - b) as f64).powi(2));
        }
        // away from the box's edges (on its sharp edges a pixel is at its window's side: the
        // edge noise moves ramps, next test)
        for (v, u) in [(2usize, 2usize), (18, 24), (30, 40)] {
            let est = (s2[[v, u]] / n as f64).sqrt();
            let want = sigma[[v, u]] as f64;
            assert!(
                (est - want).abs() < 0.06 * want,
                "pixel ({u}, {v}): draws σ {est}, model σ {want}"
            );
        }
        // same seed and draw: same map; another draw: another map
        assert_eq!(m.draw(&d, 7, 3), m.draw(&d, 7, 3));
        assert_ne!(m.draw(&d, 7, 3), m.draw(&d, 7, 4));
    }

    /// The edge noise moves silhouettes: on a ramp from a table at 1 m to a box top at 0.95 m
    /// over 4 px, a draw puts a mid-ramp pixel at the table, at the top, or leaves it, never
    /// in mid-air elsewhere; over many draws its σ is the σ map's edge part, `edge_gain` × the
    /// window's range (0.3 × 50 mm), and it goes up and down equally often.
    #[test]
    fn the_edge_noise_moves_silhouettes_and_has_the_modelled_variance() {
        let (w, h) = (40usize, 8usize);
        let ramp = |u: usize| match u {
            0..=20 => 1.0f32,
            21..=23 => 1.0 - 0.0125 * (u - 20) as f32,
            _ => 0.95,
        };
        let d = MetricDepth::new(Array2::from_shape_fn((h, w), |(_, u)| ramp(u)));
        let m = DepthErrorModel {
            sigma_flat_m: 0.0,
            edge_gain: 0.3,
            edge_radius_px: 2,
            ..DepthErrorModel::default()
        };
        let want = f64::from(m.sigma_map(&d)[[4, 22]]);
        assert!((want - 0.015).abs() < 1e-6, "{want}");
        let n = 4000;
        let (mut s2, mut up, mut down) = (0.0f64, 0, 0);
        for k in 0..n {
            let z = m.draw(&d, 11, k).depth_m[[4, 22]];
            assert!(
                [0.975f32, 0.95, 1.0].iter().any(|s| (z - s).abs() < 1e-6),
                "draw {k}: {z} m is in mid-air"
            );
            s2 += f64::from(z - 0.975).powi(2);
            up += usize::from(z > 0.976);
            down += usize::from(z < 0.974);
        }
        let est = (s2 / n as f64).sqrt();
        assert!(
            (est - want).abs() < 0.06 * want,
            "draws σ {est}, model σ {want}"
        );
        // each side with chance 2 g² = 0.18
        for side in [up, down] {
            assert!(
                (side as f64 / n as f64 - 0.18).abs() < 0.03,
                "{up} up, {down} down"
            );
        }
    }

    #[test]
    fn sigma_grows_with_depth_squared_in_inverse_space() {
        let m = DepthErrorModel {
            sigma_flat_m: 0.005,
            depth_ref_m: 1.0,
            depth_exponent: 2.0,
            ..DepthErrorModel::default()
        };
        let d = MetricDepth::new(Array2::from_shape_fn(
            (4, 4),
            |(v, _)| if v < 2 { 1.0 } else { 2.0 },
        ));
        let s = m.sigma_map(&d);
        assert!((s[[0, 0]] - 0.005).abs() < 1e-7);
        assert!((s[[3, 3]] - 0.02).abs() < 1e-7);
    }

    #[test]
    fn no_depth_stays_no_depth_and_a_zero_model_changes_nothing() {
        let mut a = step_scene(20, 10);
        a[[0, 0]] = f32::NAN;
        let d = MetricDepth::new(a);
        let m = DepthErrorModel::uniform(0.01).unwrap();
        let x = m.draw(&d, 1, 0);
        assert!(x.depth_m[[0, 0]].is_nan());
        assert!(m.sigma_map(&d)[[0, 0]].is_nan());
        assert_eq!(
            DepthErrorModel::default().draw(&d, 1, 0).depth_m[[5, 5]],
            d.depth_m[[5, 5]]
        );
        assert!(DepthErrorModel::uniform(-1.0).is_err());
        assert!(DepthErrorModel::uniform(f64::NAN).is_err());
        let shares = DepthErrorModel {
            variance_shares: [0.5, 0.5, 0.5, 0.5],
            ..DepthErrorModel::default()
        };
        assert!(shares.validate().is_err());
    }

    #[test]
    fn a_frame_residual_sets_the_flat_sigma_within_bounds() {
        let m = DepthErrorModel::uniform(0.008).unwrap();
        // narrower and wider than the calibration's, as the frame's anchors measure
        assert_eq!(m.for_frame(Some(0.003)).sigma_flat_m, 0.003);
        assert_eq!(m.for_frame(Some(0.012)).sigma_flat_m, 0.012);
        // never below a quarter of the calibration's, never above 10 m
        assert_eq!(m.for_frame(Some(0.0005)).sigma_flat_m, 0.002);
        assert_eq!(m.for_frame(Some(0.0)).sigma_flat_m, 0.002);
        assert_eq!(m.for_frame(Some(1e6)).sigma_flat_m, 10.0);
        // no residual, or a meaningless one: the calibration's
        assert_eq!(m.for_frame(None).sigma_flat_m, 0.008);
        assert_eq!(m.for_frame(Some(f64::NAN)).sigma_flat_m, 0.008);
        assert_eq!(m.for_frame(Some(f64::INFINITY)).sigma_flat_m, 0.008);
    }

    #[test]
    fn a_drift_residual_adds_to_the_calibrations_own_error() {
        let fitted = DepthErrorModel {
            sigma_flat_m: 0.010,
            sigma_dense_m: Some(0.003),
            ..DepthErrorModel::default()
        };
        // 3-4-5: the calibration frame's own 3 mm and a 4 mm drift residual
        let m = fitted.with_frame_drift(Some(0.004));
        assert!((m.sigma_flat_m - 0.005).abs() < 1e-12, "{}", m.sigma_flat_m);
        // without a drift, the calibration's own error (not its cross-validated floor)
        assert!((fitted.with_frame_drift(Some(0.0)).sigma_flat_m - 0.003).abs() < 1e-12);
        // a model from an older file: sigma_flat_m stands in for the dense part
        let old = DepthErrorModel::uniform(0.006).unwrap();
        assert!((old.with_frame_drift(Some(0.008)).sigma_flat_m - 0.010).abs() < 1e-12);
        // no residual, or a meaningless one: the calibration's model; never above 10 m
        assert_eq!(fitted.with_frame_drift(None), fitted);
        assert_eq!(fitted.with_frame_drift(Some(f64::NAN)), fitted);
        assert_eq!(fitted.with_frame_drift(Some(1e6)).sigma_flat_m, 10.0);
        // every other part is the calibration's
        assert_eq!(m.sigma_dense_m, fitted.sigma_dense_m);
        assert_eq!(m.relief_bias, fitted.relief_bias);
    }

    #[test]
    fn a_drift_residual_moves_whole_frames_and_keeps_the_short_range_noise() {
        // the calibration's 3 mm: 40 % offset, 30 % fine, 20 % medium, 10 % coarse
        let fitted = DepthErrorModel {
            sigma_flat_m: 0.010,
            sigma_dense_m: Some(0.003),
            variance_shares: [0.4, 0.3, 0.2, 0.1],
            ..DepthErrorModel::default()
        };
        let m = fitted.with_frame_drift(Some(0.004));
        // 5 mm in all (3-4-5); each field keeps its variance in metres², the offset takes the
        // drift's 16 mm²: (0.4·9 + 16) / 25, 0.3·9 / 25, 0.2·9 / 25, 0.1·9 / 25
        let expected = [19.6 / 25.0, 2.7 / 25.0, 1.8 / 25.0, 0.9 / 25.0];
        for (got, want) in m.variance_shares.iter().zip(expected) {
            assert!((got - want).abs() < 1e-12, "{:?}", m.variance_shares);
        }
        assert!((m.variance_shares.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        // so the noise within a patch, which tilts a cup, is the calibration frame's own
        // (σ_dense's), whatever the drift
        for radius_px in [1.0, 4.0, 10.0, 40.0] {
            let own = DepthErrorModel {
                sigma_flat_m: 0.003,
                ..fitted.clone()
            };
            let (a, b) = (
                m.noise_within_m(1.0, radius_px),
                own.noise_within_m(1.0, radius_px),
            );
            assert!((a - b).abs() < 1e-12, "{radius_px}: {a} vs {b}");
        }
        // no drift: the shares as fitted
        assert_eq!(
            fitted.with_frame_drift(Some(0.0)).variance_shares,
            fitted.variance_shares
        );
        // a zero model stays zero and its shares as they were
        let zero = DepthErrorModel {
            sigma_flat_m: 0.0,
            sigma_dense_m: Some(0.0),
            ..fitted
        };
        assert_eq!(
            zero.with_frame_drift(Some(0.0)).variance_shares,
            fitted.variance_shares
        );
    }

    #[test]
    fn the_background_residual_sets_the_flat_sigma_at_the_reference_depth() {
        // σ grows as z² (inverse space), reference depth 0.5 m; the calibration frame's own
        // 3 mm: 40 % offset, 30 % fine, 20 % medium, 10 % coarse
        let fitted = DepthErrorModel {
            sigma_flat_m: 0.010,
            sigma_dense_m: Some(0.003),
            depth_ref_m: 0.5,
            depth_exponent: 2.0,
            variance_shares: [0.4, 0.3, 0.2, 0.1],
            ..DepthErrorModel::default()
        };
        // 0.04 m⁻¹ in inverse depth is 0.04 · 0.5² = 10 mm at the reference depth, whatever
        // depth the anchors were at (the metres RMSE is not used for this law)
        let m = fitted.for_frame_on_background(0.123, Some(0.04));
        assert!((m.sigma_flat_m - 0.010).abs() < 1e-15, "{}", m.sigma_flat_m);
        // and 40 mm at 1 m: the σ map of a flat model (no relief, no edges) follows z²
        let flat = MetricDepth::new(Array2::from_elem((4, 4), 1.0f32));
        let sigma = m.sigma_map(&flat);
        assert!(sigma.iter().all(|&s| (s - 0.040).abs() < 1e-6), "{sigma:?}");
        // each field keeps its variance in metres², 0.3·9, 0.2·9, 0.1·9 mm² of 100 mm²
        let expected = [1.0 - 5.4 / 100.0, 2.7 / 100.0, 1.8 / 100.0, 0.9 / 100.0];
        for (got, want) in m.variance_shares.iter().zip(expected) {
            assert!((got - want).abs() < 1e-12, "{:?}", m.variance_shares);
        }
        // so the noise within a cup's patch is the calibration frame's own
        let own = DepthErrorModel {
            sigma_flat_m: 0.003,
            ..fitted.clone()
        };
        for radius_px in [1.0, 4.0, 10.0, 40.0] {
            let (a, b) = (
                m.noise_within_m(0.5, radius_px),
                own.noise_within_m(0.5, radius_px),
            );
            assert!((a - b).abs() < 1e-12, "{radius_px}: {a} vs {b}");
        }
        // below what the fields hold (0.6 · 9 mm²): the fields alone, no offset
        let low = fitted.for_frame_on_background(0.0, Some(0.0));
        assert!((low.sigma_flat_m - (0.6f64 * 9e-6).sqrt()).abs() < 1e-15);
        let want = [0.0, 0.5, 1.0 / 3.0, 1.0 / 6.0];
        for (got, want) in low.variance_shares.iter().zip(want) {
            assert!((got - want).abs() < 1e-12, "{:?}", low.variance_shares);
        }
        // a frame with no short-range fields: the floor, a quarter of the dense σ
        let smooth = DepthErrorModel {
            variance_shares: [1.0, 0.0, 0.0, 0.0],
            ..fitted.clone()
        };
        let floored = smooth.for_frame_on_background(0.0, Some(0.0));
        assert!((floored.sigma_flat_m - 0.00075).abs() < 1e-15);
        assert_eq!(floored.variance_shares, [1.0, 0.0, 0.0, 0.0]);
        // σ constant in metres (depth space): the metres RMSE itself
        let metric = DepthErrorModel {
            depth_exponent: 0.0,
            ..fitted.clone()
        };
        let m0 = metric.for_frame_on_background(0.007, Some(0.04));
        assert!((m0.sigma_flat_m - 0.007).abs() < 1e-15);
        // every result a valid model; a meaningless residual changes nothing; never above 10 m
        for r in [m, low, floored, m0] {
            r.validate().unwrap();
        }
        assert_eq!(
            fitted.for_frame_on_background(f64::NAN, Some(f64::NAN)),
            fitted
        );
        assert_eq!(metric.for_frame_on_background(f64::INFINITY, None), metric);
        let huge = fitted.for_frame_on_background(1.0, Some(1e9));
        assert_eq!(huge.sigma_flat_m, 10.0);
        huge.validate().unwrap();
        // a model from an older file (no dense σ): sigma_flat_m stands in for it
        let old = DepthErrorModel {
            sigma_dense_m: None,
            ..fitted
        };
        let o = old.for_frame_on_background(0.0, Some(0.0));
        assert!((o.sigma_flat_m - (0.6f64 * 1e-4).sqrt()).abs() < 1e-15);
    }

    #[test]
    fn the_fit_records_its_dense_sigma_below_the_held_out_level() {
        // truth = aligned + 2 mm of alternating noise on a flat 1 m plane; samples 6 mm off out
        // of the fit that sat on them (a fit exact at its samples: the optimism is without
        // bound, and the held-out level bounds it): σ_flat 6 mm, the dense part the frame's 2 mm
        let aligned = Array2::from_elem((64, 64), 1.0f32);
        let truth = Array2::from_shape_fn((64, 64), |(v, u)| {
            1.0 + if (u + v) % 2 == 0 { 0.002 } else { -0.002 }
        });
        let frame = ResidualFrame {
            aligned_m: aligned.view(),
            truth_m: truth.view(),
        };
        let cv = vec![
            HeldOutResidual {
                held_out_m: 0.006,
                in_sample_m: 0.0,
                depth_m: 1.0,
            };
            20
        ];
        let m = DepthErrorModel::fit(&[frame], &cv, 0.0).unwrap();
        assert!((m.sigma_flat_m - 0.006).abs() < 1e-6, "{}", m.sigma_flat_m);
        // samples 6 mm off out of the fit and 5.9 mm in it: a ratio of (6 / 5.9)² on the dense
        // 2 mm
        let near = vec![
            HeldOutResidual {
                held_out_m: 0.006,
                in_sample_m: 0.0059,
                depth_m: 1.0,
            };
            20
        ];
        let m = DepthErrorModel::fit(&[frame], &near, 0.0).unwrap();
        let want = 0.002 * 0.006 / 0.0059;
        assert!(
            (m.sigma_flat_m - want).abs() < 1e-5,
            "{} {want}",
            m.sigma_flat_m
        );
        // a non-finite residual is left out, not a NaN σ
        let mut odd = near.clone();
        odd.push(HeldOutResidual {
            held_out_m: f64::NAN,
            in_sample_m: 0.001,
            depth_m: 1.0,
        });
        let m = DepthErrorModel::fit(&[frame], &odd, 0.0).unwrap();
        assert!((m.sigma_flat_m - want).abs() < 1e-5, "{}", m.sigma_flat_m);
        let dense = m.sigma_dense_m.unwrap();
        assert!((dense - 0.002).abs() < 1e-4, "{dense}");
    }
}
