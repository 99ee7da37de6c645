//! Hot inner loops, written so that LLVM auto-vectorises them, compiled twice: for the baseline
//! target and (on x86-64) for AVX2+FMA, chosen at run time. Internal to the crate.

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
pub(crate) use multiversion;

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
            *o = x * s + t;
        }
    }
}

multiversion! {
    /// `out[j] = z[j]·(col[j] + r) + t` (SSRA row).
    pub(crate) fn ssra_row(z: &[f32], out: &mut [f32], col: &[f32], r: f32, t: f32) {
        let n = out.len().min(z.len()).min(col.len());
        let (z, out, col) = (&z[..n], &mut out[..n], &col[..n]);
        for j in 0..n {
            out[j] = z[j] * (col[j] + r) + t;
        }
    }
}

multiversion! {
    /// `out[j] = z[j]·s[j] + t[j]` (LWLR maps).
    pub(crate) fn affine_maps(z: &[f32], out: &mut [f32], s: &[f32], t: &[f32]) {
        let n = out.len().min(z.len()).min(s.len()).min(t.len());
        let (z, out, s, t) = (&z[..n], &mut out[..n], &s[..n], &t[..n]);
        for j in 0..n {
            out[j] = z[j] * s[j] + t[j];
        }
    }
}

/// Column block of the LWLR sums kernel (f64 lanes); the weight table rows are padded to it.
pub(crate) const LWLR_BLOCK: usize = 8;

multiversion! {
    /// The five LWLR weighted sums of one image row, for every (padded) column `j`:
    /// `sums[m][j] = Σ_k coef[k][m] · wu[k·stride + j]`, where `coef[k] = wv_k·(1, x_k, x_k², y_k, x_k·y_k)`
    /// and `wu[k·stride + j] = exp(−(j − u_k)²/(2b²))`. `stride` is a multiple of [`LWLR_BLOCK`];
    /// each `sums[m]` has length `stride`.
    pub(crate) fn lwlr_row_sums(wu: &[f64], stride: usize, coef: &[[f64; 5]], sums: &mut [Vec<f64>; 5]) {
        const B: usize = LWLR_BLOCK;
        let mut j0 = 0;
        while j0 + B <= stride {
            let mut acc = [[0.0f64; B]; 5];
            for (k, c) in coef.iter().enumerate() {
                let w: &[f64; B] = wu[k * stride + j0..k * stride + j0 + B].try_into().unwrap_or(&[0.0; B]);
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
}
