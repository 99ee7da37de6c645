//! The element types (f32, f64) of the training path's CPU kernels: one trait for the LayerNorm,
//! resampling and attention-backward kernels.

use std::ops::{Add, AddAssign, Mul, Sub};

/// An element type of the training kernels: f32 (what `moma finetune` runs) or f64 (the
/// gradient checks and the PyTorch parity test).
pub(crate) trait Elem:
    Copy
    + Send
    + Sync
    + Default
    + 'static
    + Mul<Output = Self>
    + Add<Output = Self>
    + Sub<Output = Self>
    + AddAssign
{
    const ZERO: Self;
    /// From f64 (rounded to nearest for f32).
    fn of(v: f64) -> Self;
    /// To f64 (exact).
    fn f(self) -> f64;
}

impl Elem for f32 {
    const ZERO: Self = 0.0;
    fn of(v: f64) -> Self {
        v as f32
    }
    fn f(self) -> f64 {
        f64::from(self)
    }
}

impl Elem for f64 {
    const ZERO: Self = 0.0;
    fn of(v: f64) -> Self {
        v
    }
    fn f(self) -> f64 {
        self
    }
}
