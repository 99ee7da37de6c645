//! Training losses over valid ground-truth pixels (docs/method.md §9).

use std::fmt;
use std::str::FromStr;

use candle_core::{Result, Tensor};
use serde::{Deserialize, Serialize};

use super::model::NetOutput;

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
    loss_with_log(kind, pred, None, gt_m, valid)
}

/// [`loss`] of a training forward's output: the log losses take the stably computed logarithm
/// of a metric head's depth ([`NetOutput::log_pred`]) instead of `ln pred`, which is −∞ where
/// the sigmoid underflows to 0 (the same value wherever `pred > 0`).
///
/// # Errors
/// As [`loss`].
pub fn loss_of(kind: LossKind, out: &NetOutput, gt_m: &Tensor, valid: &[u32]) -> Result<Tensor> {
    loss_with_log(kind, &out.pred, out.log_pred.as_ref(), gt_m, valid)
}

fn loss_with_log(
    kind: LossKind,
    pred: &Tensor,
    log_pred: Option<&Tensor>,
    gt_m: &Tensor,
    valid: &[u32],
) -> Result<Tensor> {
    if valid.is_empty() {
        candle_core::bail!("no valid ground-truth pixel for the loss");
    }
    let idx = Tensor::from_slice(valid, valid.len(), pred.device())?;
    let p = pred.flatten_all()?.index_select(&idx, 0)?;
    let g = gt_m
        .flatten_all()?
        .to_dtype(pred.dtype())?
        .index_select(&idx, 0)?;
    // ln pred over the valid pixels: from the logits where the network gives it.
    let log_p = || -> Result<Tensor> {
        match log_pred {
            Some(lp) => lp.flatten_all()?.index_select(&idx, 0),
            None => p.log(),
        }
    };
    match kind {
        LossKind::Silog => {
            let d = (g.log()? - log_p()?)?;
            let m2 = d.sqr()?.mean_all()?;
            let m = d.mean_all()?;
            (m2 - (m.sqr()? * 0.5)?)?.sqrt()
        }
        LossKind::SilogMoma => {
            let d = (log_p()? - g.log()?)?;
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
    use crate::candle::train::metric_output;
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

    /// A seeded uniform draw in `[lo, hi)` (splitmix64).
    fn draws(n: usize, seed: u64, lo: f64, hi: f64) -> Vec<f64> {
        let mut z = seed;
        (0..n)
            .map(|_| {
                z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
                let mut x = z;
                x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
                x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
                x ^= x >> 31;
                lo + (hi - lo) * (x >> 11) as f64 / (1u64 << 53) as f64
            })
            .collect()
    }

    /// Worst relative error of the autograd gradient of `f` at `x0` against central
    /// differences (f64, step h).
    fn fd_check(x0: &[f64], f: &dyn Fn(&Tensor) -> Tensor) -> f64 {
        let dev = Device::Cpu;
        let var = candle_core::Var::from_slice(x0, x0.len(), &dev).unwrap();
        let l = f(var.as_tensor());
        let g: Vec<f64> = l
            .backward()
            .unwrap()
            .get(var.as_tensor())
            .unwrap()
            .to_vec1()
            .unwrap();
        let h = 1e-6;
        let scale = g.iter().map(|v| v.abs()).fold(0.0, f64::max);
        assert!(scale > 0.0);
        let mut worst = 0.0f64;
        for i in 0..x0.len() {
            let at = |d: f64| {
                let mut x = x0.to_vec();
                x[i] += d;
                scalar(f(&t(&x)))
            };
            let fd = (at(h) - at(-h)) / (2.0 * h);
            worst = worst.max((fd - g[i]).abs() / scale);
        }
        worst
    }

    #[test]
    fn ssi_gradient_matches_finite_differences() {
        // Disparity predictions and depths with no exact fit (residuals away from |r| = 0,
        // where the mean absolute residual has a kink).
        let n = 40;
        let gt = draws(n, 1, 0.4, 3.0);
        let pred = draws(n, 2, 0.1, 2.5);
        let valid: Vec<u32> = (0..n as u32).collect();
        let gt_t = t(&gt);
        let worst = fd_check(&pred, &|p| loss(LossKind::Ssi, p, &gt_t, &valid).unwrap());
        assert!(
            worst < 1e-6,
            "SSI gradient vs central differences: {worst:.3e}"
        );
    }

    #[test]
    fn log_losses_from_logits_have_the_right_gradient() {
        // Metric-head logits, SILog and the MOMA variant through the log-sigmoid: gradients
        // with respect to the logits against central differences.
        let n = 30;
        let gt = draws(n, 3, 0.5, 15.0);
        let z = draws(n, 4, -4.0, 4.0);
        let valid: Vec<u32> = (0..n as u32).collect();
        let gt_t = t(&gt);
        for kind in [LossKind::Silog, LossKind::SilogMoma] {
            let f = |z: &Tensor| {
                loss_of(kind, &metric_output(z, 20.0).unwrap(), &gt_t, &valid).unwrap()
            };
            let worst = fd_check(&z, &f);
            assert!(
                worst < 1e-6,
                "{kind} gradient vs central differences: {worst:.3e}"
            );
            // The same value as the loss of the depth itself where the sigmoid is well inside
            // (0, 1).
            let depth = metric_output(&t(&z), 20.0).unwrap().pred;
            let direct = scalar(loss(kind, &depth, &gt_t, &valid).unwrap());
            assert!((scalar(f(&t(&z))) - direct).abs() < 1e-12);
        }
    }

    #[test]
    fn saturated_metric_logits_keep_the_loss_and_gradient_finite() {
        // In f32 the sigmoid of −120 is exactly 0: ln(σ·max) = −∞ and the SILog is NaN. This is
        // how the NaN of a too-high head learning rate started. From the logits it is
        // finite, with a gradient that pulls the saturated logit back up.
        let dev = Device::Cpu;
        let z = candle_core::Var::from_slice(&[-120.0f32, 0.5, 1.0, -0.5], 4, &dev).unwrap();
        let gt = Tensor::from_slice(&[2.0f32, 8.0, 9.0, 7.0], 4, &dev).unwrap();
        let valid = [0, 1, 2, 3];
        let out = metric_output(z.as_tensor(), 20.0).unwrap();
        let pred: Vec<f32> = out.pred.to_vec1().unwrap();
        assert_eq!(pred[0], 0.0, "f32 sigmoid underflows");
        let naive: f32 = loss(LossKind::Silog, &out.pred, &gt, &valid)
            .unwrap()
            .to_scalar()
            .unwrap();
        assert!(!naive.is_finite(), "the depth's log gives {naive}");
        let l = loss_of(LossKind::Silog, &out, &gt, &valid).unwrap();
        let v: f32 = l.to_scalar().unwrap();
        assert!(v.is_finite() && v > 1.0, "{v}");
        let g: Vec<f32> = l
            .backward()
            .unwrap()
            .get(z.as_tensor())
            .unwrap()
            .to_vec1()
            .unwrap();
        assert!(g.iter().all(|x| x.is_finite()), "{g:?}");
        assert!(g[0] < 0.0, "descent raises the saturated logit: {g:?}");
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
