//! Training losses over valid ground-truth pixels (METHOD.md §9).

use std::fmt;
use std::str::FromStr;

use candle_core::{Result, Tensor};
use serde::{Deserialize, Serialize};

/// Which loss.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LossKind {
    /// Official Depth Anything V2 SILog: `sqrt(mean(d²) − 0.5·mean(d)²)`, `d = log gt − log pred`.
    Silog,
    /// The authors' MOMA variant: `10·sqrt(var(g) + 0.15·mean(g)²)`, `g = log pred − log gt`
    /// (population variance).
    SilogMoma,
    /// Scale-and-shift-invariant loss in disparity (relative heads): the prediction is aligned to
    /// the ground-truth disparity `1/gt` by least-squares scale and shift (solved in closed form,
    /// differentiable), then the mean absolute residual.
    Ssi,
}

impl fmt::Display for LossKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Silog => "silog",
            Self::SilogMoma => "silog-moma",
            Self::Ssi => "ssi",
        })
    }
}

impl FromStr for LossKind {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "silog" => Ok(Self::Silog),
            "silog-moma" => Ok(Self::SilogMoma),
            "ssi" => Ok(Self::Ssi),
            other => Err(format!(
                "unknown loss {other:?} (expected silog, silog-moma or ssi)"
            )),
        }
    }
}

/// Flat indices of valid pixels: ground truth finite in `[min_depth_m, max_depth_m]` and, when
/// given, `mask` non-zero.
pub fn valid_indices(
    gt_m: &[f32],
    mask: Option<&[bool]>,
    min_depth_m: f32,
    max_depth_m: f32,
) -> Vec<u32> {
    gt_m.iter()
        .enumerate()
        .filter(|&(i, &g)| {
            g.is_finite()
                && g >= min_depth_m
                && g <= max_depth_m
                && mask.is_none_or(|m| m.get(i).copied().unwrap_or(false))
        })
        .map(|(i, _)| i as u32)
        .collect()
}

/// The loss of prediction `pred` (any shape) against ground truth `gt_m` (same shape, metres) over
/// the flat pixel indices `valid` (see [`valid_indices`]). For [`LossKind::Silog`] and
/// [`LossKind::SilogMoma`] `pred` is depth (metres); for [`LossKind::Ssi`] disparity (any scale).
///
/// # Errors
/// No valid pixel; shape errors.
pub fn loss(kind: LossKind, pred: &Tensor, gt_m: &Tensor, valid: &[u32]) -> Result<Tensor> {
    if valid.is_empty() {
        candle_core::bail!("no valid ground-truth pixel for the loss");
    }
    let idx = Tensor::from_slice(valid, valid.len(), pred.device())?;
    let p = pred.flatten_all()?.index_select(&idx, 0)?;
    let g = gt_m
        .flatten_all()?
        .to_dtype(pred.dtype())?
        .index_select(&idx, 0)?;
    match kind {
        LossKind::Silog => {
            let d = (g.log()? - p.log()?)?;
            let m2 = d.sqr()?.mean_all()?;
            let m = d.mean_all()?;
            (m2 - (m.sqr()? * 0.5)?)?.sqrt()
        }
        LossKind::SilogMoma => {
            let d = (p.log()? - g.log()?)?;
            let m = d.mean_all()?;
            let var = d.broadcast_sub(&m)?.sqr()?.mean_all()?;
            (var + (m.sqr()? * 0.15)?)?.sqrt()? * 10.0
        }
        LossKind::Ssi => {
            // Closed-form least squares of s·p + t ≈ 1/g.
            let y = g.recip()?;
            let n = valid.len() as f64;
            let mp = p.mean_all()?;
            let my = y.mean_all()?;
            let pc = p.broadcast_sub(&mp)?;
            let yc = y.broadcast_sub(&my)?;
            let var_p = (pc.sqr()?.sum_all()? / n)?;
            let cov = ((&pc * &yc)?.sum_all()? / n)?;
            let s = (cov / (var_p + 1e-12)?)?;
            let fitted = pc.broadcast_mul(&s)?.broadcast_add(&my)?;
            (fitted - y)?.abs()?.mean_all()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    fn t(v: &[f64]) -> Tensor {
        Tensor::from_slice(v, v.len(), &Device::Cpu).unwrap()
    }

    fn scalar(x: Tensor) -> f64 {
        x.to_scalar::<f64>().unwrap()
    }

    #[test]
    fn silog_matches_hand_computation() {
        // gt = (1, 2, 4), pred = (2, 2, 2): d = log gt − log pred = (−ln2, 0, ln2);
        // mean d = 0, mean d² = 2·ln²2/3 → sqrt(2/3)·ln 2.
        let l = scalar(
            loss(
                LossKind::Silog,
                &t(&[2., 2., 2.]),
                &t(&[1., 2., 4.]),
                &[0, 1, 2],
            )
            .unwrap(),
        );
        let want = (2.0f64 / 3.0).sqrt() * 2f64.ln();
        assert!((l - want).abs() < 1e-12, "{l} vs {want}");
        // A global scale: d constant c: sqrt(c² − 0.5c²) = |c|/√2.
        let l = scalar(loss(LossKind::Silog, &t(&[2., 4.]), &t(&[1., 2.]), &[0, 1]).unwrap());
        assert!((l - 2f64.ln() / 2f64.sqrt()).abs() < 1e-12);
        // Only the valid pixels count (pixel 2 would be log 0 = −inf).
        let l = scalar(
            loss(
                LossKind::Silog,
                &t(&[2., 4., 0.]),
                &t(&[1., 2., 5.]),
                &[0, 1],
            )
            .unwrap(),
        );
        assert!((l - 2f64.ln() / 2f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn silog_moma_matches_hand_computation() {
        // g = log pred − log gt = (ln2, 0, −ln2) → var = 2ln²2/3, mean 0 → 10·sqrt(2/3)·ln2.
        let l = scalar(
            loss(
                LossKind::SilogMoma,
                &t(&[2., 2., 2.]),
                &t(&[1., 2., 4.]),
                &[0, 1, 2],
            )
            .unwrap(),
        );
        assert!((l - 10.0 * (2.0f64 / 3.0).sqrt() * 2f64.ln()).abs() < 1e-12);
        // Constant g = ln 2: var 0 → 10·sqrt(0.15)·ln 2.
        let l = scalar(loss(LossKind::SilogMoma, &t(&[2., 4.]), &t(&[1., 2.]), &[0, 1]).unwrap());
        assert!((l - 10.0 * 0.15f64.sqrt() * 2f64.ln()).abs() < 1e-12);
    }

    #[test]
    fn ssi_is_zero_for_an_affine_disparity_and_hand_computed_otherwise() {
        // pred = 3·(1/gt) + 2 exactly → 0.
        let gt = [1.0, 2.0, 4.0, 0.5];
        let pred: Vec<f64> = gt.iter().map(|g| 3.0 / g + 2.0).collect();
        let l = scalar(loss(LossKind::Ssi, &t(&pred), &t(&gt), &[0, 1, 2, 3]).unwrap());
        assert!(l.abs() < 1e-9, "{l}");
        // pred = (0, 1, 2), y = 1/gt = (1, 1, 2): least squares slope 0.5, fitted
        // (5/6, 4/3, 11/6); residuals (−1/6, 1/3, −1/6) → mean |r| = 2/9.
        let l = scalar(
            loss(
                LossKind::Ssi,
                &t(&[0., 1., 2.]),
                &t(&[1., 1., 0.5]),
                &[0, 1, 2],
            )
            .unwrap(),
        );
        assert!((l - 2.0 / 9.0).abs() < 1e-9, "{l}");
    }

    #[test]
    fn valid_pixels_and_errors() {
        let v = valid_indices(
            &[0.0, 0.5, 1.0, f32::NAN, 30.0, 2.0],
            Some(&[true, true, true, true, true, false]),
            0.001,
            20.0,
        );
        assert_eq!(v, vec![1, 2]);
        assert!(loss(LossKind::Silog, &t(&[1.0]), &t(&[1.0]), &[]).is_err());
        assert_eq!("silog-moma".parse::<LossKind>(), Ok(LossKind::SilogMoma));
        assert_eq!(LossKind::Ssi.to_string(), "ssi");
        assert!("l1".parse::<LossKind>().is_err());
    }
}
