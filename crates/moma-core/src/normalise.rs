//! Normalisation of a depth model's output (METHOD.md §1).
//!

use ndarray::Array2;
use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};
use crate::image::{Mask, Prediction, PredictionKind};

/// How a prediction map is normalised before alignment.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum Normalisation {
    /// Paper's exact formula: ẑ = (z − z_min)/(z_max − z_min) + z_min.
    #[default]
    Minmax,
    /// The authors' code: ẑ = (z − z_min)/(z_max − z_min).
    MinmaxUnit,
    /// Ranftl et al.: ẑ = (z − m)/μ, m = median, μ = mean |z − m|.
    Median,
    /// ẑ = z.
    None,
}

/// Normalisation settings; identical at calibration and at run time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
pub struct NormalisationConfig {
    /// The formula.
    pub method: Normalisation,
    /// For `inverse-depth` predictions: align in inverse space instead of converting to 1/d first.
    pub inverse_space: bool,
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

/// Normalises `pred` per METHOD.md §1 over its valid pixels, or over `region` when given.
///
/// Steps, in this order:
/// 1. Every value of `pred` must be finite (else [`CoreError::NonFinitePrediction`] with the count
///    and the first offending pixel in row-major order).
/// 2. For [`PredictionKind::InverseDepth`] (unless `config.inverse_space`): `z = 1/d` for `d > 0`,
///    `NaN` for `d ≤ 0` (no depth can be inferred there). Otherwise `z = d`.
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
/// let pred = Prediction::new(ndarray::array![[1.0f32, 2.0], [3.0, 5.0]], PredictionKind::Depth);
/// let cfg = NormalisationConfig { method: Normalisation::MinmaxUnit, inverse_space: false };
/// let n = normalise(&pred, &cfg, None).unwrap();
/// assert_eq!(n.values, ndarray::array![[0.0f32, 0.25], [0.5, 1.0]]);
/// ```
pub fn normalise(
    pred: &Prediction,
    config: &NormalisationConfig,
    region: Option<&Mask>,
) -> Result<NormalisedMap> {
    let size = pred.size();
    if let Some(r) = region {
        size.expect_eq("normalisation region", r.size())?;
    }
    // 1. non-finite check over the whole map (vectorised count; position only on error).
    let d_std = pred.values.as_standard_layout();
    let d: &[f32] = d_std.as_slice().unwrap_or(&[]);
    let bad = d.iter().filter(|x| !x.is_finite()).count();
    if bad > 0 {
        let first = d.iter().position(|x| !x.is_finite()).unwrap_or(0);
        let w = size.width.max(1);
        return Err(CoreError::NonFinitePrediction {
            count: bad,
            u: first % w,
            v: first / w,
        });
    }
    // 2. kind conversion.
    let invert = pred.kind == PredictionKind::InverseDepth && !config.inverse_space;
    let mut z: Vec<f32> = if invert {
        d.iter()
            .map(|&x| if x > 0.0 { 1.0 / x } else { f32::NAN })
            .collect()
    } else {
        d.to_vec()
    };
    // 3. statistics over the valid pixels of the map or region.
    let r_std = region.map(|r| r.data().as_standard_layout());
    let inside: Option<&[bool]> = r_std.as_ref().and_then(|r| r.as_slice());
    let (min, max, n) = crate::kernels::finite_min_max(&z, inside);
    if n == 0 {
        return Err(CoreError::NoValidPixels(match region {
            Some(_) => "the normalisation region holds no valid prediction pixel".into(),
            None => "the prediction holds no valid pixel".into(),
        }));
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
    let (a, b) = match config.method {
        Normalisation::Minmax | Normalisation::MinmaxUnit => {
            let range = max - min;
            if range.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) || !range.is_finite() {
                return Err(CoreError::Degenerate(format!(
                    "constant prediction: z_max = z_min = {min} over {n} pixel(s); min-max normalisation is undefined"
                )));
            }
            let offset = if config.method == Normalisation::Minmax {
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
    };
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
