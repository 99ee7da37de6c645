//! Normalisation of a depth model's output (METHOD.md §1).
//!
//! CONTRACT (implemented by the core work item): keep these names and signatures.

use ndarray::Array2;
use serde::{Deserialize, Serialize};

use crate::error::Result;
use crate::image::{Mask, Prediction};

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
/// # Errors
/// NaN/inf in the prediction, size mismatch with `region`, no valid pixel in the region,
/// degenerate statistics (z_max = z_min, μ = 0).
pub fn normalise(
    pred: &Prediction,
    config: &NormalisationConfig,
    region: Option<&Mask>,
) -> Result<NormalisedMap> {
    let _ = (pred, config, region);
    todo!("core work item")
}
