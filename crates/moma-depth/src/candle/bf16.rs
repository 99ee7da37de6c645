//! bf16 linear layers on the CPU (`--dtype bf16`): `y = x·W + b` with `W` and each row of `x`
//! rounded to bfloat16 (to nearest, ties to even), products accumulated in `f32`.
//!
//! Kernel: AVX512-BF16 `vdpbf16ps` (32 multiply-adds of bf16 pairs into `f32` per instruction,
//! twice an `f32` FMA's) where the CPU has it, found at run time; a portable loop otherwise,
//! which adds the two products of each pair in the instruction's order (the odd element
//! first). A product of two bf16 values is exact in `f32`, so both give the same bits, except
//! for subnormal bf16 inputs, which the instruction reads as zero (and weights or activations
//! below 1.2e-38 do not occur in these networks). Every thread count gives the same bits: each
//! output is summed by one thread in one order. `gemm` has no bf16 kernel and candle's CPU
//! matmul has none either, hence this one.

/// Rows of `x` per micro-kernel call.
const MR: usize = 8;
/// Output columns per micro-kernel call (two 16-lane `f32` vectors).
const NR: usize = 32;

/// `x` rounded to bfloat16 (to nearest, ties to even; NaN stays NaN).
#[inline(always)]
pub(crate) fn to_bf16(x: f32) -> u16 {
    let b = x.to_bits();
    // both computed, then selected: a blend, which vectorises (a NaN's carry could reach the
    // exponent, hence the quiet-bit NaN)
    let rounded = (b.wrapping_add(0x7FFF + ((b >> 16) & 1)) >> 16) as u16;
    let nan = ((b >> 16) as u16) | 0x40;
    if x.is_nan() { nan } else { rounded }
}

/// The `f32` value of a bf16.
fn from_bf16(h: u16) -> f32 {
    f32::from_bits(u32::from(h) << 16)
}

/// A linear layer in bf16 (module documentation).
#[derive(Debug, Clone)]
pub(crate) struct Bf16Linear {
    k: usize,
    n: usize,
    /// `k` rounded up to a multiple of 2 (one `vdpbf16ps` lane takes a pair).
    kp: usize,
    /// `n` rounded up to a multiple of [`NR`].
    np: usize,
    /// `W` in blocks of 16 columns: block `jb` holds, for each pair of rows `kb`, 16 × 2
    /// values (`[j][kk]` = `W[2·kb + kk, 16·jb + j]`); zero outside `k × n`.
    packed: Vec<u16>,
    bias: Vec<f32>,
}

impl Bf16Linear {
    /// Rounds `weight_t` (`k × n`, row-major) to bf16 and keeps `bias` (`n`).
    ///
    /// # Errors
    /// Sizes that do not match; a weight that is not finite.
    pub(crate) fn new(
        weight_t: &[f32],
        k: usize,
        n: usize,
        bias: &[f32],
    ) -> candle_core::Result<Self> {
        if weight_t.len() != k * n || bias.len() != n || k == 0 || n == 0 {
            candle_core::bail!(
                "bf16 linear: weight of {} values for {k}×{n}, bias of {}",
                weight_t.len(),
                bias.len()
            );
        }
        if weight_t.iter().any(|w| !w.is_finite()) {
            candle_core::bail!("bf16 linear: the weights hold a value that is not finite");
        }
        let kp = k.div_ceil(2) * 2;
        let np = n.div_ceil(NR) * NR;
        let mut packed = vec![0u16; np * kp];
        for (i, row) in weight_t.chunks_exact(n).enumerate() {
            let at = (i / 2) * 32 + i % 2;
            for (j, &w) in row.iter().enumerate() {
                packed[(j / 16) * kp * 16 + at + (j % 16) * 2] = to_bf16(w);
            }
        }
        Ok(Self {
            k,
            n,
            kp,
            np,
            packed,
            bias: bias.to_vec(),
        })
    }

    /// `PackedLinear::run_chunk` with the fast kernel or (`fast` false) the portable one.
    fn run_chunk_with(
        &self,
        x: &[f32],
        rows: usize,
        residual: Option<&[f32]>,
        out: &mut [f32],
        fast: bool,
    ) {
        let (k, n, kp) = (self.k, self.n, self.kp);
        let padded = rows.div_ceil(MR) * MR;
        ROWS.with(|cell| {
            let mut a = cell.borrow_mut();
            if a.len() < padded * kp {
                a.resize(padded * kp, 0);
            }
            let a = &mut a[..padded * kp];
            a[rows * kp..].fill(0);
            for (row, a) in x.chunks_exact(k).zip(a.chunks_exact_mut(kp)) {
                round_row(row, &mut a[..k]);
                a[k..].fill(0);
            }
            let mut tile = [[0f32; NR]; MR];
            for jb2 in 0..self.np / NR {
                let w = &self.packed[jb2 * 2 * kp * 16..(jb2 + 1) * 2 * kp * 16];
                for r0 in (0..rows).step_by(MR) {
                    let ar = &a[r0 * kp..(r0 + MR) * kp];
                    if fast {
                        #[cfg(target_arch = "x86_64")]
                        // SAFETY: `has_bf16` found the features; `ar` holds MR rows of `kp`
                        // values and `w` two column blocks of `kp · 16`.
                        unsafe {
                            kernel_avx512(ar, w, kp, &mut tile);
                        }
                    } else {
                        kernel_portable(ar, w, kp, &mut tile);
                    }
                    let j0 = jb2 * NR;
                    let cols = NR.min(n.saturating_sub(j0));
                    for (r, t) in tile.iter().enumerate().take(rows - r0) {
                        let i = r0 + r;
                        let o = &mut out[i * n + j0..i * n + j0 + cols];
                        for ((o, &t), &b) in o.iter_mut().zip(&t[..cols]).zip(&self.bias[j0..]) {
                            *o = t + b;
                        }
                        if let Some(res) = residual {
                            for (o, &r) in o.iter_mut().zip(&res[i * n + j0..]) {
                                *o += r;
                            }
                        }
                    }
                }
            }
        });
    }
}

impl super::ops::PackedLinear for Bf16Linear {
    fn run_chunk(&self, x: &[f32], rows: usize, residual: Option<&[f32]>, out: &mut [f32]) {
        self.run_chunk_with(x, rows, residual, out, has_bf16());
    }

    fn pack(weight_t: &[f32], k: usize, n: usize, bias: &[f32]) -> candle_core::Result<Self> {
        Self::new(weight_t, k, n, bias)
    }

    /// Input features.
    fn in_features(&self) -> usize {
        self.k
    }

    /// Output features.
    fn out_features(&self) -> usize {
        self.n
    }
}

thread_local! {
    static ROWS: std::cell::RefCell<Vec<u16>> = const { std::cell::RefCell::new(Vec::new()) };
}

super::ops::simd_dispatch! {
    /// `row` rounded to bf16 into `a` (integer operations and a blend, which vectorise).
    fn round_row(row: &[f32], a: &mut [u16]) {
        for (a, &v) in a.iter_mut().zip(row) {
            *a = to_bf16(v);
        }
    }
}

/// Whether the CPU has AVX512-BF16 (with AVX512F), checked once.
pub(crate) fn has_bf16() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        static BF16: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
        *BF16.get_or_init(|| {
            std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512bf16")
        })
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// `acc[r][j] = Σ_k a[r, k] · w[k, j]` over [`MR`] rows of `a` and two packed column blocks
/// `w`, in `vdpbf16ps`'s order, without it.
fn kernel_portable(a: &[u16], w: &[u16], kp: usize, acc: &mut [[f32; NR]; MR]) {
    for (r, acc) in acc.iter_mut().enumerate() {
        *acc = [0.0; NR];
        let row = &a[r * kp..(r + 1) * kp];
        for (half, acc) in acc.chunks_exact_mut(16).enumerate() {
            let w = &w[half * kp * 16..(half + 1) * kp * 16];
            for (kb, a2) in row.chunks_exact(2).enumerate() {
                let (a0, a1) = (from_bf16(a2[0]), from_bf16(a2[1]));
                let w = &w[kb * 32..kb * 32 + 32];
                for (j, acc) in acc.iter_mut().enumerate() {
                    *acc += a1 * from_bf16(w[j * 2 + 1]);
                    *acc += a0 * from_bf16(w[j * 2]);
                }
            }
        }
    }
}

/// [`kernel_portable`] with `vdpbf16ps`.
///
/// # Safety
/// The CPU must have AVX512F and AVX512-BF16; `a` must hold [`MR`] · `kp` values and `w`
/// 2 · `kp` · 16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bf16")]
unsafe fn kernel_avx512(a: &[u16], w: &[u16], kp: usize, acc: &mut [[f32; NR]; MR]) {
    use std::arch::x86_64::*;
    debug_assert!(a.len() >= MR * kp && w.len() >= 2 * kp * 16);
    let mut s = [[_mm512_setzero_ps(); 2]; MR];
    let a = a.as_ptr();
    let w0 = w.as_ptr();
    // SAFETY: every read is inside `a` (row r < MR, value 2·kb + 1 < kp) and `w` (two blocks of
    // kp · 16 values), as the caller guarantees; `__m512bh` is 32 bf16 in 64 bytes, as
    // `__m512i`.
    unsafe {
        let w1 = w0.add(kp * 16);
        for kb in 0..kp / 2 {
            let b0: __m512bh = std::mem::transmute(_mm512_loadu_si512(w0.add(kb * 32).cast()));
            let b1: __m512bh = std::mem::transmute(_mm512_loadu_si512(w1.add(kb * 32).cast()));
            for (r, s) in s.iter_mut().enumerate() {
                let x: __m512bh = std::mem::transmute(_mm512_set1_epi32(
                    a.add(r * kp + kb * 2).cast::<i32>().read_unaligned(),
                ));
                s[0] = _mm512_dpbf16_ps(s[0], x, b0);
                s[1] = _mm512_dpbf16_ps(s[1], x, b1);
            }
        }
        for (acc, s) in acc.iter_mut().zip(&s) {
            _mm512_storeu_ps(acc.as_mut_ptr(), s[0]);
            _mm512_storeu_ps(acc.as_mut_ptr().add(16), s[1]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::candle::ops::{PACKED_CHUNK as CHUNK, PackedLinear};

    fn uniform(state: &mut u64) -> f32 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }

    #[test]
    fn rounding_to_bf16() {
        assert_eq!(to_bf16(1.0), 0x3F80);
        // 1 + 2⁻⁸ is halfway between 1 and 1 + 2⁻⁷: ties to even (1)
        assert_eq!(to_bf16(1.0 + 1.0 / 256.0), 0x3F80);
        // 1 + 3·2⁻⁸ is halfway between 1 + 2⁻⁷ and 1 + 2⁻⁶: ties to even (1 + 2⁻⁶)
        assert_eq!(to_bf16(1.0 + 3.0 / 256.0), 0x3F82);
        assert_eq!(from_bf16(to_bf16(-2.5)), -2.5);
        assert!(from_bf16(to_bf16(f32::NAN)).is_nan());
    }

    #[test]
    fn products_of_the_rounded_values_summed_in_f32() {
        let (m, k, n) = (13, 37, 45);
        let mut st = 3;
        let x: Vec<f32> = (0..m * k).map(|_| uniform(&mut st)).collect();
        let w: Vec<f32> = (0..k * n).map(|_| uniform(&mut st)).collect();
        let b: Vec<f32> = (0..n).map(|_| uniform(&mut st)).collect();
        let l = Bf16Linear::new(&w, k, n, &b).unwrap();
        let y = l.forward(&x, m, None);
        let r = |v: f32| f64::from(from_bf16(to_bf16(v)));
        for i in 0..m {
            for j in 0..n {
                let want: f64 = f64::from(b[j])
                    + (0..k)
                        .map(|t| r(x[i * k + t]) * r(w[t * n + j]))
                        .sum::<f64>();
                let got = f64::from(y[i * n + j]);
                // f32 summation of k exact products: k·ε·Σ|terms|
                let tol = 1e-6 * (k as f64) * (1.0 + want.abs());
                assert!((got - want).abs() < tol, "{i},{j}: {got} vs {want}");
            }
        }
        assert_eq!((l.in_features(), l.out_features()), (k, n));
    }

    #[test]
    fn avx512_and_portable_kernels_agree_bit_for_bit_on_any_thread_count() {
        let (m, k, n) = (150, 384, 96);
        let mut st = 9;
        let x: Vec<f32> = (0..m * k).map(|_| uniform(&mut st) * 3.0).collect();
        let w: Vec<f32> = (0..k * n).map(|_| uniform(&mut st) * 0.1).collect();
        let b: Vec<f32> = (0..n).map(|_| uniform(&mut st)).collect();
        let res: Vec<f32> = (0..m * n).map(|_| uniform(&mut st)).collect();
        let l = Bf16Linear::new(&w, k, n, &b).unwrap();
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| l.forward(&x, m, Some(&res)))
        };
        let one = run(1);
        assert_eq!(one, run(3));
        let mut portable = vec![0f32; m * n];
        for (c, out) in portable.chunks_mut(CHUNK * n).enumerate() {
            let rows = out.len() / n;
            l.run_chunk_with(
                &x[c * CHUNK * k..(c * CHUNK + rows) * k],
                rows,
                Some(&res[c * CHUNK * n..(c * CHUNK + rows) * n]),
                out,
                false,
            );
        }
        assert_eq!(one, portable, "AVX512-BF16 on this CPU: {}", has_bf16());
        assert!(Bf16Linear::new(&[f32::NAN], 1, 1, &[0.0]).is_err());
    }
}
