//! Depth metrics (docs/method.md §3): δ1.05, δ1.10, δ1.25, REL, RMSE, MAE.
//!

use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};
use crate::image::{Mask, MetricDepth};

/// Metrics of one image (or pooled over several), over pixels inside the mask where ground truth
/// is valid and the prediction is finite.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DepthMetrics {
    /// Fraction with max(p/g, g/p) < 1.05.
    pub d105: f64,
    /// Fraction with max(p/g, g/p) < 1.10.
    pub d110: f64,
    /// Fraction with max(p/g, g/p) < 1.25.
    pub d125: f64,
    /// mean |p − g| / g.
    pub rel: f64,
    /// sqrt(mean (p − g)²), metres.
    pub rmse: f64,
    /// mean |p − g|, metres.
    pub mae: f64,
    /// Pixels counted.
    pub n: usize,
}

impl DepthMetrics {
    /// Metrics of `pred` against `gt` inside `mask` (whole image when `None`).
    ///
    /// Pixels counted: inside the mask, ground truth valid (finite, > 0 m) and prediction finite.
    /// A finite prediction `p ≤ 0` is counted (it is a wrong answer, not a missing one): it enters
    /// REL, RMSE and MAE with its value and fails every δ threshold. With `g` the ground truth:
    /// - `δ_t` = fraction with `max(p/g, g/p) < t`, evaluated as `p < t·g ∧ g < t·p`;
    /// - `REL = mean |p − g|/g`, `RMSE = sqrt(mean (p − g)²)` (m), `MAE = mean |p − g|` (m).
    ///
    /// Single pass; per-pixel work in f32, row sums accumulated in f64.
    ///
    /// # Errors
    /// Size mismatch; no pixel to score ([`CoreError::NoValidPixels`], never silently NaN).
    ///
    /// # Example
    /// ```
    /// use moma_core::{metrics::DepthMetrics, MetricDepth};
    /// let gt = MetricDepth::new(ndarray::array![[1.0f32, 2.0]]);
    /// let pred = MetricDepth::new(ndarray::array![[1.02f32, 2.4]]);
    /// let m = DepthMetrics::compute(&pred, &gt, None).unwrap();
    /// assert_eq!((m.n, m.d105, m.d125), (2, 0.5, 1.0));
    /// assert!((m.mae - 0.21).abs() < 1e-6);
    /// ```
    pub fn compute(pred: &MetricDepth, gt: &MetricDepth, mask: Option<&Mask>) -> Result<Self> {
        let size = gt.size();
        size.expect_eq("prediction", pred.size())?;
        if let Some(m) = mask {
            size.expect_eq("evaluation mask", m.size())?;
        }
        let w = size.width;
        let p_std = pred.depth_m.as_standard_layout();
        let g_std = gt.depth_m.as_standard_layout();
        let (ps, gs) = match (p_std.as_slice(), g_std.as_slice()) {
            (Some(p), Some(g)) => (p, g),
            _ => {
                return Err(CoreError::InvalidParameter(
                    "depth maps must be contiguous".into(),
                ));
            }
        };
        let m_std = mask.map(|m| m.data().as_standard_layout());
        let ms: Option<&[bool]> = m_std.as_ref().and_then(|m| m.as_slice());
        let mut acc = Sums::default();
        if w > 0 {
            for v in 0..size.height {
                let range = v * w..(v + 1) * w;
                let row = row_sums(
                    &ps[range.clone()],
                    &gs[range.clone()],
                    ms.map(|m| &m[range]),
                );
                acc.add(&row);
            }
        }
        acc.finish().ok_or_else(|| {
            CoreError::NoValidPixels(format!(
                "no pixel to score: {} no pixel with valid ground truth and a finite prediction",
                if mask.is_some() {
                    "the mask holds"
                } else {
                    "there is"
                }
            ))
        })
    }

    /// Mean over images of each metric (each image weighs the same; `n` is the total pixel count).
    ///
    /// # Errors
    /// [`CoreError::NoValidPixels`] for an empty list.
    pub fn mean(per_image: &[DepthMetrics]) -> Result<Self> {
        if per_image.is_empty() {
            return Err(CoreError::NoValidPixels(
                "no image to average metrics over".into(),
            ));
        }
        let k = per_image.len() as f64;
        let avg = |f: fn(&DepthMetrics) -> f64| per_image.iter().map(f).sum::<f64>() / k;
        Ok(Self {
            d105: avg(|m| m.d105),
            d110: avg(|m| m.d110),
            d125: avg(|m| m.d125),
            rel: avg(|m| m.rel),
            rmse: avg(|m| m.rmse),
            mae: avg(|m| m.mae),
            n: per_image.iter().map(|m| m.n).sum(),
        })
    }

    /// Pixel-pooled metrics: as if all pixels of all images were one image (each image weighted by
    /// its `n`; RMSE pools squared errors).
    ///
    /// # Errors
    /// [`CoreError::NoValidPixels`] for an empty list or zero pixels in total.
    pub fn pooled(per_image: &[DepthMetrics]) -> Result<Self> {
        let n: usize = per_image.iter().map(|m| m.n).sum();
        if n == 0 {
            return Err(CoreError::NoValidPixels(
                "no pixel to pool metrics over".into(),
            ));
        }
        let nf = n as f64;
        let wavg = |f: fn(&DepthMetrics) -> f64| {
            per_image.iter().map(|m| f(m) * m.n as f64).sum::<f64>() / nf
        };
        Ok(Self {
            d105: wavg(|m| m.d105),
            d110: wavg(|m| m.d110),
            d125: wavg(|m| m.d125),
            rel: wavg(|m| m.rel),
            rmse: wavg(|m| m.rmse * m.rmse).sqrt(),
            mae: wavg(|m| m.mae),
            n,
        })
    }
}

/// Per-image metrics plus their image mean and pixel-pooled summary.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MetricsAggregator {
    /// Metrics of each image, in the order added.
    pub per_image: Vec<DepthMetrics>,
}

impl MetricsAggregator {
    /// An empty aggregator.
    pub fn new() -> Self {
        Self::default()
    }
    /// Adds one image's metrics.
    pub fn push(&mut self, m: DepthMetrics) {
        self.per_image.push(m);
    }
    /// Number of images added.
    pub fn len(&self) -> usize {
        self.per_image.len()
    }
    /// `true` when no image was added.
    pub fn is_empty(&self) -> bool {
        self.per_image.is_empty()
    }
    /// Mean over images ([`DepthMetrics::mean`]).
    ///
    /// # Errors
    /// No image added.
    pub fn mean(&self) -> Result<DepthMetrics> {
        DepthMetrics::mean(&self.per_image)
    }
    /// Pixel-pooled ([`DepthMetrics::pooled`]).
    ///
    /// # Errors
    /// No pixel in total.
    pub fn pooled(&self) -> Result<DepthMetrics> {
        DepthMetrics::pooled(&self.per_image)
    }
}

/// Raw sums of one row or image.
#[derive(Debug, Default, Clone, Copy)]
struct Sums {
    n: f64,
    c105: f64,
    c110: f64,
    c125: f64,
    rel: f64,
    sq: f64,
    abs: f64,
}

impl Sums {
    /// From per-pixel totals in the kernels' order: n, δ1.05, δ1.10, δ1.25, rel, squared, absolute.
    fn from_totals(tot: [f64; 7]) -> Self {
        let [n, c105, c110, c125, rel, sq, abs] = tot;
        Self {
            n,
            c105,
            c110,
            c125,
            rel,
            sq,
            abs,
        }
    }

    fn add(&mut self, o: &Sums) {
        self.n += o.n;
        self.c105 += o.c105;
        self.c110 += o.c110;
        self.c125 += o.c125;
        self.rel += o.rel;
        self.sq += o.sq;
        self.abs += o.abs;
    }
    fn finish(&self) -> Option<DepthMetrics> {
        if self.n < 0.5 {
            return None;
        }
        let n = self.n;
        Some(DepthMetrics {
            d105: self.c105 / n,
            d110: self.c110 / n,
            d125: self.c125 / n,
            rel: self.rel / n,
            rmse: (self.sq / n).sqrt(),
            mae: self.abs / n,
            n: n.round() as usize,
        })
    }
}

/// Per-pixel contributions `(counted, δ1.05, δ1.10, δ1.25, rel, sq, abs)`, zero when not counted.
/// Branch-free (selects only) so that the lane loops below vectorise.
#[inline(always)]
fn pixel(p: f32, g: f32, inside: bool) -> [f32; 7] {
    // g > 0 ∧ g < ∞ excludes NaN; |p| < ∞ excludes NaN and ±∞
    let ok = inside & (g > 0.0) & (g < f32::INFINITY) & (p.abs() < f32::INFINITY);
    let (p, g) = if ok { (p, g) } else { (1.0, 1.0) };
    let one = if ok { 1.0f32 } else { 0.0 };
    let d = p - g;
    let ad = d.abs();
    let ind = |t: f32| if (p < t * g) & (g < t * p) { one } else { 0.0 };
    [
        one,
        ind(1.05),
        ind(1.10),
        ind(1.25),
        one * ad / g,
        one * d * d,
        one * ad,
    ]
}

/// Lanes of the metric accumulators: float sums are only vectorised when written lane-parallel.
const LANES: usize = 8;

#[allow(clippy::needless_range_loop)] // explicit lanes vectorise
#[inline(always)]
fn lane_sums(n: usize, mut px: impl FnMut(usize) -> [f32; 7]) -> Sums {
    let mut acc = [[0.0f32; LANES]; 7];
    let full = n / LANES * LANES;
    let mut j0 = 0;
    while j0 < full {
        for l in 0..LANES {
            let c = px(j0 + l);
            for m in 0..7 {
                acc[m][l] += c[m];
            }
        }
        j0 += LANES;
    }
    let mut tot = [0.0f64; 7];
    for j in full..n {
        let c = px(j);
        for m in 0..7 {
            tot[m] += f64::from(c[m]);
        }
    }
    for m in 0..7 {
        tot[m] += acc[m].iter().map(|&x| f64::from(x)).sum::<f64>();
    }
    Sums::from_totals(tot)
}

/// Sums of one row (`mask` = `None`: every pixel inside). AVX2 intrinsics when available (float
/// reductions are not auto-vectorised: the compiler may not reorder float additions), else the
/// portable lane loop.
fn row_sums(p: &[f32], g: &[f32], mask: Option<&[bool]>) -> Sums {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 was just detected.
        return unsafe { avx2::row_sums(p, g, mask) };
    }
    let n = p.len().min(g.len());
    match mask {
        Some(m) => {
            let n = n.min(m.len());
            lane_sums(n, |j| pixel(p[j], g[j], m[j]))
        }
        None => lane_sums(n, |j| pixel(p[j], g[j], true)),
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{Sums, pixel};
    use std::arch::x86_64::*;

    /// AVX2 version of [`super::row_sums`]: 8 pixels per step, masks by bitwise AND (an invalid
    /// pixel's NaN/inf terms become +0), f32 lane sums per row, f64 totals.
    #[target_feature(enable = "avx2")]
    pub(super) fn row_sums(p: &[f32], g: &[f32], mask: Option<&[bool]>) -> Sums {
        let n = match mask {
            Some(m) => p.len().min(g.len()).min(m.len()),
            None => p.len().min(g.len()),
        };
        let full = n / 8 * 8;
        let zero = _mm256_setzero_ps();
        let one = _mm256_set1_ps(1.0);
        let inf = _mm256_set1_ps(f32::INFINITY);
        let abs_mask = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
        let t = [
            _mm256_set1_ps(1.05),
            _mm256_set1_ps(1.10),
            _mm256_set1_ps(1.25),
        ];
        let mut acc = [zero; 7];
        let mut j = 0;
        while j < full {
            // SAFETY: j + 8 ≤ full ≤ len of p, g (and mask); unaligned loads.
            let (pv, gv) = unsafe {
                (
                    _mm256_loadu_ps(p.as_ptr().add(j)),
                    _mm256_loadu_ps(g.as_ptr().add(j)),
                )
            };
            let mut ok = _mm256_and_ps(
                _mm256_and_ps(
                    _mm256_cmp_ps::<_CMP_GT_OQ>(gv, zero),
                    _mm256_cmp_ps::<_CMP_LT_OQ>(gv, inf),
                ),
                _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_and_ps(pv, abs_mask), inf),
            );
            if let Some(m) = mask {
                // SAFETY: 8 bytes at j are inside `m`; bool is one byte, 0 or 1.
                let bytes = unsafe { _mm_loadl_epi64(m.as_ptr().add(j).cast()) };
                let lanes = _mm256_cvtepu8_epi32(bytes);
                ok = _mm256_and_ps(
                    ok,
                    _mm256_castsi256_ps(_mm256_cmpgt_epi32(lanes, _mm256_setzero_si256())),
                );
            }
            let d = _mm256_sub_ps(pv, gv);
            let ad = _mm256_and_ps(d, abs_mask);
            acc[0] = _mm256_add_ps(acc[0], _mm256_and_ps(ok, one));
            for k in 0..3 {
                let inside = _mm256_and_ps(
                    _mm256_cmp_ps::<_CMP_LT_OQ>(pv, _mm256_mul_ps(t[k], gv)),
                    _mm256_cmp_ps::<_CMP_LT_OQ>(gv, _mm256_mul_ps(t[k], pv)),
                );
                acc[1 + k] =
                    _mm256_add_ps(acc[1 + k], _mm256_and_ps(_mm256_and_ps(ok, inside), one));
            }
            acc[4] = _mm256_add_ps(acc[4], _mm256_and_ps(ok, _mm256_div_ps(ad, gv)));
            acc[5] = _mm256_add_ps(acc[5], _mm256_and_ps(ok, _mm256_mul_ps(d, d)));
            acc[6] = _mm256_add_ps(acc[6], _mm256_and_ps(ok, ad));
            j += 8;
        }
        let mut tot = [0.0f64; 7];
        for (m, a) in acc.iter().enumerate() {
            let mut lanes = [0.0f32; 8];
            // SAFETY: `lanes` holds 8 f32.
            unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), *a) };
            tot[m] = lanes.iter().map(|&x| f64::from(x)).sum();
        }
        for j in full..n {
            let c = pixel(p[j], g[j], mask.is_none_or(|m| m[j]));
            for m in 0..7 {
                tot[m] += f64::from(c[m]);
            }
        }
        Sums::from_totals(tot)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The portable lane loop and the AVX2 kernel agree (the integration tests only exercise
    /// whichever path the test machine selects).
    #[test]
    fn portable_and_simd_row_sums_agree() {
        let n = 203; // not a multiple of 8
        let specials = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 0.0, -0.5];
        let p: Vec<f32> = (0..n)
            .map(|j| {
                if j % 17 == 3 {
                    specials[j % 5]
                } else {
                    0.5 + (j * 37 % 101) as f32 * 0.01
                }
            })
            .collect();
        let g: Vec<f32> = (0..n)
            .map(|j| {
                if j % 13 == 5 {
                    specials[(j + 2) % 5]
                } else {
                    0.5 + (j * 53 % 97) as f32 * 0.01
                }
            })
            .collect();
        let m: Vec<bool> = (0..n).map(|j| j % 7 != 0).collect();
        for mask in [None, Some(m.as_slice())] {
            let portable = match mask {
                Some(m) => lane_sums(n, |j| pixel(p[j], g[j], m[j])),
                None => lane_sums(n, |j| pixel(p[j], g[j], true)),
            };
            let fast = row_sums(&p, &g, mask);
            let (a, b) = (portable.finish().unwrap(), fast.finish().unwrap());
            assert_eq!((a.n, a.d105, a.d110, a.d125), (b.n, b.d105, b.d110, b.d125));
            assert!(
                (a.rel - b.rel).abs() < 1e-6
                    && (a.rmse - b.rmse).abs() < 1e-6
                    && (a.mae - b.mae).abs() < 1e-6
            );
            assert!(a.n > 100 && a.n < n);
        }
    }
}
