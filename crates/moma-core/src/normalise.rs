//! Normalisation of a depth model's output (docs/method.md §1).
//!

use ndarray::{Array2, ArrayView2};
use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};
use crate::image::{Mask, Prediction, PredictionKind};

/// How a prediction map is normalised before alignment.
///
/// No `Default`: the default depends on the prediction's kind
/// ([`crate::policy::default_normalisation`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Normalisation {
    /// Paper's exact formula: ẑ = (z − z_min)/(z_max − z_min) + z_min.
    Minmax,
    /// The authors' code: ẑ = (z − z_min)/(z_max − z_min).
    MinmaxUnit,
    /// Ranftl et al.: ẑ = (z − m)/μ, m = median, μ = mean |z − m|.
    Median,
    /// ẑ = z.
    None,
}

impl Normalisation {
    /// Every normalisation, in documentation order.
    pub const ALL: [Normalisation; 4] = [
        Normalisation::Minmax,
        Normalisation::MinmaxUnit,
        Normalisation::Median,
        Normalisation::None,
    ];

    /// The command-line and file name (`minmax`, `minmax-unit`, `median`, `none`).
    pub const fn name(self) -> &'static str {
        match self {
            Self::Minmax => "minmax",
            Self::MinmaxUnit => "minmax-unit",
            Self::Median => "median",
            Self::None => "none",
        }
    }
}

impl std::fmt::Display for Normalisation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Normalisation {
    type Err = CoreError;
    fn from_str(s: &str) -> Result<Self> {
        crate::names::parse(s, &Self::ALL, Self::name, "normalisation")
    }
}

/// The space in which a prediction is normalised and aligned (docs/method.md §1, "Alignment space").
///
/// - [`AlignSpace::Depth`]: the predictor is depth (an inverse-depth prediction d becomes 1/d,
///   invalid where d ≤ 0), the fit's target is the ground-truth depth z (metres) and its output is
///   metric depth directly.
/// - [`AlignSpace::Inverse`]: the predictor is disparity (a depth prediction z becomes 1/z), the
///   fit's target is 1/z (1/m) and the output is the reciprocal of the fitted value (invalid, NaN,
///   where the fitted disparity is ≤ 0). This is the only space in which the unknown *shift* of a
///   relative model's disparity (d ≈ a/z + b) can be undone.
///
/// Default: the prediction's own space ([`AlignSpace::native`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AlignSpace {
    /// Fit depth on depth.
    Depth,
    /// Fit inverse depth on disparity.
    Inverse,
}

impl AlignSpace {
    /// Both spaces.
    pub const ALL: [AlignSpace; 2] = [AlignSpace::Depth, AlignSpace::Inverse];

    /// The prediction's own space: disparity (`relative-disparity`) aligns in inverse space, the
    /// two depth kinds in depth space.
    pub const fn native(kind: PredictionKind) -> Self {
        if kind.is_disparity() {
            Self::Inverse
        } else {
            Self::Depth
        }
    }

    /// The command-line and file name (`depth`, `inverse`).
    pub const fn name(self) -> &'static str {
        match self {
            Self::Depth => "depth",
            Self::Inverse => "inverse",
        }
    }

    /// The unit of the fit's target, and so of every fitted parameter and target-space error:
    /// `m` in depth space, `1/m` in inverse space.
    pub const fn target_unit(self) -> &'static str {
        match self {
            Self::Depth => "m",
            Self::Inverse => "1/m",
        }
    }

    /// The fit's target for a ground-truth depth `z_m` (metres): z, or 1/z in inverse space.
    #[inline]
    pub fn target_from_depth(self, z_m: f64) -> f64 {
        match self {
            Self::Depth => z_m,
            Self::Inverse => 1.0 / z_m,
        }
    }

    /// Metric depth (metres) from a fitted value: itself, or its reciprocal in inverse space
    /// (NaN unless the reciprocal of the fitted disparity is positive and finite).
    #[inline]
    pub fn depth_from_target(self, t: f64) -> f64 {
        match self {
            Self::Depth => t,
            Self::Inverse => {
                let z = 1.0 / t;
                if z > 0.0 && z.is_finite() {
                    z
                } else {
                    f64::NAN
                }
            }
        }
    }
}

impl std::fmt::Display for AlignSpace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for AlignSpace {
    type Err = CoreError;
    fn from_str(s: &str) -> Result<Self> {
        crate::names::parse(s, &Self::ALL, Self::name, "alignment space")
    }
}

/// Normalisation settings; identical at calibration and at run time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NormalisationConfig {
    /// The formula.
    pub method: Normalisation,
    /// The space the prediction is converted to before normalising (and aligned in).
    pub space: AlignSpace,
}

impl NormalisationConfig {
    /// `method` in the native space of predictions of `kind`.
    pub const fn native(method: Normalisation, kind: PredictionKind) -> Self {
        Self {
            method,
            space: AlignSpace::native(kind),
        }
    }
}

/// Statistics the normalisation used (over the valid pixels of the map or the region).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NormStats {
    /// Smallest valid value (after the inverse-depth conversion, if any).
    pub min: f64,
    /// Largest valid value.
    pub max: f64,
    /// Median (computed for `median`, else NaN).
    pub median: f64,
    /// Mean absolute deviation from the median (computed for `median`, else NaN).
    pub mad: f64,
    /// Number of pixels the statistics were computed over.
    pub n: usize,
}

/// A normalised prediction map, the input of every alignment method. Unitless.
#[derive(Debug, Clone, PartialEq)]
pub struct NormalisedMap {
    /// `(height, width)` normalised values ẑ; `NaN` where the prediction was unusable (e.g. d ≤ 0 for inverse depth).
    pub values: Array2<f32>,
    /// What was used to normalise.
    pub stats: NormStats,
}

/// Normalises `pred` per docs/method.md §1 over its valid pixels, or over `region` when given.
///
/// Steps, in this order:
/// 1. Every value of `pred` must be finite (else [`CoreError::NonFinitePrediction`] with the count
///    and the first offending pixel in row-major order).
/// 2. Conversion to `config.space`: an inverse-depth prediction in depth space, or a depth
///    prediction in inverse space, becomes `z = 1/d` for `d > 0` and `NaN` for `d ≤ 0` (nothing
///    can be inferred there). Otherwise `z = d`.
/// 3. Statistics over the *valid* pixels (finite `z`) of the whole map, or of `region` only:
///    `z_min`, `z_max`, `n`, and for `median` also `m` = median (mean of the two middle values for
///    even `n`, found in O(n) with `select_nth_unstable`) and `μ = mean |z − m|`.
/// 4. Every pixel of the map (inside the region or not) is mapped with the formula:
///    - `minmax` (paper): `ẑ = (z − z_min)/(z_max − z_min) + z_min`,
///    - `minmax-unit` (authors' code): `ẑ = (z − z_min)/(z_max − z_min)`,
///    - `median`: `ẑ = (z − m)/μ`,
///    - `none`: `ẑ = z`.
///
/// `NaN` pixels (from step 2) stay `NaN`. Values are unitless (the input's units cancel for the
/// min-max and median forms; `minmax`'s `+ z_min` keeps the input's unit offset, as the paper does).
///
/// # Errors
/// - [`CoreError::NonFinitePrediction`]: NaN/inf in the prediction;
/// - [`CoreError::SizeMismatch`]: `region` and `pred` differ in size;
/// - [`CoreError::NoValidPixels`]: no valid pixel in the map / region;
/// - [`CoreError::Degenerate`]: `z_max = z_min` (min-max forms) or `μ = 0` (median).
///
/// # Example
/// ```
/// use moma_core::normalise::{normalise, Normalisation, NormalisationConfig};
/// use moma_core::{Prediction, PredictionKind};
/// let pred = Prediction::new(ndarray::array![[1.0f32, 2.0], [3.0, 5.0]], PredictionKind::MetricDepth);
/// let cfg = NormalisationConfig::native(Normalisation::MinmaxUnit, PredictionKind::MetricDepth);
/// let n = normalise(&pred, &cfg, None).unwrap();
/// assert_eq!(n.values, ndarray::array![[0.0f32, 0.25], [0.5, 1.0]]);
/// ```
pub fn normalise(
    pred: &Prediction,
    config: &NormalisationConfig,
    region: Option<&Mask>,
) -> Result<NormalisedMap> {
    normalise_view(pred.values.view(), pred.kind, config, region)
}

/// [`normalise`] reading the prediction through a view (`values` of kind `kind`, any strides):
/// no copy of the input is made (a non-row-major view is read through one standard-layout copy).
///
/// # Errors
/// As [`normalise`].
pub fn normalise_view(
    values: ArrayView2<'_, f32>,
    kind: PredictionKind,
    config: &NormalisationConfig,
    region: Option<&Mask>,
) -> Result<NormalisedMap> {
    let size = crate::image::ImageSize::of(&values);
    if let Some(r) = region {
        size.expect_eq("normalisation region", r.size())?;
    }
    // 1. non-finite check over the whole map (vectorised count; position only on error).
    let d_std = values.as_standard_layout();
    let d: &[f32] = d_std.as_slice().unwrap_or(&[]);
    let bad = d.iter().filter(|x| !x.is_finite()).count();
    if bad > 0 {
        let first = d.iter().position(|x| !x.is_finite()).unwrap_or(0);
        let w = size.width.max(1);
        return Err(CoreError::NonFinitePrediction {
            count: bad,
            u: first % w,
            v: first / w,
            metric_depth: kind == PredictionKind::MetricDepth,
        });
    }
    // 2. kind conversion.
    let seen = Seen::of(kind, config);
    let mut z: Vec<f32> = d.iter().map(|&x| seen.value(x)).collect();
    // 3. statistics over the valid pixels of the map or region.
    let r_std = region.map(|r| r.data().as_standard_layout());
    let inside: Option<&[bool]> = r_std.as_ref().and_then(|r| r.as_slice());
    let (min, max, n) = crate::kernels::finite_min_max(&z, inside);
    if n == 0 {
        return Err(no_valid_pixels(region.is_some()));
    }
    let (median, mad) = if config.method == Normalisation::Median {
        let mut vals: Vec<f32> = match inside {
            Some(m) => z
                .iter()
                .zip(m)
                .filter(|(x, i)| **i && x.is_finite())
                .map(|(x, _)| *x)
                .collect(),
            None => z.iter().copied().filter(|x| x.is_finite()).collect(),
        };
        median_mad(&mut vals)
    } else {
        (f64::NAN, f64::NAN)
    };
    let stats = NormStats {
        min,
        max,
        median,
        mad,
        n,
    };
    // 4. the affine map ẑ = a·z + b.
    let (a, b) = affine_coefficients(config.method, &stats)?;
    if config.method != Normalisation::None {
        crate::kernels::affine_f64(&mut z, a, b);
    }
    let values = Array2::from_shape_vec(size.shape(), z).map_err(|_| CoreError::BufferLength {
        len: d.len(),
        size,
        expected: size.pixels(),
    })?;
    Ok(NormalisedMap { values, stats })
}

/// What the normalisation sees of a prediction's value: its inverse where the calibration's
/// space is not the prediction's own, NaN (no value) where that is undefined (x ≤ 0) and where a
/// metric depth is at or behind the camera (a model's or a file's placeholder for "none":
/// neither a calibration sample nor an output pixel), NaN for a non-finite value.
#[derive(Debug, Clone, Copy)]
struct Seen {
    invert: bool,
    metric: bool,
}

impl Seen {
    fn of(kind: PredictionKind, config: &NormalisationConfig) -> Self {
        Self {
            invert: AlignSpace::native(kind) != config.space,
            metric: kind == PredictionKind::MetricDepth,
        }
    }

    #[inline]
    fn value(self, x: f32) -> f32 {
        if !x.is_finite() || ((self.invert || self.metric) && x <= 0.0) {
            f32::NAN
        } else if self.invert {
            1.0 / x
        } else {
            x
        }
    }
}

/// A note when a min-max normalisation hangs on a few isolated pixels: the map's minimum or
/// maximum (of the values the normalisation sees: the prediction in the calibration's space,
/// inside `region`) lies beyond the rest by more than [`ISOLATED_GAP`] times the spread of its
/// 0.5–99.5 % quantiles. One glitched pixel of a prediction (a reviewer's −1 in a disparity
/// map) then moves the whole aligned frame by centimetres to metres, with no error; so does a
/// small far region that comes and goes between frames. `None` for the other normalisations,
/// and when nothing is isolated. Quantiles from an even stride of about 20 000 pixels, the
/// extremes and the count exact (one more pass over the image).
pub fn isolated_extremes(
    values: ArrayView2<'_, f32>,
    kind: PredictionKind,
    config: &NormalisationConfig,
    region: Option<&Mask>,
) -> Option<String> {
    if !matches!(
        config.method,
        Normalisation::Minmax | Normalisation::MinmaxUnit
    ) {
        return None;
    }
    let seen = Seen::of(kind, config);
    let invert = seen.invert;
    let w = values.ncols().max(1);
    // row-major slices (a copy only for a non-standard layout), read pixel by pixel
    let v_std = values.as_standard_layout();
    let r_std = region.map(|r| r.data().as_standard_layout());
    let (Some(vals), inside) = (v_std.as_slice(), r_std.as_ref().map(|r| r.as_slice())) else {
        return None;
    };
    let inside: Option<&[bool]> = match inside {
        Some(Some(m)) => Some(m),
        Some(None) => return None,
        None => None,
    };
    let pixel = |i: usize| -> Option<(usize, f32, f32)> {
        if inside.is_some_and(|m| !m[i]) {
            return None;
        }
        let z = seen.value(vals[i]);
        (!z.is_nan()).then_some((i, vals[i], z))
    };
    // the quantiles from an even stride of about 20 000 pixels of the image
    let stride = (vals.len() / 20_000).max(1);
    let mut sample: Vec<f32> = (0..vals.len())
        .step_by(stride)
        .filter_map(|i| pixel(i).map(|(_, _, z)| z))
        .collect();
    if sample.len() < 1000 {
        return None; // too few pixels for a tail to say anything
    }
    let m = sample.len() - 1;
    let lo = *sample.select_nth_unstable_by(m / 200, f32::total_cmp).1;
    let hi = *sample.select_nth_unstable_by(m - m / 200, f32::total_cmp).1;
    let spread = hi - lo;
    if spread.is_nan() || spread <= 0.0 {
        return None;
    }
    let (low, high) = (lo - ISOLATED_GAP * spread, hi + ISOLATED_GAP * spread);
    let (mut n_low, mut n_high) = (0usize, 0usize);
    let (mut min, mut max) = (
        (f32::INFINITY, 0usize, 0.0f32),
        (f32::NEG_INFINITY, 0usize, 0.0f32),
    );
    // one pass: without a conversion, a value within both bounds is neither extreme
    for (i, &x) in vals.iter().enumerate() {
        if !(invert || x < low || x > high) {
            continue;
        }
        let Some((i, x, z)) = pixel(i) else {
            continue;
        };
        if z < low {
            n_low += 1;
            if z < min.0 {
                min = (z, i, x);
            }
        } else if z > high {
            n_high += 1;
            if z > max.0 {
                max = (z, i, x);
            }
        }
    }
    // in the prediction's own values (inverted: the lowest seen is the highest given)
    let name = |pixels: usize, (_, i, x): (f32, usize, f32), seen_low: bool| {
        format!(
            "{pixels} pixel(s) of the prediction lie far {} the rest of its values (the most \
             extreme {x} at pixel (u={}, v={}))",
            if seen_low != invert { "below" } else { "above" },
            i % w,
            i / w
        )
    };
    let mut parts = Vec::new();
    if n_low > 0 {
        parts.push(name(n_low, min, true));
    }
    if n_high > 0 {
        parts.push(name(n_high, max, false));
    }
    (!parts.is_empty()).then(|| {
        format!(
            "{}: the min-max normalisation follows them, and moves the whole aligned map with \
             them; a glitch, or a region that comes and goes between frames, misaligns the \
             frame (fix the prediction, or calibrate again with a workspace mask that leaves \
             them out: --workspace, Python workspace=)",
            parts.join("; ")
        )
    })
}

/// How far beyond the spread of its 0.5–99.5 % quantiles a map's extreme must lie to be
/// isolated ([`isolated_extremes`]).
pub const ISOLATED_GAP: f32 = 0.5;

/// The error for a map or region without a valid pixel.
pub(crate) fn no_valid_pixels(in_region: bool) -> CoreError {
    CoreError::NoValidPixels(if in_region {
        "the normalisation region holds no valid prediction pixel".into()
    } else {
        "the prediction holds no valid pixel".into()
    })
}

/// The affine map `ẑ = a·z + b` of `method` for the statistics `stats` (min, max, n; median and
/// mad for `median`).
///
/// # Errors
/// [`CoreError::Degenerate`]: `z_max = z_min` (min-max forms) or `μ = 0` (median).
pub(crate) fn affine_coefficients(method: Normalisation, stats: &NormStats) -> Result<(f64, f64)> {
    let NormStats {
        min,
        max,
        median,
        mad,
        n,
    } = *stats;
    Ok(match method {
        Normalisation::Minmax | Normalisation::MinmaxUnit => {
            let range = max - min;
            if range.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) || !range.is_finite() {
                return Err(CoreError::Degenerate(format!(
                    "constant prediction: z_max = z_min = {min} over {n} pixel(s); min-max normalisation is undefined"
                )));
            }
            let offset = if method == Normalisation::Minmax {
                min
            } else {
                0.0
            };
            (1.0 / range, offset - min / range)
        }
        Normalisation::Median => {
            if mad.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) || !mad.is_finite() {
                return Err(CoreError::Degenerate(format!(
                    "mean absolute deviation from the median ({median}) is 0 over {n} pixel(s); median normalisation is undefined"
                )));
            }
            (1.0 / mad, -median / mad)
        }
        Normalisation::None => (1.0, 0.0),
    })
}

/// Median (mean of the two middle values for even length) and mean absolute deviation from it,
/// in O(n) expected time. `vals` is reordered. Requires `vals` non-empty and NaN-free.
fn median_mad(vals: &mut [f32]) -> (f64, f64) {
    let n = vals.len();
    let mid = n / 2;
    let (lower, &mut upper_mid, _) = vals.select_nth_unstable_by(mid, f32::total_cmp);
    let median = if n % 2 == 1 {
        f64::from(upper_mid)
    } else {
        // the largest value of the lower half is the other middle value
        let lower_mid = lower.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        0.5 * (f64::from(lower_mid) + f64::from(upper_mid))
    };
    let sum: f64 = vals.iter().map(|&x| (f64::from(x) - median).abs()).sum();
    (median, sum / n as f64)
}
