//! The fused run-time path of [`Calibration::align`](crate::Calibration::align) for a raw prediction:
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

// Indexed loops over explicit lanes are what makes LLVM vectorise these kernels.
#![allow(clippy::needless_range_loop)]

use std::mem::MaybeUninit;

use ndarray::{ArrayView2, ArrayViewMut2};

use crate::align::AlignmentModel;
use crate::error::{CoreError, Result};
use crate::image::Mask;
use crate::normalise::{
    AlignSpace, NormStats, Normalisation, NormalisationConfig, affine_coefficients, no_valid_pixels,
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
                t: m.shift as f32,
            }),
            AlignmentModel::Ssra(m) => Some(Self {
                col: m.column_terms(width),
                rows: (0..height).map(|v| m.row_term(v)).collect(),
                t: m.t3 as f32,
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
/// `None` when the normalisation is not covered (median), or when `positive_in` (a metric
/// depth, where a value ≤ 0 is no prediction) and the map holds such a value.
///
/// # Errors
/// As [`normalise`](crate::normalise::normalise): non-finite values, no valid pixel, degenerate
/// statistics; a size mismatch of the region (checked by the caller).
pub(crate) fn prepare(
    pred: ArrayView2<'_, f32>,
    invert_in: bool,
    positive_in: bool,
    config: &NormalisationConfig,
    region: Option<&Mask>,
    terms: ModelTerms,
) -> Result<Option<FusedPass>> {
    if config.method == Normalisation::Median {
        return Ok(None);
    }
    let region_view = region.map(|m| m.data().view());
    let acc = statistics(pred, invert_in, region_view);
    if acc.non_finite {
        // The slow path only on error: the count and the first offending pixel (row-major).
        let w = pred.ncols().max(1);
        let first = pred.iter().position(|x| !x.is_finite()).unwrap_or_default();
        return Err(CoreError::NonFinitePrediction {
            count: pred.iter().filter(|x| !x.is_finite()).count(),
            u: first % w,
            v: first / w,
            metric_depth: positive_in,
        });
    }
    // No valid value: min stayed +inf, max −inf.
    if acc.min > acc.max {
        return Err(no_valid_pixels(region.is_some()));
    }
    // A metric depth ≤ 0 is no prediction: the unfused path makes it invalid (rare: the
    // statistics' minimum says so for the whole map, a scan only with a region)
    if positive_in && !invert_in {
        let any_non_positive = match region {
            None => acc.min <= 0.0,
            Some(_) => pred.iter().any(|&d| d <= 0.0),
        };
        if any_non_positive {
            return Ok(None);
        }
    }
    let mut stats = NormStats {
        min: f64::from(acc.min),
        max: f64::from(acc.max),
        median: f64::NAN,
        mad: f64::NAN,
        n: 0,
    };
    let (a, b) = match affine_coefficients(config.method, &stats) {
        Ok(ab) => ab,
        Err(_) => {
            // Degenerate: the error names the number of valid pixels, counted only here.
            stats.n = count_valid(pred, invert_in, region_view);
            affine_coefficients(config.method, &stats)?
        }
    };
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
pub(crate) fn apply<O: Slot>(
    pass: &FusedPass,
    pred: ArrayView2<'_, f32>,
    out: &mut ArrayViewMut2<'_, O>,
) {
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
fn apply_avx2<O: Slot>(
    pass: &FusedPass,
    pred: ArrayView2<'_, f32>,
    out: &mut ArrayViewMut2<'_, O>,
) {
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
    for ((zin, mut zout), &r) in pred.rows().into_iter().zip(out.rows_mut()).zip(&terms.rows) {
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
        y = if RECIP {
            crate::kernels::depth_of_disparity(y)
        } else {
            crate::kernels::positive_or_nan(y)
        };
        out[j].set(y);
    }
}

/// Lanes of the statistics pass.
const L: usize = 8;

/// Pass 1's result.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Stats {
    /// Some prediction value (anywhere in the map) is not finite.
    non_finite: bool,
    /// Smallest valid value after the space conversion (inside the region); +inf if none.
    min: f32,
    /// Largest valid value; −inf if none.
    max: f32,
}

/// Lane-parallel accumulators (so that the loop vectorises): minimum and maximum of the valid
/// values, and `Σ (d − d)`, 0 while every value is finite and NaN from the first that is not.
#[derive(Clone, Copy)]
struct Acc {
    lo: [f32; L],
    hi: [f32; L],
    nan: [f32; L],
}

/// The value of a prediction `d` after the space conversion, and whether it is valid (finite
/// after the conversion, inside the region).
#[inline(always)]
fn converted<const INV: bool>(d: f32, inside: bool) -> (f32, bool) {
    let z = if INV {
        if d > 0.0 { 1.0 / d } else { f32::NAN }
    } else {
        d
    };
    // `z − z == 0` ⇔ z finite (NaN for ±inf and NaN): a float compare, no integer masks.
    #[allow(clippy::eq_op)]
    let finite = z - z == 0.0;
    (z, inside & finite)
}

/// Accumulates one row (`mask`: the region's row, ignored unless `MASK`) into `acc`, on local
/// copies so that the accumulators stay in registers. Only float selects, min and max: the
/// loop maps onto vector instructions one to one.
#[inline(always)]
fn statistics_row<const INV: bool, const MASK: bool>(x: &[f32], mask: &[bool], acc: &mut Acc) {
    let Acc {
        mut lo,
        mut hi,
        mut nan,
    } = *acc;
    #[allow(clippy::eq_op)] // d − d: 0 for finite d, NaN otherwise
    let mut visit = |l: usize, d: f32, inside: bool| {
        nan[l] += d - d;
        let (z, ok) = converted::<INV>(d, inside);
        let zl = if ok { z } else { f32::INFINITY };
        let zh = if ok { z } else { f32::NEG_INFINITY };
        lo[l] = if zl < lo[l] { zl } else { lo[l] };
        hi[l] = if zh > hi[l] { zh } else { hi[l] };
    };
    let n = if MASK {
        x.len().min(mask.len())
    } else {
        x.len()
    };
    let full = n / L * L;
    let (x, xt) = x[..n].split_at(full);
    for (j, c) in x.chunks_exact(L).enumerate() {
        let c: &[f32; L] = c.try_into().unwrap_or(&[0.0; L]);
        if MASK {
            let m: &[bool; L] = mask[j * L..j * L + L].try_into().unwrap_or(&[false; L]);
            for l in 0..L {
                visit(l, c[l], m[l]);
            }
        } else {
            for l in 0..L {
                visit(l, c[l], true);
            }
        }
    }
    for (k, &d) in xt.iter().enumerate() {
        visit(0, d, !MASK || mask[full + k]);
    }
    *acc = Acc { lo, hi, nan };
}

/// [`statistics_row`] with AVX2 intrinsics (LLVM does not vectorise the lane loop well: it
/// narrows the masks). Same values: min / max are exact, the NaN sum is order-free.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn statistics_row_avx2<const INV: bool, const MASK: bool>(x: &[f32], mask: &[bool], acc: &mut Acc) {
    use std::arch::x86_64::*;
    let n = if MASK {
        x.len().min(mask.len())
    } else {
        x.len()
    };
    let full = n / L * L;
    let zero = _mm256_setzero_ps();
    let (inf, ninf) = (
        _mm256_set1_ps(f32::INFINITY),
        _mm256_set1_ps(f32::NEG_INFINITY),
    );
    let (one, nan_v) = (_mm256_set1_ps(1.0), _mm256_set1_ps(f32::NAN));
    // SAFETY: the accumulators are arrays of L = 8 f32.
    let (mut lo, mut hi, mut nan) = unsafe {
        (
            _mm256_loadu_ps(acc.lo.as_ptr()),
            _mm256_loadu_ps(acc.hi.as_ptr()),
            _mm256_loadu_ps(acc.nan.as_ptr()),
        )
    };
    let mut j = 0;
    while j < full {
        // SAFETY: j + 8 ≤ full ≤ x.len().
        let d = unsafe { _mm256_loadu_ps(x.as_ptr().add(j)) };
        let dd = _mm256_sub_ps(d, d);
        nan = _mm256_add_ps(nan, dd);
        let (z, zz) = if INV {
            let pos = _mm256_cmp_ps::<_CMP_GT_OQ>(d, zero);
            let z = _mm256_blendv_ps(nan_v, _mm256_div_ps(one, d), pos);
            (z, _mm256_sub_ps(z, z))
        } else {
            (d, dd)
        };
        let mut ok = _mm256_cmp_ps::<_CMP_EQ_OQ>(zz, zero);
        if MASK {
            // SAFETY: j + 8 ≤ full ≤ mask.len(); a bool is one byte, 0 or 1.
            let m = unsafe { _mm_loadl_epi64(mask.as_ptr().add(j).cast::<__m128i>()) };
            let m = _mm256_cmpgt_epi32(_mm256_cvtepu8_epi32(m), _mm256_setzero_si256());
            ok = _mm256_and_ps(ok, _mm256_castsi256_ps(m));
        }
        lo = _mm256_min_ps(_mm256_blendv_ps(inf, z, ok), lo);
        hi = _mm256_max_ps(_mm256_blendv_ps(ninf, z, ok), hi);
        j += L;
    }
    // SAFETY: as for the loads.
    unsafe {
        _mm256_storeu_ps(acc.lo.as_mut_ptr(), lo);
        _mm256_storeu_ps(acc.hi.as_mut_ptr(), hi);
        _mm256_storeu_ps(acc.nan.as_mut_ptr(), nan);
    }
    let tail_mask = if MASK { &mask[full..n] } else { &[] };
    statistics_row::<INV, MASK>(&x[full..n], tail_mask, acc);
}

fn statistics(
    pred: ArrayView2<'_, f32>,
    invert: bool,
    region: Option<ArrayView2<'_, bool>>,
) -> Stats {
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
    if invert {
        statistics_rows::<true, true>(pred, region)
    } else {
        statistics_rows::<false, true>(pred, region)
    }
}

fn statistics_dispatch(
    pred: ArrayView2<'_, f32>,
    invert: bool,
    region: Option<ArrayView2<'_, bool>>,
) -> Stats {
    if invert {
        statistics_rows::<true, false>(pred, region)
    } else {
        statistics_rows::<false, false>(pred, region)
    }
}

/// `AVX`: rows through [`statistics_row_avx2`]; only from [`statistics_avx2`].
#[inline(always)]
fn statistics_rows<const INV: bool, const AVX: bool>(
    pred: ArrayView2<'_, f32>,
    region: Option<ArrayView2<'_, bool>>,
) -> Stats {
    let mut acc = Acc {
        lo: [f32::INFINITY; L],
        hi: [f32::NEG_INFINITY; L],
        nan: [0.0; L],
    };
    let mut scratch: Vec<f32> = Vec::new();
    let mut scratch_mask: Vec<bool> = Vec::new();
    for (v, row) in pred.rows().into_iter().enumerate() {
        let x: &[f32] = match row.as_slice() {
            Some(s) => s,
            None => {
                scratch.clear();
                scratch.extend(row.iter().copied());
                &scratch
            }
        };
        let row_kernel = |x: &[f32], mask: Option<&[bool]>, acc: &mut Acc| {
            #[cfg(target_arch = "x86_64")]
            if AVX {
                // SAFETY: AVX is true only inside `statistics_avx2`, called after detecting AVX2
                // and FMA.
                unsafe {
                    match mask {
                        None => statistics_row_avx2::<INV, false>(x, &[], acc),
                        Some(m) => statistics_row_avx2::<INV, true>(x, m, acc),
                    }
                }
                return;
            }
            match mask {
                None => statistics_row::<INV, false>(x, &[], acc),
                Some(m) => statistics_row::<INV, true>(x, m, acc),
            }
        };
        match &region {
            None => row_kernel(x, None, &mut acc),
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
                row_kernel(x, Some(mask), &mut acc);
            }
        }
    }
    Stats {
        non_finite: acc.nan.iter().any(|x| x.is_nan()),
        min: acc.lo.iter().copied().fold(f32::INFINITY, f32::min),
        max: acc.hi.iter().copied().fold(f32::NEG_INFINITY, f32::max),
    }
}

/// The number of valid values (for an error message only).
fn count_valid(
    pred: ArrayView2<'_, f32>,
    invert: bool,
    region: Option<ArrayView2<'_, bool>>,
) -> usize {
    pred.indexed_iter()
        .filter(|&((v, u), &d)| {
            let inside = region.is_none_or(|m| m[[v, u]]);
            if invert {
                converted::<true>(d, inside).1
            } else {
                converted::<false>(d, inside).1
            }
        })
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::{Array2, s};

    /// The portable statistics (and the AVX2 ones where the CPU has them) against a direct
    /// computation, with and without inversion and region, with tails and strides.
    #[test]
    fn statistics_kernels_agree_with_a_direct_computation() {
        let (h, w) = (7, 29);
        let pred = Array2::from_shape_fn((h, w), |(v, u)| {
            let k = (u * 31 + v * 17) % 23;
            if k == 0 {
                -0.5
            } else if k == 1 {
                0.0
            } else {
                0.1 * k as f32 - 0.05 * v as f32
            }
        });
        let region = Array2::from_shape_fn((h, w), |(v, u)| (u + 2 * v) % 3 != 0);
        let wide = {
            let mut a = Array2::<f32>::zeros((h, 2 * w));
            a.slice_mut(s![.., ..;2]).assign(&pred);
            a
        };
        for view in [pred.view(), wide.slice(s![.., ..;2])] {
            for invert in [false, true] {
                for r in [None, Some(region.view())] {
                    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                    for ((v, u), &d) in view.indexed_iter() {
                        let z = if invert {
                            if d > 0.0 { 1.0 / d } else { f32::NAN }
                        } else {
                            d
                        };
                        if z.is_finite() && r.is_none_or(|m| m[[v, u]]) {
                            lo = lo.min(z);
                            hi = hi.max(z);
                        }
                    }
                    let want = Stats {
                        non_finite: false,
                        min: lo,
                        max: hi,
                    };
                    assert_eq!(statistics_dispatch(view, invert, r), want);
                    assert_eq!(statistics(view, invert, r), want);
                    let mut bad = view.to_owned();
                    bad[[h - 1, w - 1]] = f32::INFINITY; // in a row tail
                    assert!(statistics_dispatch(bad.view(), invert, r).non_finite);
                    assert!(statistics(bad.view(), invert, r).non_finite);
                    let mut bad = view.to_owned();
                    bad[[2, 3]] = f32::NAN; // in a vector chunk
                    assert!(statistics_dispatch(bad.view(), invert, r).non_finite);
                    assert!(statistics(bad.view(), invert, r).non_finite);
                }
            }
        }
    }

    /// The portable output pass equals the dispatched one (AVX2 where available).
    #[test]
    fn apply_kernels_agree() {
        let (h, w) = (5, 21);
        let pred = Array2::from_shape_fn((h, w), |(v, u)| 0.2 + 0.03 * u as f32 - 0.07 * v as f32);
        for (invert_in, norm, recip_out) in [
            (false, Some((1.7, -0.2)), true),
            (true, Some((0.9, 0.1)), false),
            (true, None, true),
            (false, None, false),
        ] {
            let pass = FusedPass {
                invert_in,
                norm,
                terms: ModelTerms {
                    col: (0..w).map(|u| 0.01 * u as f32).collect(),
                    rows: (0..h).map(|v| 0.5 - 0.02 * v as f32).collect(),
                    t: 0.05,
                },
                recip_out,
            };
            let mut a = Array2::<f32>::zeros((h, w));
            let mut b = Array2::<f32>::zeros((h, w));
            apply(&pass, pred.view(), &mut a.view_mut());
            apply_dispatch(&pass, pred.view(), &mut b.view_mut());
            for ((v, u), &x) in a.indexed_iter() {
                let y = b[[v, u]];
                assert!(x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()));
                // Independent: the formula in f64, rounded where the path rounds.
                let mut z = pred[[v, u]];
                if invert_in {
                    z = if z > 0.0 { 1.0 / z } else { f32::NAN };
                }
                if let Some((na, nb)) = norm {
                    z = (na * f64::from(z) + nb) as f32;
                }
                let mut want = z * (pass.terms.col[u] + pass.terms.rows[v]) + pass.terms.t;
                if recip_out {
                    want = if want > 0.0 && want.is_finite() {
                        1.0 / want
                    } else {
                        f32::NAN
                    };
                }
                assert!(x.to_bits() == want.to_bits() || (x.is_nan() && want.is_nan()));
            }
        }
    }
}
