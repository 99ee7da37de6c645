//! GSSA — global scale and shift (docs/method.md §2): `min_{s,t} Σ (z_k − (s ẑ_k + t))²`, closed form.

use serde::{Deserialize, Serialize};

use super::Sample;
use crate::error::{CoreError, Result};

/// Fewest samples GSSA needs.
pub const MIN_SAMPLES: usize = 2;

/// Relative threshold on the centred variance of ẑ below which the fit is degenerate:
/// `Σ(ẑ − ẑ̄)² ≤ DEGENERATE_REL · Σ ẑ²` (ẑ constant to ~1e-5 relative, or all zero).
pub(crate) const DEGENERATE_REL: f64 = 1e-10;

/// Fitted global scale-shift: target = scale·ẑ + shift, in the target units of the calibration's
/// space ([`crate::normalise::AlignSpace::target_unit`]): depth in metres in depth space, 1/depth
/// in 1/m in inverse space (the aligned depth is then its reciprocal).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GssaModel {
    /// Scale, target units per unit ẑ.
    pub scale: f64,
    /// Shift, target units (`shift_m` in files before version 5).
    #[serde(alias = "shift_m")]
    pub shift: f64,
}

impl GssaModel {
    /// The identity map (scale 1, shift 0).
    pub const IDENTITY: Self = Self {
        scale: 1.0,
        shift: 0.0,
    };

    /// The target (metres in depth space, 1/m in inverse space) for a normalised value ẑ:
    /// `scale·ẑ + shift`.
    #[inline]
    pub fn predict(&self, pred: f64) -> f64 {
        self.scale * pred + self.shift
    }
}

/// Closed-form least squares with centred sums (f64):
/// `s = Σ(ẑ−ẑ̄)(z−z̄) / Σ(ẑ−ẑ̄)²`, `t = z̄ − s ẑ̄`.
///
/// Samples are assumed validated (finite); callers go through [`super::Method::fit`].
///
/// # Errors
/// [`CoreError::TooFewSamples`] below 2 samples; [`CoreError::Degenerate`] when ẑ is constant.
pub fn fit(samples: &[Sample]) -> Result<GssaModel> {
    fit_with(samples, None)
}

/// Weighted least squares `min Σ w_k (z_k − (s ẑ_k + t))²` (weighted centred sums; weights
/// ≥ 0, one per sample, e.g. the IRLS weights of [`super::robust`]). Unit weights give exactly
/// [`fit`].
///
/// # Errors
/// As [`fit`] (counting samples of positive weight; constant ẑ over them is degenerate), and
/// [`CoreError::InvalidParameter`] when `weights` has another length than `samples` or holds a
/// negative or non-finite weight.
pub fn fit_weighted(samples: &[Sample], weights: &[f64]) -> Result<GssaModel> {
    super::check_weights(samples.len(), weights)?;
    fit_with(samples, Some(weights))
}

fn fit_with(samples: &[Sample], weights: Option<&[f64]>) -> Result<GssaModel> {
    let w = |k: usize| weights.map_or(1.0, |w| w[k]);
    let n = (0..samples.len()).filter(|&k| w(k) > 0.0).count();
    if n < MIN_SAMPLES {
        return Err(CoreError::TooFewSamples {
            method: "gssa",
            got: n,
            need: MIN_SAMPLES,
        });
    }
    let (sw, sx, sy) = samples
        .iter()
        .enumerate()
        .fold((0.0, 0.0, 0.0), |(a, b, c), (k, s)| {
            let wk = w(k);
            (a + wk, b + wk * s.pred, c + wk * s.target)
        });
    let (mx, my) = (sx / sw, sy / sw);
    let (mut sxx, mut sxy, mut sxx_raw) = (0.0, 0.0, 0.0);
    for (k, s) in samples.iter().enumerate() {
        let wk = w(k);
        let dx = s.pred - mx;
        sxx += wk * dx * dx;
        sxy += wk * dx * (s.target - my);
        sxx_raw += wk * s.pred * s.pred;
    }
    if sxx.is_nan() || sxx <= DEGENERATE_REL * sxx_raw {
        return Err(CoreError::Degenerate(format!(
            "normalised prediction is constant (ẑ = {mx}) over the {n} samples; scale is undetermined"
        )));
    }
    let scale = sxy / sxx;
    Ok(GssaModel {
        scale,
        shift: my - scale * mx,
    })
}
