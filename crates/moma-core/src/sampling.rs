//! Seeded choice of the n calibration pixels (METHOD.md §2).
//!
//! CONTRACT (implemented by the core work item): keep these names and signatures.

use serde::{Deserialize, Serialize};

use crate::error::Result;
use crate::image::{Mask, MetricDepth};

/// How calibration pixels are chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum SamplingStrategy {
    /// MOMA's protocol: uniform without replacement over valid ground-truth pixels.
    #[default]
    Random,
    /// BoostingDepth's: √n × √n grid nodes, each snapped to the nearest valid pixel.
    Grid,
}

/// Sampling settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct SamplingConfig {
    /// Strategy.
    pub strategy: SamplingStrategy,
    /// Number of samples n (default 100).
    pub n: usize,
    /// Seed of every random choice.
    pub seed: u64,
}

impl Default for SamplingConfig {
    fn default() -> Self {
        Self {
            strategy: SamplingStrategy::Random,
            n: 100,
            seed: 0,
        }
    }
}

/// A pixel position: `u` = column, `v` = row (pixels).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Pixel {
    /// Column.
    pub u: u32,
    /// Row.
    pub v: u32,
}

/// Chooses up to `config.n` distinct pixels with valid ground truth (inside `restrict` when given).
/// Returns fewer only when fewer valid pixels exist (the fit then decides whether that is enough).
///
/// # Errors
/// No valid pixel; size mismatch between `gt` and `restrict`; `n == 0`.
pub fn sample_pixels(
    gt: &MetricDepth,
    config: &SamplingConfig,
    restrict: Option<&Mask>,
) -> Result<Vec<Pixel>> {
    let _ = (gt, config, restrict);
    todo!("core work item")
}
