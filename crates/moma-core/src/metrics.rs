//! Depth metrics (METHOD.md §3): δ1.05, δ1.10, δ1.25, REL, RMSE, MAE.
//!
//! CONTRACT (implemented by the core work item): keep these names and signatures.

use serde::{Deserialize, Serialize};

use crate::error::Result;
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
    /// # Errors
    /// Size mismatch; no pixel to score (reported, never silently NaN).
    pub fn compute(pred: &MetricDepth, gt: &MetricDepth, mask: Option<&Mask>) -> Result<Self> {
        let _ = (pred, gt, mask);
        todo!("core work item")
    }
}
