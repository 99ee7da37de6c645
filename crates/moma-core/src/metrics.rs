//! Depth metrics (METHOD.md §3): δ1.05, δ1.10, δ1.25, REL, RMSE, MAE.
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
    /// let pred = MetricDepth::new(ndarray::array![[1.02f32, 2.5]]);
    /// let m = DepthMetrics::compute(&pred, &gt, None).unwrap();
    /// assert_eq!((m.n, m.d105, m.d125), (2, 0.5, 1.0));
    /// assert!((m.mae - 0.26).abs() < 1e-6);
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
                let row = match ms {
                    Some(m) => row_sums_masked(&ps[range.clone()], &gs[range.clone()], &m[range]),
                    None => row_sums(&ps[range.clone()], &gs[range]),
                };
                acc.add(&row);
            }
        }
        acc.finish().ok_or_else(|| {
            CoreError::NoValidPixels(
                "no pixel to score: the mask holds no pixel with valid ground truth and a finite prediction".into(),
            )
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
#[inline(always)]
fn pixel(p: f32, g: f32, inside: bool) -> [f32; 7] {
    let ok = inside && g.is_finite() && g > 0.0 && p.is_finite();
    let (p, g) = if ok { (p, g) } else { (1.0, 1.0) };
    let one = if ok { 1.0f32 } else { 0.0 };
    let d = p - g;
    let ad = d.abs();
    let ind = |t: f32| if p < t * g && g < t * p { one } else { 0.0 };
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

crate::kernels::multiversion! {
    fn row_sums(p: &[f32], g: &[f32]) -> Sums {
        let mut a = [0.0f32; 7];
        let n = p.len().min(g.len());
        let (p, g) = (&p[..n], &g[..n]);
        for j in 0..n {
            let c = pixel(p[j], g[j], true);
            for m in 0..7 {
                a[m] += c[m];
            }
        }
        to_sums(a)
    }
}

crate::kernels::multiversion! {
    fn row_sums_masked(p: &[f32], g: &[f32], mask: &[bool]) -> Sums {
        let mut a = [0.0f32; 7];
        let n = p.len().min(g.len()).min(mask.len());
        let (p, g, mask) = (&p[..n], &g[..n], &mask[..n]);
        for j in 0..n {
            let c = pixel(p[j], g[j], mask[j]);
            for m in 0..7 {
                a[m] += c[m];
            }
        }
        to_sums(a)
    }
}

#[inline(always)]
fn to_sums(a: [f32; 7]) -> Sums {
    Sums {
        n: f64::from(a[0]),
        c105: f64::from(a[1]),
        c110: f64::from(a[2]),
        c125: f64::from(a[3]),
        rel: f64::from(a[4]),
        sq: f64::from(a[5]),
        abs: f64::from(a[6]),
    }
}
