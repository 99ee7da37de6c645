//! The fused run-time path of [`Calibration::align_view_into`](crate::Calibration::align_view_into):
//! normalisation, a global alignment (GSSA, SSRA) and the reciprocal of inverse space in two
//! passes over the image, reading the prediction in place:
//!
//! 1. statistics: non-finite count of the prediction, and min / max / count of the valid values
//!    after the space conversion (over the workspace, if any);
//! 2. output: per pixel `z → (1/z) → a·z + b (f64) → ẑ·(αu + βv + γ) + T3 → (1/y)`, with `αu`
//!    precomputed per column and `βv + γ` per row (GSSA is the same with `αu = −0` and
//!    `βv + γ = scale`, which is bit-exact: `−0 + s = s`).
//!
//! Every operation is the one the unfused path ([`normalise`](crate::normalise::normalise) then
//! [`AlignmentModel::apply_into`](crate::align::AlignmentModel::apply_into)) performs, in the
//! same order and precision, so the results are identical bit for bit (tested). Not covered, and
//! left to the unfused path: median normalisation (needs a selection over a copy), LWLR and the
//! local models (per-pixel maps), RAW.
//!
//! The loops are written over row slices with the per-pixel choices as const generics, so that
//! the compiler vectorises them; on x86-64 an AVX2 clone is chosen at run time.

use std::mem::MaybeUninit;

use ndarray::{ArrayView2, ArrayViewMut2};

use crate::align::AlignmentModel;
use crate::error::{CoreError, Result};
use crate::image::Mask;
use crate::normalise::{
    AlignSpace, NormStats, Normalisation, NormalisationConfig, affine_coefficients,
    no_valid_pixels,
};

/// The model part of the fused pass: `out = ẑ·(col[u] + rows[v]) + t`.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ModelTerms {
    col: Vec<f32>,
    rows: Vec<f32>,
    t: f32,
}

impl ModelTerms {
    /// The terms of `model` for a `width × height` image, or `None` where the fused path does not
    /// apply (LWLR, local models, RAW).
    pub(crate) fn of(model: &AlignmentModel, width: usize, height: usize) -> Option<Self> {
        match model {
            AlignmentModel::Gssa(m) => Some(Self {
                col: vec![-0.0; width],
                rows: vec![m.scale as f32; height],
                t: m.shift_m as f32,
            }),
            AlignmentModel::Ssra(m) => Some(Self {
                col: m.column_terms(width),
                rows: (0..height).map(|v| m.row_term(v)).collect(),
                t: m.t3_m as f32,
            }),
            AlignmentModel::Auto(m) => Self::of(&m.chosen, width, height),
            AlignmentModel::Raw | AlignmentModel::Lwlr(_) | AlignmentModel::Local(_) => None,
        }
    }
}

/// Everything the output pass needs.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct FusedPass {
    /// Convert the prediction to the other space first (`1/d`, NaN for `d ≤ 0`).
    invert_in: bool,
    /// The normalisation's affine map `(a, b)` in f64, `None` for normalisation `none`.
    norm: Option<(f64, f64)>,
    terms: ModelTerms,
    /// Inverse space: the output is the reciprocal of the fitted disparity.
    recip_out: bool,
}

/// Pass 1: checks the prediction and computes the normalisation exactly as
/// [`normalise`](crate::normalise::normalise) does; returns the output pass.
///
/// `None` when the normalisation is not covered (median).
///
/// # Errors
/// As [`normalise`](crate::normalise::normalise): non-finite values, no valid pixel, degenerate
/// statistics; a size mismatch of the region (checked by the caller).
pub(crate) fn prepare(
    pred: ArrayView2<'_, f32>,
    invert_in: bool,
    config: &NormalisationConfig,
    region: Option<&Mask>,
    terms: ModelTerms,
) -> Result<Option<FusedPass>> {
    if config.method == Normalisation::Median {
        return Ok(None);
    }
    let acc = statistics(pred, invert_in, region.map(|m| m.data().view()));
    if acc.bad > 0 {
        // The slow path only on error: the first offending pixel in row-major order.
        let w = pred.ncols().max(1);
        let first = pred
            .iter()
            .position(|x| !x.is_finite())
            .unwrap_or_default();
        return Err(CoreError::NonFinitePrediction {
            count: acc.bad,
            u: first % w,
            v: first / w,
        });
    }
    if acc.n == 0 {
        return Err(no_valid_pixels(region.is_some()));
    }
    let stats = NormStats {
        min: f64::from(acc.min),
        max: f64::from(acc.max),
        median: f64::NAN,
        mad: f64::NAN,
        n: acc.n,
    };
    let (a, b) = affine_coefficients(config.method, &stats)?;
    Ok(Some(FusedPass {
        invert_in,
        norm: (config.method != Normalisation::None).then_some((a, b)),
        terms,
        recip_out: config.space == AlignSpace::Inverse,
    }))
}

/// Where one output pixel is written: a plain `f32`, or a slot of a fresh buffer.
pub(crate) trait Slot {
    /// Stores `v`.
    fn set(&mut self, v: f32);
}

impl Slot for f32 {
    #[inline(always)]
    fn set(&mut self, v: f32) {
        *self = v;
    }
}

impl Slot for MaybeUninit<f32> {
    #[inline(always)]
    fn set(&mut self, v: f32) {
        self.write(v);
    }
}

/// Pass 2: writes every pixel of `out` (same shape as `pred`, checked by the caller).
pub(crate) fn apply<O: Slot>(pass: &FusedPass, pred: ArrayView2<'_, f32>, out: &mut ArrayViewMut2<'_, O>) {
    debug_assert_eq!(pred.dim(), out.dim());
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
        // SAFETY: `apply_avx2` only needs the CPU features just detected.
        return unsafe { apply_avx2(pass, pred, out) };
    }
    apply_dispatch(pass, pred, out);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn apply_avx2<O: Slot>(pass: &FusedPass, pred: ArrayView2<'_, f32>, out: &mut ArrayViewMut2<'_, O>) {
    apply_dispatch(pass, pred, out);
}

#[inline(always)]
fn apply_dispatch<O: Slot>(
    pass: &FusedPass,
    pred: ArrayView2<'_, f32>,
    out: &mut ArrayViewMut2<'_, O>,
) {
    match (pass.invert_in, pass.norm.is_some(), pass.recip_out) {
        (false, false, false) => apply_rows::<O, false, false, false>(pass, pred, out),
        (false, false, true) => apply_rows::<O, false, false, true>(pass, pred, out),
        (false, true, false) => apply_rows::<O, false, true, false>(pass, pred, out),
        (false, true, true) => apply_rows::<O, false, true, true>(pass, pred, out),
        (true, false, false) => apply_rows::<O, true, false, false>(pass, pred, out),
        (true, false, true) => apply_rows::<O, true, false, true>(pass, pred, out),
        (true, true, false) => apply_rows::<O, true, true, false>(pass, pred, out),
        (true, true, true) => apply_rows::<O, true, true, true>(pass, pred, out),
    }
}

#[inline(always)]
fn apply_rows<O: Slot, const INV: bool, const NORM: bool, const RECIP: bool>(
    pass: &FusedPass,
    pred: ArrayView2<'_, f32>,
    out: &mut ArrayViewMut2<'_, O>,
) {
    let (a, b) = pass.norm.unwrap_or((1.0, 0.0));
    let terms = &pass.terms;
    let mut scratch_in: Vec<f32> = Vec::new();
    let mut scratch_out: Vec<f32> = Vec::new();
    for ((zin, mut zout), &r) in pred
        .rows()
        .into_iter()
        .zip(out.rows_mut())
        .zip(&terms.rows)
    {
        let x: &[f32] = match zin.as_slice() {
            Some(s) => s,
            None => {
                scratch_in.clear();
                scratch_in.extend(zin.iter().copied());
                &scratch_in
            }
        };
        match zout.as_slice_mut() {
            Some(o) => fused_row::<O, INV, NORM, RECIP>(x, o, &terms.col, a, b, r, terms.t),
            None => {
                scratch_out.resize(x.len(), 0.0);
                fused_row::<f32, INV, NORM, RECIP>(
                    x,
                    &mut scratch_out,
                    &terms.col,
                    a,
                    b,
                    r,
                    terms.t,
                );
                zout.iter_mut()
                    .zip(&scratch_out)
                    .for_each(|(o, &y)| o.set(y));
            }
        }
    }
}

/// One output row; the operations (and their order and precision) of the unfused path.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn fused_row<O: Slot, const INV: bool, const NORM: bool, const RECIP: bool>(
    x: &[f32],
    out: &mut [O],
    col: &[f32],
    a: f64,
    b: f64,
    r: f32,
    t: f32,
) {
    let n = out.len().min(x.len()).min(col.len());
    let (x, out, col) = (&x[..n], &mut out[..n], &col[..n]);
    for j in 0..n {
        let mut z = x[j];
        if INV {
            z = if z > 0.0 { 1.0 / z } else { f32::NAN };
        }
        if NORM {
            z = (a * f64::from(z) + b) as f32;
        }
        let mut y = z * (col[j] + r) + t;
        if RECIP {
            y = if y > 0.0 && y.is_finite() {
                1.0 / y
            } else {
                f32::NAN
            };
        }
        out[j].set(y);
    }
}

/// Lanes of the statistics pass.
const L: usize = 8;

/// Pass 1's result.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Stats {
    /// Non-finite prediction values (whole map).
    bad: usize,
    /// Smallest valid value after the space conversion (inside the region).
    min: f32,
    /// Largest valid value.
    max: f32,
    /// Valid values counted.
    n: usize,
}

/// Lane-parallel accumulators (so that the loop vectorises).
struct Acc {
    lo: [f32; L],
    hi: [f32; L],
    cnt: [u32; L],
    bad: [u32; L],
}

impl Acc {
    #[inline(always)]
    fn visit<const INV: bool>(&mut self, l: usize, d: f32, inside: bool) {
        self.bad[l] += u32::from(!(d.abs() < f32::INFINITY));
        let z = if INV {
            if d > 0.0 { 1.0 / d } else { f32::NAN }
        } else {
            d
        };
        let ok = inside & (z.abs() < f32::INFINITY);
        self.lo[l] = if ok & (z < self.lo[l]) { z } else { self.lo[l] };
        self.hi[l] = if ok & (z > self.hi[l]) { z } else { self.hi[l] };
        self.cnt[l] += u32::from(ok);
    }
}

fn statistics(pred: ArrayView2<'_, f32>, invert: bool, region: Option<ArrayView2<'_, bool>>) -> Stats {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
        // SAFETY: `statistics_avx2` only needs the CPU features just detected.
        return unsafe { statistics_avx2(pred, invert, region) };
    }
    statistics_dispatch(pred, invert, region)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn statistics_avx2(
    pred: ArrayView2<'_, f32>,
    invert: bool,
    region: Option<ArrayView2<'_, bool>>,
) -> Stats {
    statistics_dispatch(pred, invert, region)
}

#[inline(always)]
fn statistics_dispatch(
    pred: ArrayView2<'_, f32>,
    invert: bool,
    region: Option<ArrayView2<'_, bool>>,
) -> Stats {
    if invert {
        statistics_rows::<true>(pred, region)
    } else {
        statistics_rows::<false>(pred, region)
    }
}

#[inline(always)]
fn statistics_rows<const INV: bool>(
    pred: ArrayView2<'_, f32>,
    region: Option<ArrayView2<'_, bool>>,
) -> Stats {
    let mut acc = Acc {
        lo: [f32::INFINITY; L],
        hi: [f32::NEG_INFINITY; L],
        cnt: [0; L],
        bad: [0; L],
    };
    let mut scratch: Vec<f32> = Vec::new();
    let mut scratch_mask: Vec<bool> = Vec::new();
    // Counts are per row into u32 lanes (a row holds < 2^32 pixels), summed in usize.
    let (mut n, mut bad) = (0usize, 0usize);
    for (v, row) in pred.rows().into_iter().enumerate() {
        let x: &[f32] = match row.as_slice() {
            Some(s) => s,
            None => {
                scratch.clear();
                scratch.extend(row.iter().copied());
                &scratch
            }
        };
        match &region {
            None => {
                let mut chunks = x.chunks_exact(L);
                for c in &mut chunks {
                    for l in 0..L {
                        acc.visit::<INV>(l, c[l], true);
                    }
                }
                for &d in chunks.remainder() {
                    acc.visit::<INV>(0, d, true);
                }
            }
            Some(m) => {
                let mrow = m.row(v);
                let mask: &[bool] = match mrow.as_slice() {
                    Some(s) => s,
                    None => {
                        scratch_mask.clear();
                        scratch_mask.extend(mrow.iter().copied());
                        &scratch_mask
                    }
                };
                let mut chunks = x.chunks_exact(L);
                let mut mchunks = mask.chunks_exact(L);
                for (c, mc) in (&mut chunks).zip(&mut mchunks) {
                    for l in 0..L {
                        acc.visit::<INV>(l, c[l], mc[l]);
                    }
                }
                for (&d, &i) in chunks.remainder().iter().zip(mchunks.remainder()) {
                    acc.visit::<INV>(0, d, i);
                }
            }
        }
        n += acc.cnt.iter().map(|&c| c as usize).sum::<usize>();
        bad += acc.bad.iter().map(|&c| c as usize).sum::<usize>();
        acc.cnt = [0; L];
        acc.bad = [0; L];
    }
    Stats {
        bad,
        min: acc.lo.iter().copied().fold(f32::INFINITY, f32::min),
        max: acc.hi.iter().copied().fold(f32::NEG_INFINITY, f32::max),
        n,
    }
}
