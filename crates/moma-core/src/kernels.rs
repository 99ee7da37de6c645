//! Hot inner loops, written so that LLVM auto-vectorises them, compiled twice: for the baseline
//! target and (on x86-64) for AVX2+FMA, chosen at run time. Internal to the crate.

// Indexed loops over explicit lanes are what makes LLVM vectorise these kernels.
#![allow(clippy::needless_range_loop)]

use ndarray::{ArrayView2, ArrayViewMut2};

/// Defines `fn name(args) -> ret { body }` with an AVX2+FMA clone selected at run time on x86-64.
macro_rules! multiversion {
    ($(#[$m:meta])* $vis:vis fn $name:ident($($arg:ident : $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block) => {
        $(#[$m])*
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            fn imp($($arg: $ty),*) $(-> $ret)? $body
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2,fma")]
            fn avx2($($arg: $ty),*) $(-> $ret)? { imp($($arg),*) }
            #[cfg(target_arch = "x86_64")]
            if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                // SAFETY: `avx2` only needs the CPU features just detected.
                return unsafe { avx2($($arg),*) };
            }
            imp($($arg),*)
        }
    };
}

/// Calls `f(row, input_row, output_row)` for every row with contiguous slices, copying through a
/// scratch row only when a view is not row-contiguous. Shapes must be equal (checked by callers).
pub(crate) fn map_rows(
    input: ArrayView2<'_, f32>,
    out: &mut ArrayViewMut2<'_, f32>,
    mut f: impl FnMut(usize, &[f32], &mut [f32]),
) {
    debug_assert_eq!(input.dim(), out.dim());
    let w = input.ncols();
    let mut scratch_in: Vec<f32> = Vec::new();
    let mut scratch_out: Vec<f32> = Vec::new();
    for (v, (zin, mut zout)) in input.rows().into_iter().zip(out.rows_mut()).enumerate() {
        let zin_slice: &[f32] = match zin.as_slice() {
            Some(s) => s,
            None => {
                scratch_in.clear();
                scratch_in.extend(zin.iter().copied());
                &scratch_in
            }
        };
        match zout.as_slice_mut() {
            Some(o) => f(v, zin_slice, o),
            None => {
                scratch_out.resize(w, 0.0);
                f(v, zin_slice, &mut scratch_out);
                zout.iter_mut().zip(&scratch_out).for_each(|(o, &x)| *o = x);
            }
        }
    }
}

multiversion! {
    /// `out = s·z + t`.
    pub(crate) fn affine(z: &[f32], out: &mut [f32], s: f32, t: f32) {
        for (o, &x) in out.iter_mut().zip(z) {
            *o = positive_or_nan(x * s + t);
        }
    }
}

multiversion! {
    /// `out[j] = z[j]·(col[j] + r) + t` (SSRA row).
    pub(crate) fn ssra_row(z: &[f32], out: &mut [f32], col: &[f32], r: f32, t: f32) {
        let n = out.len().min(z.len()).min(col.len());
        let (z, out, col) = (&z[..n], &mut out[..n], &col[..n]);
        for j in 0..n {
            out[j] = positive_or_nan(z[j] * (col[j] + r) + t);
        }
    }
}

multiversion! {
    /// `out[j] = z[j]·s[j] + t[j]` (LWLR maps).
    pub(crate) fn affine_maps(z: &[f32], out: &mut [f32], s: &[f32], t: &[f32]) {
        let n = out.len().min(z.len()).min(s.len()).min(t.len());
        let (z, out, s, t) = (&z[..n], &mut out[..n], &s[..n], &t[..n]);
        for j in 0..n {
            out[j] = positive_or_nan(z[j] * s[j] + t[j]);
        }
    }
}

/// Column block of the LWLR sums kernel (f64 lanes); the weight table rows are padded to it.
pub(crate) const LWLR_BLOCK: usize = 8;

/// The five LWLR weighted sums of one image row, for every (padded) column `j`:
/// `sums[m][j] = Σ_k coef[k][m] · wu[k·stride + j]`, where `coef[k] = wv_k·(1, x_k, x_k², y_k, x_k·y_k)`
/// and `wu[k·stride + j] = exp(−(j − u_k)²/(2b²))`. `stride` is a multiple of [`LWLR_BLOCK`];
/// each `sums[m]` has length `stride`. A small GEMM: FMA intrinsics on AVX2+FMA CPUs, else a
/// lane loop the compiler vectorises.
pub(crate) fn lwlr_row_sums(
    wu: &[f64],
    stride: usize,
    coef: &[[f64; 5]],
    sums: &mut [Vec<f64>; 5],
) {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU features were just detected.
        unsafe { lwlr_row_sums_fma(wu, stride, coef, sums) };
        return;
    }
    lwlr_row_sums_portable(wu, stride, coef, sums);
}

pub(crate) fn lwlr_row_sums_portable(
    wu: &[f64],
    stride: usize,
    coef: &[[f64; 5]],
    sums: &mut [Vec<f64>; 5],
) {
    const B: usize = LWLR_BLOCK;
    let mut j0 = 0;
    while j0 + B <= stride {
        let mut acc = [[0.0f64; B]; 5];
        for (k, c) in coef.iter().enumerate() {
            let w: &[f64; B] = wu[k * stride + j0..k * stride + j0 + B]
                .try_into()
                .unwrap_or(&[0.0; B]);
            for l in 0..B {
                acc[0][l] += c[0] * w[l];
                acc[1][l] += c[1] * w[l];
                acc[2][l] += c[2] * w[l];
                acc[3][l] += c[3] * w[l];
                acc[4][l] += c[4] * w[l];
            }
        }
        for m in 0..5 {
            sums[m][j0..j0 + B].copy_from_slice(&acc[m]);
        }
        j0 += B;
    }
}

/// AVX2+FMA micro-kernel: 8 columns (two 4-lane registers) × 5 sums = 10 accumulators.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn lwlr_row_sums_fma(wu: &[f64], stride: usize, coef: &[[f64; 5]], sums: &mut [Vec<f64>; 5]) {
    use std::arch::x86_64::*;
    const B: usize = LWLR_BLOCK;
    const _: () = assert!(B == 8);
    let n = coef.len().min(wu.len() / stride.max(1));
    if sums.iter().any(|s| s.len() < stride) {
        return lwlr_row_sums_portable(wu, stride, coef, sums);
    }
    let mut j0 = 0;
    while j0 + B <= stride {
        let mut a = [_mm256_setzero_pd(); 10];
        for (k, c) in coef.iter().enumerate().take(n) {
            // SAFETY: k < n ≤ wu.len()/stride and j0 + 8 ≤ stride, so both loads are in bounds.
            let (w0, w1) = unsafe {
                let ptr = wu.as_ptr().add(k * stride + j0);
                (_mm256_loadu_pd(ptr), _mm256_loadu_pd(ptr.add(4)))
            };
            for m in 0..5 {
                let cm = _mm256_set1_pd(c[m]);
                a[2 * m] = _mm256_fmadd_pd(cm, w0, a[2 * m]);
                a[2 * m + 1] = _mm256_fmadd_pd(cm, w1, a[2 * m + 1]);
            }
        }
        for m in 0..5 {
            // SAFETY: j0 + 8 ≤ stride ≤ sums[m].len().
            unsafe {
                let ptr = sums[m].as_mut_ptr().add(j0);
                _mm256_storeu_pd(ptr, a[2 * m]);
                _mm256_storeu_pd(ptr.add(4), a[2 * m + 1]);
            }
        }
        j0 += B;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lwlr_kernels_agree() {
        let (n, stride) = (13, 24);
        let wu: Vec<f64> = (0..n * stride)
            .map(|i| ((i * 37) % 101) as f64 / 101.0)
            .collect();
        let coef: Vec<[f64; 5]> = (0..n)
            .map(|k| std::array::from_fn(|m| (k * 5 + m) as f64 * 0.1 - 1.0))
            .collect();
        let mut a: [Vec<f64>; 5] = std::array::from_fn(|_| vec![0.0; stride]);
        let mut b = a.clone();
        lwlr_row_sums(&wu, stride, &coef, &mut a);
        lwlr_row_sums_portable(&wu, stride, &coef, &mut b);
        for m in 0..5 {
            for j in 0..stride {
                let want: f64 = (0..n).map(|k| coef[k][m] * wu[k * stride + j]).sum();
                assert!((a[m][j] - want).abs() < 1e-12 && (b[m][j] - want).abs() < 1e-12);
            }
        }
    }
}

multiversion! {
    /// `z = (a·z + b)` computed in f64, in place.
    pub(crate) fn affine_f64(z: &mut [f32], a: f64, b: f64) {
        for x in z.iter_mut() {
            *x = (a * f64::from(*x) + b) as f32;
        }
    }
}

multiversion! {
    /// Minimum, maximum (as f64) and count of the finite values of `z` (inside `mask` when given).
    /// Lane-parallel so that it vectorises; `(inf, −inf, 0)` when there is none.
    pub(crate) fn finite_min_max(z: &[f32], mask: Option<&[bool]>) -> (f64, f64, usize) {
        const L: usize = 8;
        let mut lo = [f32::INFINITY; L];
        let mut hi = [f32::NEG_INFINITY; L];
        let mut cnt = [0u32; L];
        let mut visit = |l: usize, x: f32, inside: bool| {
            let ok = inside & (x.abs() < f32::INFINITY);
            lo[l] = if ok & (x < lo[l]) { x } else { lo[l] };
            hi[l] = if ok & (x > hi[l]) { x } else { hi[l] };
            cnt[l] += u32::from(ok);
        };
        let n = match mask {
            Some(m) => z.len().min(m.len()),
            None => z.len(),
        };
        let full = n / L * L;
        match mask {
            Some(m) => {
                for j0 in (0..full).step_by(L) {
                    for l in 0..L {
                        visit(l, z[j0 + l], m[j0 + l]);
                    }
                }
                for j in full..n {
                    visit(0, z[j], m[j]);
                }
            }
            None => {
                for j0 in (0..full).step_by(L) {
                    for l in 0..L {
                        visit(l, z[j0 + l], true);
                    }
                }
                for j in full..n {
                    visit(0, z[j], true);
                }
            }
        }
        let min = lo.iter().copied().fold(f32::INFINITY, f32::min);
        let max = hi.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        (f64::from(min), f64::from(max), cnt.iter().map(|&c| c as usize).sum())
    }
}

/// `y` where positive and finite, else `NaN`: an alignment's output is a depth in metres (depth
/// space) or a disparity that becomes one (inverse space), and either is a depth only where it
/// is positive. A fit that goes through zero (a depth-space model extrapolated beyond the
/// calibration's range) writes an invalid pixel, never zero or negative metres; one whose
/// product overflows f32 (parameters read from a file can be as large as f64 allows) never
/// `±inf` metres.
#[inline(always)]
pub(crate) fn positive_or_nan(y: f32) -> f32 {
    // `y − y == 0` ⇔ y finite
    #[allow(clippy::eq_op)]
    if y > 0.0 && y - y == 0.0 { y } else { f32::NAN }
}

/// The depth of a fitted disparity `y` (inverse space): `1/y` where that is positive and
/// finite, else `NaN`. A fitted disparity is a depth only where it is positive; one below
/// 1/f32::MAX ≈ 2.9e-39 m⁻¹ has no finite reciprocal in f32 and is invalid too, not `inf`
/// metres.
#[inline(always)]
pub(crate) fn depth_of_disparity(y: f32) -> f32 {
    let z = 1.0 / y;
    // Valid ⇔ 0 < z < inf: that excludes y ≤ 0 (z ≤ 0, ±inf or NaN), a subnormal y (z = inf),
    // y < 1/f32::MAX (z = inf), y = inf (z = 0) and NaN. `z − z == 0` ⇔ z finite.
    #[allow(clippy::eq_op)]
    if z > 0.0 && z - z == 0.0 { z } else { f32::NAN }
}

/// In place: [`depth_of_disparity`] of every value.
pub(crate) fn reciprocal_positive(out: &mut ndarray::ArrayViewMut2<'_, f32>) {
    out.mapv_inplace(depth_of_disparity);
}

#[cfg(test)]
mod output_tests {
    use super::*;

    #[test]
    fn a_disparity_is_a_depth_only_where_its_reciprocal_is_positive_and_finite() {
        let cases: [(f32, Option<f32>); 12] = [
            (2.0, Some(0.5)),
            (0.5, Some(2.0)),
            (f32::MAX, Some(1.0 / f32::MAX)),
            (1.0e-38, Some(1.0 / 1.0e-38)), // 1/y = 1e38 < f32::MAX
            (2.0e-39, None),                // below 1/f32::MAX ≈ 2.9e-39: 1/y overflows
            (1.0e-45, None),
            (0.0, None),
            (-0.0, None),
            (-1.0, None),
            (f32::INFINITY, None), // 1/inf = 0 m is no depth
            (f32::NEG_INFINITY, None),
            (f32::NAN, None),
        ];
        for (y, want) in cases {
            let got = depth_of_disparity(y);
            match want {
                Some(z) => assert_eq!(got, z, "y = {y:e}"),
                None => assert!(got.is_nan(), "y = {y:e} gave {got}"),
            }
        }
        let mut m = ndarray::array![[2.0f32, 1.0e-45], [f32::INFINITY, -3.0]];
        reciprocal_positive(&mut m.view_mut());
        assert_eq!(m[[0, 0]], 0.5);
        assert!(m[[0, 1]].is_nan() && m[[1, 0]].is_nan() && m[[1, 1]].is_nan());
    }

    #[test]
    fn overflowing_or_non_positive_alignments_write_nan() {
        for (y, keep) in [
            (1.5f32, true),
            (1.0e-45, true),
            // a fitted depth at or behind the camera is no depth: NaN in every output file
            (-2.0, false),
            (0.0, false),
            (-0.0, false),
            (f32::MAX, true),
            (f32::INFINITY, false),
            (f32::NEG_INFINITY, false),
            (f32::NAN, false),
        ] {
            let got = positive_or_nan(y);
            assert!(if keep { got == y } else { got.is_nan() }, "{y} gave {got}");
        }
        let z = [1.0f32, 2.0, 3.0];
        let mut out = [0.0f32; 3];
        affine(&z, &mut out, 3.0e38, 0.0);
        assert_eq!(out[0], 3.0e38);
        assert!(out[1].is_nan() && out[2].is_nan(), "{out:?}");
        ssra_row(&z, &mut out, &[0.0, 0.0, 3.0e38], 0.0, 1.0);
        assert_eq!(&out[..2], &[1.0, 1.0]);
        assert!(out[2].is_nan());
        affine_maps(&z, &mut out, &[1.0, f32::MAX, 1.0], &[0.0, 0.0, f32::MAX]);
        assert_eq!(out[0], 1.0);
        assert!(out[1].is_nan(), "{out:?}");
        assert_eq!(out[2], f32::MAX); // 3 + f32::MAX rounds to f32::MAX
    }
}
