//! Small numerical kernels of the candle backend.

use candle_core::{CpuStorage, CustomOp1, CustomOp3, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// A zeroed `Vec<f32>` of `len`, zeroed in parallel (chunks of 64 Ki values).
///
/// `vec![0f32; len]` is one `memset` on the calling thread for memory the allocator reuses
/// (moma keeps freed memory: `candle/heap.rs`), while the other threads wait for the kernel
/// that then overwrites it: 3.8–4.5 % of an int8 ViT-S frame's samples, serial. Written by
/// hand because neither `Vec` nor rayon has a parallel zeroed allocation.
pub(crate) fn zeroed(len: usize) -> Vec<f32> {
    const CHUNK: usize = 1 << 16;
    if len <= CHUNK {
        return vec![0f32; len];
    }
    let mut v: Vec<f32> = Vec::with_capacity(len);
    v.spare_capacity_mut()[..len]
        .par_chunks_mut(CHUNK)
        .for_each(|c| c.fill(std::mem::MaybeUninit::new(0.0)));
    // SAFETY: the capacity is at least `len` and every one of the first `len` values was
    // written (initialised to 0.0) above.
    unsafe { v.set_len(len) };
    v
}

/// LayerNorm over the last dimension: `(x − mean) / sqrt(var + eps) · weight + bias`.
///
/// On the CPU a two-pass kernel (mean, then centred variance, in `f32`), parallel over rows:
/// `candle_nn::ops::layer_norm` uses `E[x²] − mean²`, which loses digits on the large-norm tokens
/// of real DINOv2 checkpoints. Other devices use `candle_nn::ops::layer_norm`, always in `f32`
/// (f16/bf16/f64 are converted there and back: squares of large-norm tokens overflow f16).
///
/// # Errors
/// Shape or dtype errors.
pub(crate) fn layer_norm(xs: &Tensor, weight: &Tensor, bias: &Tensor, eps: f32) -> Result<Tensor> {
    use candle_core::DType;
    if xs.device().is_cpu() && xs.dtype() == DType::F32 {
        let xs = xs.contiguous()?;
        xs.apply_op3_no_bwd(weight, bias, &TwoPassLayerNorm { eps })
    } else if xs.dtype() == DType::F32 {
        candle_nn::ops::layer_norm(xs, weight, bias, eps)
    } else {
        let f32 = |t: &Tensor| t.to_dtype(DType::F32);
        candle_nn::ops::layer_norm(&f32(xs)?, &f32(weight)?, &f32(bias)?, eps)?.to_dtype(xs.dtype())
    }
}

struct TwoPassLayerNorm {
    eps: f32,
}

fn contiguous<'a>(s: &'a CpuStorage, l: &Layout) -> Result<&'a [f32]> {
    let s = s.as_slice::<f32>()?;
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&s[a..b]),
        None => candle_core::bail!("layer-norm: operand must be contiguous"),
    }
}

impl CustomOp3 for TwoPassLayerNorm {
    fn name(&self) -> &'static str {
        "two-pass-layer-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let src = contiguous(s1, l1)?;
        let weight = contiguous(s2, l2)?;
        let bias = contiguous(s3, l3)?;
        let dim = l1.dims().last().copied().unwrap_or(1);
        if weight.len() != dim || bias.len() != dim {
            candle_core::bail!(
                "layer-norm: weight/bias length {} vs dim {dim}",
                weight.len()
            );
        }
        let mut dst = zeroed(src.len());
        let eps = self.eps;
        dst.par_chunks_mut(16 * dim)
            .zip(src.par_chunks(16 * dim))
            .for_each(|(d, s)| {
                for (d, s) in d.chunks_exact_mut(dim).zip(s.chunks_exact(dim)) {
                    layer_norm_row(s, weight, bias, eps, d);
                }
            });
        Ok((CpuStorage::F32(dst), l1.shape().clone()))
    }
}

simd_dispatch! {
    /// One row of [`layer_norm`]: the mean, then the variance of the deviations (two passes),
    /// each summed in 16 lanes (vectorises; a sequential sum was 3 % of an int8 ViT-S frame).
    fn layer_norm_row(s: &[f32], weight: &[f32], bias: &[f32], eps: f32, d: &mut [f32]) {
        let n = s.len() as f32;
        let mut acc = [0f32; 16];
        let mut chunks = s.chunks_exact(16);
        for c in &mut chunks {
            for l in 0..16 {
                acc[l] += c[l];
            }
        }
        let mean = (acc.iter().sum::<f32>() + chunks.remainder().iter().sum::<f32>()) / n;
        let mut acc = [0f32; 16];
        let mut chunks = s.chunks_exact(16);
        for c in &mut chunks {
            for l in 0..16 {
                let t = c[l] - mean;
                acc[l] += t * t;
            }
        }
        let rest: f32 = chunks.remainder().iter().map(|&v| (v - mean) * (v - mean)).sum();
        let var = (acc.iter().sum::<f32>() + rest) / n;
        let inv = 1.0 / (var + eps).sqrt();
        for ((o, v), (w, b)) in d.iter_mut().zip(s).zip(weight.iter().zip(bias)) {
            *o = (v - mean) * inv * w + b;
        }
    }
}

/// Implements candle's `CustomOp2` (no residual) and `CustomOp3` (third operand = residual) for an
/// op with `fn run(&self, x, x_layout, w, w_layout, residual: Option<&[f32]>)` on contiguous `f32`.
macro_rules! residual_op {
    ($ty:ident, $name:literal, $name_residual:literal) => {
        impl candle_core::CustomOp2 for $ty<'_> {
            fn name(&self) -> &'static str {
                $name
            }

            fn cpu_fwd(
                &self,
                s1: &CpuStorage,
                l1: &Layout,
                s2: &CpuStorage,
                l2: &Layout,
            ) -> Result<(CpuStorage, Shape)> {
                self.run(contiguous(s1, l1)?, l1, contiguous(s2, l2)?, l2, None)
            }
        }

        impl CustomOp3 for $ty<'_> {
            fn name(&self) -> &'static str {
                $name_residual
            }

            fn cpu_fwd(
                &self,
                s1: &CpuStorage,
                l1: &Layout,
                s2: &CpuStorage,
                l2: &Layout,
                s3: &CpuStorage,
                l3: &Layout,
            ) -> Result<(CpuStorage, Shape)> {
                let r = contiguous(s3, l3)?;
                self.run(contiguous(s1, l1)?, l1, contiguous(s2, l2)?, l2, Some(r))
            }
        }
    };
}

/// A strided `f32` matrix operand of [`sgemm`]: element `(i, j)` at `ptr + i·rs + j·cs`.
#[derive(Clone, Copy)]
pub(super) struct MatRef {
    pub(super) ptr: *const f32,
    pub(super) rs: isize,
    pub(super) cs: isize,
}

/// `dst (m×n, row stride dst_rs) = [dst +] lhs (m×k) · rhs (k×n)` with the `gemm` crate
/// (candle's own CPU matmul backend), multi-threaded on rayon when `parallel`.
///
/// # Safety
/// Every element addressed by the operands must be valid; `dst` must not alias `lhs`/`rhs`.
#[allow(clippy::too_many_arguments)]
pub(super) unsafe fn sgemm(
    m: usize,
    n: usize,
    k: usize,
    dst: *mut f32,
    dst_rs: isize,
    accumulate: bool,
    lhs: MatRef,
    rhs: MatRef,
    parallel: bool,
) {
    let par = if parallel {
        gemm::Parallelism::Rayon(0)
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: forwarded to the caller.
    unsafe {
        gemm::gemm(
            m, n, k, dst, 1, dst_rs, accumulate, lhs.ptr, lhs.cs, lhs.rs, rhs.ptr, rhs.cs, rhs.rs,
            1.0, 1.0, false, false, false, par,
        );
    }
}

/// A raw output pointer shared by parallel tasks that write disjoint elements.
#[derive(Clone, Copy)]
pub(super) struct SendPtr(pub(super) *mut f32);
impl SendPtr {
    /// The pointer (a method, so that closures capture the whole `Sync` wrapper).
    pub(super) fn get(self) -> *mut f32 {
        self.0
    }
}

// SAFETY: only used for disjoint writes from rayon tasks.
unsafe impl Send for SendPtr {}
// SAFETY: as above.
unsafe impl Sync for SendPtr {}

/// Defines `fn $name(args)` whose body is compiled twice, for baseline x86-64 and for AVX2+FMA,
/// and dispatched at run time (the crate is built for baseline x86-64; the FMA feature does not
/// change results: Rust never contracts `a·b + c`).
macro_rules! simd_dispatch {
    ($(#[$m:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block) => {
        $(#[$m])*
        #[allow(clippy::too_many_arguments)]
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            #[allow(clippy::too_many_arguments)]
            fn generic($($arg: $ty),*) $(-> $ret)? $body
            #[cfg(target_arch = "x86_64")]
            {
                // 16 lanes per instruction; the source fixes every sum's order, so each
                // variant gives the same bits
                #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx2,fma")]
                #[allow(clippy::too_many_arguments)]
                fn avx512($($arg: $ty),*) $(-> $ret)? {
                    generic($($arg),*)
                }
                if std::arch::is_x86_feature_detected!("avx512f")
                    && std::arch::is_x86_feature_detected!("avx512bw")
                    && std::arch::is_x86_feature_detected!("avx512vl")
                {
                    // SAFETY: the CPU has the features `avx512` was compiled for (AVX-512
                    // implies AVX2 and FMA).
                    return unsafe { avx512($($arg),*) };
                }
                #[target_feature(enable = "avx2,fma")]
                #[allow(clippy::too_many_arguments)]
                fn avx2($($arg: $ty),*) $(-> $ret)? {
                    generic($($arg),*)
                }
                if std::arch::is_x86_feature_detected!("avx2")
                    && std::arch::is_x86_feature_detected!("fma")
                {
                    // SAFETY: the CPU has the features `avx2` was compiled for.
                    return unsafe { avx2($($arg),*) };
                }
            }
            generic($($arg),*)
        }
    };
}
/// For the int8 and bf16 kernels' row loops.
pub(crate) use simd_dispatch;

simd_dispatch! {
    /// Unnormalised softmax: each length-`n` row of `s` becomes `exp(scale · (row − max row))`
    /// and `inv` receives `1 / Σ row` (applied by the caller after the `· v` product).
    fn exp_rows(s: &mut [f32], n: usize, scale: f32, inv: &mut [f32]) {
        for (row, inv) in s.chunks_exact_mut(n).zip(inv.iter_mut()) {
            let max = row_max(row);
            let mut acc = [0f32; 16];
            let mut chunks = row.chunks_exact_mut(16);
            for c in &mut chunks {
                for i in 0..16 {
                    let e = exp_f32((c[i] - max) * scale);
                    c[i] = e;
                    acc[i] += e;
                }
            }
            let mut rest = 0f32;
            for o in chunks.into_remainder() {
                *o = exp_f32((*o - max) * scale);
                rest += *o;
            }
            *inv = 1.0 / (acc.iter().sum::<f32>() + rest);
        }
    }
}

simd_dispatch! {
    /// The int8 attention's softmax, straight into bytes: each length-`n` row of the scores
    /// `s` becomes `q = round(255 · exp(scale · (row − max row)))` (in [0, 255], 255 at the
    /// row's max: the scale of the probabilities is known without a pass over them) in rows of
    /// `kp` bytes (the rest zero), and `inv` receives `255 / Σ q`, so that the quantised
    /// weights sum to one. One pass after the row maximum: no `f32` probabilities are written.
    ///
    /// `255 · exp(x) = 255 · 2ʸ`, `y = x·log₂e = n + f` with `n` an integer and `|f| ≤ ½`:
    /// `2ⁿ` built in the exponent bits (as [`exp_f32`]) times a degree-4 polynomial for
    /// `255 · 2ᶠ` (least squares in the relative error at Chebyshev points: ≤ 2.7e-6, 0.0007
    /// of a level at 255, where [`exp_f32`]'s degree 6 serves f32 outputs). `y` is clamped at
    /// −16 (`255 · 2⁻¹⁶` rounds to 0; `2ⁿ` stays normal); `y ≤ 0`, and the polynomial keeps
    /// `255 · 2ᶠ` below 255.5 at `f = 0`, so a byte never wraps.
    pub(crate) fn softmax_u8(s: &[f32], n: usize, scale: f32, q: &mut [u8], kp: usize, inv: &mut [f32]) {
        const C: [f32; 5] = [
            254.999_79,
            176.746_1,
            61.2637,
            14.258_845,
            2.43793,
        ];
        // adding 1.5·2²³ rounds to an integer held in the low mantissa bits (to nearest, ties
        // to even); read with a mask, unlike a float-to-int cast this vectorises
        const ROUND: f32 = 12_582_912.0;
        let k = scale * std::f32::consts::LOG2_E;
        for ((row, q), inv) in s.chunks_exact(n).zip(q.chunks_exact_mut(kp)).zip(inv.iter_mut()) {
            let (q, pad) = q.split_at_mut(n);
            pad.fill(0);
            // v·k ≤ max·k for v ≤ max (rounding is monotone): y ≤ 0, and 0 at the maximum
            let top = row_max(row) * k;
            let mut sum = 0u32;
            for (o, &v) in q.iter_mut().zip(row) {
                let y = v * k - top;
                let y = if y < -16.0 { -16.0 } else { y };
                let t = y + ROUND;
                let f = y - (t - ROUND);
                let p = C[0] + f * (C[1] + f * (C[2] + f * (C[3] + f * C[4])));
                let pow2n = f32::from_bits(t.to_bits().wrapping_add(127) << 23);
                let b = (p * pow2n + ROUND).to_bits() & 0xFF;
                *o = b as u8;
                sum += b;
            }
            *inv = 255.0 / sum.max(1) as f32;
        }
    }
}

/// Row-wise `softmax(scale · row)` in place on the length-`n` rows of `s` ([`exp_rows`], then
/// each row times its `1 / Σ`): the probabilities the training attention's backward recomputes.
pub(crate) fn softmax_rows_in_place(s: &mut [f32], n: usize, scale: f32) {
    let rows = s.len() / n.max(1);
    let mut inv = vec![0f32; rows];
    exp_rows(s, n, scale, &mut inv);
    for (row, f) in s.chunks_exact_mut(n).zip(inv) {
        for v in row {
            *v *= f;
        }
    }
}

simd_dispatch! {
    /// In-place exact GELU, `0.5·x·(1 + erf(x/√2))`.
    fn gelu_in_place(d: &mut [f32]) {
        for o in d.iter_mut() {
            let v = *o;
            *o = 0.5 * v * (1.0 + erf_f32(v * std::f32::consts::FRAC_1_SQRT_2));
        }
    }
}

simd_dispatch! {
    /// `g ← g · GELU'(x)`, `GELU'(x) = Φ(x) + x·φ(x)` with the erf and exp of [`gelu_in_place`].
    fn gelu_grad_in_place(x: &[f32], g: &mut [f32]) {
        const INV_SQRT_2PI: f32 = 0.398_942_3;
        for (o, &v) in g.iter_mut().zip(x) {
            let cdf = 0.5 * (1.0 + erf_f32(v * std::f32::consts::FRAC_1_SQRT_2));
            let pdf = INV_SQRT_2PI * exp_f32(-0.5 * v * v);
            *o *= cdf + v * pdf;
        }
    }
}

/// In-place exact GELU on `f32` values, parallel over chunks (the training network's GELU).
pub(crate) fn gelu_f32_in_place(d: &mut [f32]) {
    d.par_chunks_mut(16 * 1024).for_each(gelu_in_place);
}

/// `g ← g · GELU'(x)` on `f32` values, parallel over chunks (the training GELU's backward).
pub(crate) fn gelu_grad_f32_in_place(x: &[f32], g: &mut [f32]) {
    g.par_chunks_mut(16 * 1024)
        .zip(x.par_chunks(16 * 1024))
        .for_each(|(g, x)| gelu_grad_in_place(x, g));
}

/// Activation applied in place to the output of [`linear`].
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub(crate) enum Activation {
    None,
    GeluErf,
}

/// `[residual +] act(xs · weight_t + bias)` for `xs (m, k)`, `weight_t (k, n)`, `bias (n)` and
/// `residual (m, n)`. CPU f32: one `gemm` call accumulating into the bias (and residual) rows,
/// the activation in place; other devices: candle ops.
///
/// # Errors
/// Shape or dtype errors.
pub(crate) fn linear(
    xs: &Tensor,
    weight_t: &Tensor,
    bias: &Tensor,
    residual: Option<&Tensor>,
    act: Activation,
) -> Result<Tensor> {
    if !(xs.device().is_cpu() && xs.dtype() == candle_core::DType::F32) {
        let mut y = xs.matmul(weight_t)?.broadcast_add(bias)?;
        if act == Activation::GeluErf {
            y = y.gelu_erf()?;
        }
        return match residual {
            Some(r) => r + y,
            None => Ok(y),
        };
    }
    let bias_v = bias.to_vec1::<f32>()?;
    let op = LinearOp { bias: &bias_v, act };
    let xs = xs.contiguous()?;
    let w = weight_t.contiguous()?;
    match residual {
        Some(r) => xs.apply_op3_no_bwd(&w, &r.contiguous()?, &op),
        None => xs.apply_op2_no_bwd(&w, &op),
    }
}

struct LinearOp<'a> {
    bias: &'a [f32],
    act: Activation,
}

impl LinearOp<'_> {
    fn run(
        &self,
        x: &[f32],
        lx: &Layout,
        w: &[f32],
        lw: &Layout,
        residual: Option<&[f32]>,
    ) -> Result<(CpuStorage, Shape)> {
        let (m, k) = lx.shape().dims2()?;
        let (wk, n) = lw.shape().dims2()?;
        if wk != k || self.bias.len() != n || residual.is_some_and(|r| r.len() != m * n) {
            candle_core::bail!("linear: x {:?}, w {:?}", lx.dims(), lw.dims());
        }
        let mut dst: Vec<f32> = Vec::with_capacity(m * n);
        match residual {
            Some(r) => {
                for row in r.chunks_exact(n) {
                    dst.extend(row.iter().zip(self.bias).map(|(a, b)| a + b));
                }
            }
            None => {
                for _ in 0..m {
                    dst.extend_from_slice(self.bias);
                }
            }
        }
        // SAFETY: shapes checked above; dst is a fresh buffer.
        unsafe {
            sgemm(
                m,
                n,
                k,
                dst.as_mut_ptr(),
                n as isize,
                true,
                MatRef {
                    ptr: x.as_ptr(),
                    rs: k as isize,
                    cs: 1,
                },
                MatRef {
                    ptr: w.as_ptr(),
                    rs: n as isize,
                    cs: 1,
                },
                true,
            );
        }
        if self.act == Activation::GeluErf {
            dst.par_chunks_mut(16 * 1024).for_each(gelu_in_place);
        }
        Ok((CpuStorage::F32(dst), Shape::from_dims(&[m, n])))
    }
}

residual_op!(LinearOp, "fused-linear", "fused-linear-residual");

/// A linear layer packed for a low-precision CPU kernel (`--dtype int8|bf16`): weights `W`
/// (`k × n`) and bias `b` fixed at load time, or at run time for the attention's `kᵀ` and `v`.
/// Rows of `x` per task of [`PackedLinear::forward`]: each quantises its rows once and runs
/// them against every column block, so that a block's packed weights are reused from cache.
pub(crate) const PACKED_CHUNK: usize = 64;

pub(crate) trait PackedLinear: Send + Sync + std::fmt::Debug {
    /// Packs `weight_t` (`k × n`, row-major: `x·weight_t`) and `bias` (`n`).
    ///
    /// # Errors
    /// Sizes that do not match; weights that are not finite.
    fn pack(weight_t: &[f32], k: usize, n: usize, bias: &[f32]) -> Result<Self>
    where
        Self: Sized;
    /// [`Self::pack`] of `Xᵀ` (`k × n`), zero bias, where row `j < n` of `X` is
    /// `src[j·stride..][..k]`: an attention head's `kᵀ` straight from the `qkv` rows.
    ///
    /// # Errors
    /// As [`Self::pack`].
    fn pack_transposed_rows(src: &[f32], stride: usize, n: usize, k: usize) -> Result<Self>
    where
        Self: Sized,
    {
        let xt: Vec<f32> = (0..k)
            .flat_map(|d| (0..n).map(move |j| src[j * stride + d]))
            .collect();
        Self::pack(&xt, k, n, &vec![0.0; n])
    }
    /// [`Self::pack`] of `X` (`k × n`), zero bias, where row `i < k` of `X` is
    /// `src[i·stride..][..n]`: an attention head's `v` straight from the `qkv` rows.
    ///
    /// # Errors
    /// As [`Self::pack`].
    fn pack_rows(src: &[f32], stride: usize, k: usize, n: usize) -> Result<Self>
    where
        Self: Sized,
    {
        let x: Vec<f32> = (0..k)
            .flat_map(|i| src[i * stride..i * stride + n].iter().copied())
            .collect();
        Self::pack(&x, k, n, &vec![0.0; n])
    }
    /// `k`.
    fn in_features(&self) -> usize;
    /// `n`.
    fn out_features(&self) -> usize;
    /// `[residual +] x·W + b` for at most [`PACKED_CHUNK`] rows `x` (`rows × k`) into `out`
    /// (`rows × n`), on the calling thread, with the CPU's fastest kernel.
    fn run_chunk(&self, x: &[f32], rows: usize, residual: Option<&[f32]>, out: &mut [f32]);
    /// `[residual +] x·W + b` for `x` (`m × k`, row-major), parallel over chunks of
    /// [`PACKED_CHUNK`] rows (each output is summed by one thread in one order: the same bits
    /// on every thread count).
    fn forward(&self, x: &[f32], m: usize, residual: Option<&[f32]>) -> Vec<f32> {
        self.forward_act(x, m, residual, Activation::None)
    }
    /// [`Self::forward`], then `act` on each chunk while it is in cache.
    fn forward_act(
        &self,
        x: &[f32],
        m: usize,
        residual: Option<&[f32]>,
        act: Activation,
    ) -> Vec<f32> {
        let (k, n) = (self.in_features(), self.out_features());
        debug_assert_eq!(x.len(), m * k);
        let mut out = zeroed(m * n);
        out.par_chunks_mut(PACKED_CHUNK * n)
            .enumerate()
            .for_each(|(c, out)| {
                let rows = out.len() / n;
                let x = &x[c * PACKED_CHUNK * k..(c * PACKED_CHUNK + rows) * k];
                let residual =
                    residual.map(|r| &r[c * PACKED_CHUNK * n..(c * PACKED_CHUNK + rows) * n]);
                self.run_chunk(x, rows, residual, out);
                if act == Activation::GeluErf {
                    gelu_in_place(out);
                }
            });
        out
    }
    /// `x·W + b` on the calling thread (for callers that are already parallel) into `out`
    /// (`m × n`).
    fn forward_serial(&self, x: &[f32], m: usize, out: &mut [f32]) {
        let (k, n) = (self.in_features(), self.out_features());
        for (c, out) in out[..m * n].chunks_mut(PACKED_CHUNK * n).enumerate() {
            let rows = out.len() / n;
            let x = &x[c * PACKED_CHUNK * k..(c * PACKED_CHUNK + rows) * k];
            self.run_chunk(x, rows, None, out);
        }
    }
    /// `out = exp(scale · (s − max s))·W` for rows `s` (`rows × k`) of attention scores, the
    /// unnormalised softmax ([`exp_rows`]; `s` is overwritten), with `inv` receiving the
    /// factor that normalises each row of `out`.
    fn weigh_scores(
        &self,
        s: &mut [f32],
        rows: usize,
        scale: f32,
        out: &mut [f32],
        inv: &mut [f32],
    ) {
        exp_rows(s, self.in_features(), scale, inv);
        self.forward_serial(s, rows, out);
    }
}

/// `[residual +] act(xs · W + b)` with a packed low-precision layer: `xs (m, k)` f32 on the
/// CPU, `residual (m, n)`.
///
/// # Errors
/// Shape errors; another device or dtype than f32 on the CPU.
pub(crate) fn linear_packed(
    xs: &Tensor,
    layer: &dyn PackedLinear,
    residual: Option<&Tensor>,
    act: Activation,
) -> Result<Tensor> {
    if !(xs.device().is_cpu() && xs.dtype() == candle_core::DType::F32) {
        candle_core::bail!("int8 and bf16 linear layers run on the CPU in f32");
    }
    let op = PackedLinearOp { layer, act };
    let xs = xs.contiguous()?;
    match residual {
        Some(r) => xs.apply_op2_no_bwd(&r.contiguous()?, &op),
        None => xs.apply_op1_no_bwd(&op),
    }
}

struct PackedLinearOp<'a> {
    layer: &'a dyn PackedLinear,
    act: Activation,
}

impl PackedLinearOp<'_> {
    fn run(&self, x: &[f32], lx: &Layout, residual: Option<&[f32]>) -> Result<(CpuStorage, Shape)> {
        let (m, k) = lx.shape().dims2()?;
        let n = self.layer.out_features();
        if k != self.layer.in_features() || residual.is_some_and(|r| r.len() != m * n) {
            candle_core::bail!(
                "packed linear: x {:?} for a {}×{n} layer",
                lx.dims(),
                self.layer.in_features()
            );
        }
        let dst = self.layer.forward_act(x, m, residual, self.act);
        Ok((CpuStorage::F32(dst), Shape::from_dims(&[m, n])))
    }
}

impl CustomOp1 for PackedLinearOp<'_> {
    fn name(&self) -> &'static str {
        "packed-linear"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        self.run(contiguous(s, l)?, l, None)
    }
}

impl candle_core::CustomOp2 for PackedLinearOp<'_> {
    fn name(&self) -> &'static str {
        "packed-linear-residual"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        self.run(contiguous(s1, l1)?, l1, Some(contiguous(s2, l2)?))
    }
}

/// `w · x + bias` with the bias per output row: `w (m, k)`, `x (k, n)` (or, with `x_t`, `x` given
/// as `(n, k)` and read transposed), `bias (m)`. The 1×1 convolutions of the DPT head. CPU f32:
/// one `gemm` accumulating into the bias rows; other devices: candle ops.
///
/// # Errors
/// Shape or dtype errors.
pub(crate) fn matmul_row_bias(w: &Tensor, x: &Tensor, bias: &Tensor, x_t: bool) -> Result<Tensor> {
    if !(x.device().is_cpu() && x.dtype() == candle_core::DType::F32) {
        let x = if x_t { x.t()? } else { x.clone() };
        return w.matmul(&x)?.broadcast_add(&bias.reshape(((), 1))?);
    }
    let bias = bias.flatten_all()?.to_vec1::<f32>()?;
    w.contiguous()?
        .apply_op2_no_bwd(&x.contiguous()?, &MatmulRowBias { bias: &bias, x_t })
}

struct MatmulRowBias<'a> {
    bias: &'a [f32],
    x_t: bool,
}

impl candle_core::CustomOp2 for MatmulRowBias<'_> {
    fn name(&self) -> &'static str {
        "matmul-row-bias"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (w, x) = (contiguous(s1, l1)?, contiguous(s2, l2)?);
        let (m, k) = l1.shape().dims2()?;
        let (a, b) = l2.shape().dims2()?;
        let (xk, n) = if self.x_t { (b, a) } else { (a, b) };
        if xk != k || self.bias.len() != m {
            candle_core::bail!("matmul-row-bias: w {:?}, x {:?}", l1.dims(), l2.dims());
        }
        let mut dst: Vec<f32> = Vec::with_capacity(m * n);
        for &b in self.bias {
            dst.extend(std::iter::repeat_n(b, n));
        }
        let (rs, cs) = if self.x_t {
            (1, k as isize)
        } else {
            (n as isize, 1)
        };
        // SAFETY: shapes checked above.
        unsafe {
            sgemm(
                m,
                n,
                k,
                dst.as_mut_ptr(),
                n as isize,
                true,
                MatRef {
                    ptr: w.as_ptr(),
                    rs: k as isize,
                    cs: 1,
                },
                MatRef {
                    ptr: x.as_ptr(),
                    rs,
                    cs,
                },
                true,
            );
        }
        Ok((CpuStorage::F32(dst), Shape::from_dims(&[m, n])))
    }
}

/// Query rows per task of [`attention`] (bounds the per-task score block to `rows × tokens`).
const ATTN_ROWS: usize = 64;

thread_local! {
    static SCORES: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Multi-head attention core on the fused `qkv (N, 3C)` projection (PyTorch layout
/// `reshape(N, 3, heads, hd)`): `softmax(scale · q·kᵀ) · v` per head, heads concatenated to
/// `(N, C)`. CPU f32: parallel over (head, block of query rows), each score block computed,
/// normalised and consumed in cache and written straight into its column block of the output;
/// other devices: candle ops.
///
/// # Errors
/// Shape or dtype errors.
pub(crate) fn attention(qkv: &Tensor, num_heads: usize, scale: f32) -> Result<Tensor> {
    let (_, c3) = qkv.dims2()?;
    let c = c3 / 3;
    let hd = c / num_heads;
    if !(qkv.device().is_cpu() && qkv.dtype() == candle_core::DType::F32) {
        // All heads in one batched matmul: (n, 3c) -> (3, heads, n, hd).
        let n = qkv.dim(0)?;
        let qkv = qkv.reshape((n, 3, num_heads, hd))?.permute((1, 2, 0, 3))?;
        let q = qkv.get(0)?.contiguous()?;
        let k_t = qkv.get(1)?.transpose(1, 2)?.contiguous()?;
        let v = qkv.get(2)?.contiguous()?;
        let out = softmax_last_dim(&q.matmul(&k_t)?, scale)?.matmul(&v)?;
        return out.transpose(0, 1)?.reshape((n, c));
    }
    qkv.contiguous()?
        .apply_op1_no_bwd(&AttentionOp { num_heads, scale })
}

/// [`attention`]'s CPU f32 kernel on one contiguous `(n, 3c)` slice → `(n, c)` (the training
/// network's memory-light attention, which recomputes the probabilities in its backward).
///
/// # Errors
/// Shape errors.
pub(crate) fn attention_cpu_f32(
    qkv: &[f32],
    n: usize,
    num_heads: usize,
    scale: f32,
) -> Result<Vec<f32>> {
    if n == 0 || !qkv.len().is_multiple_of(n) {
        candle_core::bail!("attention: {} values are not {n} rows", qkv.len());
    }
    let storage = CpuStorage::F32(qkv.to_vec());
    let layout = Layout::contiguous((n, qkv.len() / n));
    match (AttentionOp { num_heads, scale })
        .cpu_fwd(&storage, &layout)?
        .0
    {
        CpuStorage::F32(v) => Ok(v),
        _ => candle_core::bail!("attention: f32 kernel returned another dtype"),
    }
}

/// Tokens `n`, channels `c` and head size of a fused `(n, 3c)` qkv for `heads` heads.
///
/// # Errors
/// A shape that is not `(n ≥ 1, 3c)` with `c` a multiple of `heads`.
fn qkv_dims(layout: &Layout, heads: usize) -> Result<(usize, usize, usize)> {
    let (n, c3) = layout.shape().dims2()?;
    let c = c3 / 3;
    if c3 % 3 != 0 || heads == 0 || c % heads != 0 || n == 0 {
        candle_core::bail!("attention: qkv {:?}, {heads} heads", layout.dims());
    }
    Ok((n, c, c / heads))
}

struct AttentionOp {
    num_heads: usize,
    scale: f32,
}

impl CustomOp1 for AttentionOp {
    fn name(&self) -> &'static str {
        "fused-attention"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let qkv = contiguous(storage, layout)?;
        let heads = self.num_heads;
        let (n, c, hd) = qkv_dims(layout, heads)?;
        let c3 = 3 * c;
        let mut dst = zeroed(n * c);
        let out = SendPtr(dst.as_mut_ptr());
        // kᵀ of every head, (heads, hd, n) contiguous: gemm then reads it without repacking it
        // for every block of query rows.
        let mut kt = vec![0f32; heads * hd * n];
        kt.par_chunks_mut(n).enumerate().for_each(|(hd_i, row)| {
            let off = c + hd_i; // hd_i = h·hd + d: column of k in qkv
            for (j, o) in row.iter_mut().enumerate() {
                *o = qkv[j * c3 + off];
            }
        });
        let blocks = n.div_ceil(ATTN_ROWS);
        let scale = self.scale;
        (0..heads * blocks).into_par_iter().for_each(|t| {
            let (h, b) = (t / blocks, t % blocks);
            let r0 = b * ATTN_ROWS;
            let rows = ATTN_ROWS.min(n - r0);
            SCORES.with(|cell| {
                let mut s = cell.borrow_mut();
                if s.len() < rows * n {
                    s.resize(rows * n, 0.0);
                }
                let s = &mut s[..rows * n];
                let base = qkv.as_ptr();
                // SAFETY: all offsets stay inside qkv (n × 3c), the score block and the output
                // rows r0..r0+rows, columns h·hd.. of dst, which no other task writes.
                unsafe {
                    // scores = q[r0.., h] · k[:, h]ᵀ
                    sgemm(
                        rows,
                        n,
                        hd,
                        s.as_mut_ptr(),
                        n as isize,
                        false,
                        MatRef {
                            ptr: base.add(r0 * c3 + h * hd),
                            rs: c3 as isize,
                            cs: 1,
                        },
                        MatRef {
                            ptr: kt.as_ptr().add(h * hd * n),
                            rs: n as isize,
                            cs: 1,
                        },
                        false,
                    );
                }
                let mut inv = [0f32; ATTN_ROWS];
                exp_rows(s, n, scale, &mut inv[..rows]);
                // SAFETY: as above.
                unsafe {
                    sgemm(
                        rows,
                        hd,
                        n,
                        out.get().add(r0 * c + h * hd),
                        c as isize,
                        false,
                        MatRef {
                            ptr: s.as_ptr(),
                            rs: n as isize,
                            cs: 1,
                        },
                        MatRef {
                            ptr: base.add(2 * c + h * hd),
                            rs: c3 as isize,
                            cs: 1,
                        },
                        false,
                    );
                }
                for (i, &f) in inv[..rows].iter().enumerate() {
                    // SAFETY: row r0 + i, columns h·hd..(h+1)·hd of dst: this task's block.
                    let o = unsafe {
                        std::slice::from_raw_parts_mut(out.get().add((r0 + i) * c + h * hd), hd)
                    };
                    for v in o {
                        *v *= f;
                    }
                }
            });
        });
        Ok((CpuStorage::F32(dst), Shape::from_dims(&[n, c])))
    }
}

/// [`attention`] with both products in a packed low precision `L` (int8 or bf16) on the CPU:
/// per head, `kᵀ` and `v` are packed at run time (int8: `kᵀ` quantised per key, `v` per
/// feature; the query rows and the probabilities per row), the softmax stays f32.
///
/// # Errors
/// Shape errors; another device or dtype than f32 on the CPU.
pub(crate) fn attention_packed<L: PackedLinear>(
    qkv: &Tensor,
    num_heads: usize,
    scale: f32,
) -> Result<Tensor> {
    if !(qkv.device().is_cpu() && qkv.dtype() == candle_core::DType::F32) {
        candle_core::bail!("int8 and bf16 attention run on the CPU in f32");
    }
    qkv.contiguous()?.apply_op1_no_bwd(&AttentionPackedOp::<L> {
        num_heads,
        scale,
        layer: std::marker::PhantomData,
    })
}

struct AttentionPackedOp<L> {
    num_heads: usize,
    scale: f32,
    layer: std::marker::PhantomData<L>,
}

impl<L: PackedLinear> CustomOp1 for AttentionPackedOp<L> {
    fn name(&self) -> &'static str {
        "packed-attention"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let qkv = contiguous(storage, layout)?;
        let heads = self.num_heads;
        let (n, c, hd) = qkv_dims(layout, heads)?;
        let c3 = 3 * c;
        // per head: kᵀ (hd × n) and v (n × hd), packed
        let layers: Vec<(L, L)> = (0..heads)
            .into_par_iter()
            .map(|h| {
                Ok((
                    L::pack_transposed_rows(&qkv[c + h * hd..], c3, n, hd)?,
                    L::pack_rows(&qkv[2 * c + h * hd..], c3, n, hd)?,
                ))
            })
            .collect::<Result<_>>()?;
        let mut dst = zeroed(n * c);
        let out = SendPtr(dst.as_mut_ptr());
        let blocks = n.div_ceil(ATTN_ROWS);
        let scale = self.scale;
        (0..heads * blocks).into_par_iter().for_each(|t| {
            let (h, b) = (t / blocks, t % blocks);
            let r0 = b * ATTN_ROWS;
            let rows = ATTN_ROWS.min(n - r0);
            let (kt, v) = &layers[h];
            let mut q = Vec::with_capacity(rows * hd);
            for i in r0..r0 + rows {
                q.extend_from_slice(&qkv[i * c3 + h * hd..i * c3 + (h + 1) * hd]);
            }
            SCORES.with(|cell| {
                let mut s = cell.borrow_mut();
                if s.len() < rows * n {
                    s.resize(rows * n, 0.0);
                }
                let s = &mut s[..rows * n];
                kt.forward_serial(&q, rows, s);
                let mut inv = [0f32; ATTN_ROWS];
                let mut o = vec![0f32; rows * hd];
                v.weigh_scores(s, rows, scale, &mut o, &mut inv[..rows]);
                for (i, (o, &f)) in o.chunks_exact(hd).zip(&inv[..rows]).enumerate() {
                    // SAFETY: row r0 + i, columns h·hd..(h+1)·hd of dst: this task's block.
                    let d = unsafe {
                        std::slice::from_raw_parts_mut(out.get().add((r0 + i) * c + h * hd), hd)
                    };
                    for (d, &o) in d.iter_mut().zip(o) {
                        *d = o * f;
                    }
                }
            });
        });
        Ok((CpuStorage::F32(dst), Shape::from_dims(&[n, c])))
    }
}

/// 3×3 convolution, padding 1, stride 1 or 2, with bias, for `(1, c_in, h, w)` inputs; `weight`
/// `(c_out, c_in, 3, 3)`.
///
/// On the CPU (f32): im2col over chunks of output rows (bounded memory) and one large matmul per
/// chunk; candle's tiled CPU `conv2d` spends most of its time building 512-pixel tiles. Other
/// devices use `Tensor::conv2d`.
///
/// # Errors
/// Shape or dtype errors.
pub(crate) fn conv3x3(
    xs: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    stride: usize,
    fused: ConvFusion<'_>,
) -> Result<Tensor> {
    conv3x3_path(xs, weight, bias, stride, fused, ConvPath::Auto)
}

/// How the CPU computes a [`conv3x3`]: `Auto` is what the model runs; the others exist for
/// tests and benchmarks of each path.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[doc(hidden)]
pub enum ConvPath {
    /// Winograd F(2×2, 3×3) at stride 1 ([`super::winograd`]), im2col at stride 2.
    Auto,
    /// [`super::winograd`] (stride 1 only).
    Winograd,
    /// im2col and one product.
    Im2col,
}

/// [`conv3x3`] by a chosen CPU path (GPUs ignore it).
pub(crate) fn conv3x3_path(
    xs: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    stride: usize,
    fused: ConvFusion<'_>,
    path: ConvPath,
) -> Result<Tensor> {
    if !(xs.device().is_cpu() && xs.dtype() == candle_core::DType::F32) {
        let xs = if fused.relu_in {
            xs.relu()?
        } else {
            xs.clone()
        };
        let mut y = xs.conv2d(weight, 1, stride, 1, 1)?;
        if let Some(b) = bias {
            y = y.broadcast_add(&b.reshape((1, (), 1, 1))?)?;
        }
        if let Some(r) = fused.residual {
            y = (y + r)?;
        }
        return if fused.relu_out { y.relu() } else { Ok(y) };
    }
    let (b, c_in, _, _) = xs.dims4()?;
    let (c_out, wc_in, kh, kw) = weight.dims4()?;
    if b != 1
        || wc_in != c_in
        || kh != 3
        || kw != 3
        || stride == 0
        || (stride != 1 && path == ConvPath::Winograd)
    {
        candle_core::bail!(
            "conv3x3 ({path:?}): input {:?}, weight {:?}, stride {stride}",
            xs.dims(),
            weight.dims()
        );
    }
    let xs = xs.contiguous()?;
    let w_flat = weight.reshape((c_out, c_in * 9))?.contiguous()?;
    let bias = match bias {
        Some(b) => b.to_vec1::<f32>()?,
        None => vec![0f32; c_out],
    };
    let op = Conv3x3 {
        stride,
        path,
        bias: &bias,
        relu_in: fused.relu_in,
        relu_out: fused.relu_out,
    };
    match fused.residual {
        Some(r) => xs.apply_op3_no_bwd(&w_flat, &r.contiguous()?, &op),
        None => xs.apply_op2_no_bwd(&w_flat, &op),
    }
}

/// Element-wise operations fused into [`conv3x3`]: `relu_out?(conv(relu_in?(x)) + residual?)`.
#[derive(Clone, Copy, Default)]
pub(crate) struct ConvFusion<'a> {
    /// ReLU applied to the input.
    pub relu_in: bool,
    /// Added to the output (same shape).
    pub residual: Option<&'a Tensor>,
    /// ReLU applied to the output.
    pub relu_out: bool,
}

struct Conv3x3<'a> {
    stride: usize,
    path: ConvPath,
    bias: &'a [f32],
    relu_in: bool,
    relu_out: bool,
}

/// Bytes of one im2col chunk (bounds the scratch memory of [`conv3x3`]; 4 MiB measured ~0.1 s
/// faster per ViT-S frame than 16 or 1 MiB on this 2-core machine: the chunk stays in cache).
const IM2COL_CHUNK_BYTES: usize = 4 << 20;

residual_op!(Conv3x3, "conv3x3-im2col", "conv3x3-im2col-residual");

impl Conv3x3<'_> {
    fn run(
        &self,
        src: &[f32],
        l1: &Layout,
        wts: &[f32],
        l2: &Layout,
        residual: Option<&[f32]>,
    ) -> Result<(CpuStorage, Shape)> {
        let bias = self.bias;
        let (_, _, h, w) = l1.shape().dims4()?;
        let (c_out, k) = l2.shape().dims2()?;
        let s = self.stride;
        let (oh, ow) = ((h + 2 - 3) / s + 1, (w + 2 - 3) / s + 1);
        if wts.len() != c_out * k
            || bias.len() != c_out
            || k != 9 * (src.len() / (h * w))
            || residual.is_some_and(|r| r.len() != c_out * oh * ow)
        {
            candle_core::bail!("conv3x3: weight {:?}, input {:?}", l2.dims(), l1.dims());
        }
        if s == 1 && matches!(self.path, ConvPath::Auto | ConvPath::Winograd) {
            let fusion = super::winograd::Fusion {
                bias,
                relu_in: self.relu_in,
                residual,
                relu_out: self.relu_out,
                project: None,
            };
            let planes = super::winograd::Source::Planes(src);
            let dst = super::winograd::conv3x3(planes, (k / 9, h, w), wts, c_out, &fusion);
            return Ok((CpuStorage::F32(dst), Shape::from_dims(&[1, c_out, h, w])));
        }
        let rows_per_chunk = (IM2COL_CHUNK_BYTES / (4 * k * ow)).clamp(1, oh);
        // Output initialised with the bias; each chunk's matmul accumulates into it in place.
        let mut dst: Vec<f32> = Vec::with_capacity(c_out * oh * ow);
        match residual {
            Some(r) => {
                for (&b, plane) in bias.iter().zip(r.chunks_exact(oh * ow)) {
                    dst.extend(plane.iter().map(|v| v + b));
                }
            }
            None => {
                for &b in bias {
                    dst.extend(std::iter::repeat_n(b, oh * ow));
                }
            }
        }
        let relu_in = self.relu_in;
        // One im2col buffer for all chunks; every element is rewritten (zeros for padding).
        let mut col_buf = vec![0f32; k * rows_per_chunk * ow];
        let mut r0 = 0;
        while r0 < oh {
            let r1 = (r0 + rows_per_chunk).min(oh);
            let np = (r1 - r0) * ow;
            // col[(ci·9 + ky·3 + kx), p] = x[ci, oy·s + ky − 1, ox·s + kx − 1] (0 outside).
            let col = &mut col_buf[..k * np];
            col.par_chunks_mut(9 * np)
                .enumerate()
                .for_each(|(ci, rows9)| {
                    let plane = &src[ci * h * w..(ci + 1) * h * w];
                    for (kk, row) in rows9.chunks_mut(np).enumerate() {
                        let (ky, kx) = (kk / 3, kk % 3);
                        for oy in r0..r1 {
                            let iy = (oy * s + ky) as isize - 1;
                            let out = &mut row[(oy - r0) * ow..(oy - r0 + 1) * ow];
                            if iy < 0 || iy >= h as isize {
                                out.fill(0.0);
                                continue;
                            }
                            let src_row = &plane[iy as usize * w..(iy as usize + 1) * w];
                            if s == 1 && relu_in {
                                // ix = ox + kx − 1, max(x, 0)
                                let (o, i) = match kx {
                                    0 => {
                                        out[0] = 0.0;
                                        (&mut out[1..], &src_row[..w - 1])
                                    }
                                    1 => (&mut out[..], src_row),
                                    _ => {
                                        out[w - 1] = 0.0;
                                        (&mut out[..w - 1], &src_row[1..])
                                    }
                                };
                                for (o, &v) in o.iter_mut().zip(i) {
                                    *o = v.max(0.0);
                                }
                            } else if s == 1 {
                                // ix = ox + kx − 1
                                match kx {
                                    0 => {
                                        out[0] = 0.0;
                                        out[1..].copy_from_slice(&src_row[..w - 1]);
                                    }
                                    1 => out.copy_from_slice(src_row),
                                    _ => {
                                        out[..w - 1].copy_from_slice(&src_row[1..]);
                                        out[w - 1] = 0.0;
                                    }
                                }
                            } else {
                                for (ox, o) in out.iter_mut().enumerate() {
                                    let ix = (ox * s + kx) as isize - 1;
                                    *o = if ix >= 0 && ix < w as isize {
                                        let v = src_row[ix as usize];
                                        if relu_in { v.max(0.0) } else { v }
                                    } else {
                                        0.0
                                    };
                                }
                            }
                        }
                    }
                });
            // SAFETY: dst is (c_out, oh·ow); rows r0..r1 of every channel plane are written.
            unsafe {
                sgemm(
                    c_out,
                    np,
                    k,
                    dst.as_mut_ptr().add(r0 * ow),
                    (oh * ow) as isize,
                    true,
                    MatRef {
                        ptr: wts.as_ptr(),
                        rs: k as isize,
                        cs: 1,
                    },
                    MatRef {
                        ptr: col.as_ptr(),
                        rs: np as isize,
                        cs: 1,
                    },
                    true,
                );
            }
            r0 = r1;
        }
        if self.relu_out {
            dst.par_chunks_mut(16 * 1024).for_each(|d| {
                for v in d {
                    *v = v.max(0.0);
                }
            });
        }
        Ok((CpuStorage::F32(dst), Shape::from_dims(&[1, c_out, oh, ow])))
    }
}

/// `exp(x)` in `f32` without branches or libm calls, so that loops over slices vectorise:
/// Cody–Waite reduction `x = n·ln2 + r`, the Cephes `expf` polynomial on `|r| ≤ ln2/2`
/// (relative error ≈ 2e-7), `2ⁿ` built in the exponent bits. Inputs are clamped to
/// `[-87.3, 88]` (results below `2⁻¹²⁶` are not produced, nor ∞; softmax only sees `x ≤ 0`).
#[inline(always)]
fn exp_f32(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // 1.5·2²³: adding it rounds to an integer held in the low mantissa bits.
    const ROUND: f32 = 12_582_912.0;
    // comparisons, not `f32::clamp`: one min and one max instruction (NaN stays NaN either way)
    let x = if x < -87.3 { -87.3 } else { x };
    let x = if x > 88.0 { 88.0 } else { x };
    let t = x * LOG2E + ROUND;
    let n = t - ROUND;
    let r = x - n * LN2_HI - n * LN2_LO;
    let mut p = 1.987_569_2e-4f32;
    p = p * r + 1.398_199_9e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 1.666_666_5e-1;
    p = p * r + 0.5; // Cephes: 5.0000001201e-1, which is 0.5 in f32
    let e = p * r * r + r + 1.0;
    // 2ⁿ: (n + 127) << 23, n read from the low bits of t.
    let pow2n = f32::from_bits(t.to_bits().wrapping_add(127) << 23);
    e * pow2n
}

/// Sum with eight independent accumulators (vectorises; order differs from a sequential sum by
/// round-off only).
#[inline(always)]
fn sum8(xs: &[f32]) -> f32 {
    let mut acc = [0f32; 8];
    let chunks = xs.chunks_exact(8);
    let rest = chunks.remainder();
    for c in chunks {
        for i in 0..8 {
            acc[i] += c[i];
        }
    }
    acc.iter().sum::<f32>() + rest.iter().sum::<f32>()
}

/// Maximum with 64 independent lanes (vectorises, unlike a fold with `f32::max`: four
/// AVX-512 or eight AVX2 accumulators, so that the comparisons do not wait on each other; with
/// eight lanes, one dependent `vmaxps` per vector, this pass took 44 % of the int8 attention
/// softmax's samples). A comparison, not `f32::max`: one instruction instead of three per
/// vector (NaN-aware `max` adds a compare and a blend); NaN values are skipped either way, and
/// the maximum of the others does not depend on the order.
#[inline(always)]
fn row_max(xs: &[f32]) -> f32 {
    const LANES: usize = 64;
    let larger = |m: f32, x: f32| if x > m { x } else { m };
    let mut acc = [f32::NEG_INFINITY; LANES];
    let chunks = xs.chunks_exact(LANES);
    let rest = chunks.remainder();
    for c in chunks {
        for i in 0..LANES {
            acc[i] = larger(acc[i], c[i]);
        }
    }
    acc.iter()
        .chain(rest)
        .copied()
        .fold(f32::NEG_INFINITY, larger)
}

/// `softmax(scale · x)` over the last dimension (`scale > 0`). CPU: rows in parallel, vectorised
/// [`exp_f32`]; other devices: `candle_nn::ops::softmax_last_dim`.
///
/// # Errors
/// Shape or dtype errors.
pub(crate) fn softmax_last_dim(xs: &Tensor, scale: f32) -> Result<Tensor> {
    if xs.device().is_cpu() && xs.dtype() == candle_core::DType::F32 {
        xs.contiguous()?.apply_op1_no_bwd(&SoftmaxLastDim { scale })
    } else {
        candle_nn::ops::softmax_last_dim(&(xs * f64::from(scale))?)
    }
}

struct SoftmaxLastDim {
    scale: f32,
}

impl CustomOp1 for SoftmaxLastDim {
    fn name(&self) -> &'static str {
        "fast-softmax-last-dim"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let src = contiguous(storage, layout)?;
        let dim = layout.dims().last().copied().unwrap_or(1);
        let mut dst = zeroed(src.len());
        let scale = self.scale;
        dst.par_chunks_mut(dim)
            .zip(src.par_chunks(dim))
            .for_each(|(d, s)| {
                let max = row_max(s);
                for (o, v) in d.iter_mut().zip(s) {
                    *o = exp_f32((v - max) * scale);
                }
                let inv = 1.0 / sum8(d);
                for o in d.iter_mut() {
                    *o *= inv;
                }
            });
        Ok((CpuStorage::F32(dst), layout.shape().clone()))
    }
}

/// `erf(x)` by Abramowitz & Stegun 7.1.26 (absolute error ≤ 1.5e-7 in exact arithmetic, ≤ 1e-6 in
/// `f32`), the formula of PyTorch's
/// vectorised CPU `erf` (`Vectorized<float>::erf`).
#[inline(always)]
fn erf_f32(x: f32) -> f32 {
    const P: f32 = 0.327_591_1;
    const A1: f32 = 0.254_829_6;
    const A2: f32 = -0.284_496_74;
    const A3: f32 = 1.421_413_7;
    const A4: f32 = -1.453_152_1;
    const A5: f32 = 1.061_405_4;
    let a = x.abs();
    let t = 1.0 / (1.0 + P * a);
    let poly = ((((A5 * t + A4) * t + A3) * t + A2) * t + A1) * t;
    let y = 1.0 - poly * exp_f32(-a * a);
    y.copysign(x)
}

/// Exact (erf) GELU, `0.5·x·(1 + erf(x/√2))` (`nn.GELU()`). CPU: vectorised [`erf_f32`], in
/// parallel; other devices: `Tensor::gelu_erf`.
///
/// # Errors
/// Dtype errors.
#[cfg(test)]
pub(crate) fn gelu_erf(xs: &Tensor) -> Result<Tensor> {
    if xs.device().is_cpu() && xs.dtype() == candle_core::DType::F32 {
        xs.contiguous()?.apply_op1_no_bwd(&GeluErf)
    } else {
        xs.gelu_erf()
    }
}

#[cfg(test)]
struct GeluErf;

#[cfg(test)]
impl CustomOp1 for GeluErf {
    fn name(&self) -> &'static str {
        "fast-gelu-erf"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let src = contiguous(storage, layout)?;
        let mut dst = zeroed(src.len());
        dst.par_chunks_mut(16 * 1024)
            .zip(src.par_chunks(16 * 1024))
            .for_each(|(d, s)| {
                for (o, &v) in d.iter_mut().zip(s) {
                    *o = 0.5 * v * (1.0 + erf_f32(v * std::f32::consts::FRAC_1_SQRT_2));
                }
            });
        Ok((CpuStorage::F32(dst), layout.shape().clone()))
    }
}

/// Bilinear resize with `align_corners = true` of `(1, c, h, w)` to `(1, c, out_h, out_w)`
/// (`F.interpolate(..., mode="bilinear", align_corners=True)`). CPU: `f32` arithmetic in PyTorch's
/// order, parallel over channels and rows; other devices: `Tensor::upsample_bilinear2d`.
///
/// # Errors
/// Shape or dtype errors.
pub(crate) fn upsample_bilinear_align_corners(
    xs: &Tensor,
    out_h: usize,
    out_w: usize,
) -> Result<Tensor> {
    if xs.device().is_cpu() && xs.dtype() == candle_core::DType::F32 {
        xs.contiguous()?
            .apply_op1_no_bwd(&UpsampleBilinearAc { out_h, out_w })
    } else {
        xs.upsample_bilinear2d(out_h, out_w, true)
    }
}

/// A 1×1 convolution to one channel after [`upsample_conv3x3`]: weight `(1, c_out)` and bias
/// `(1, 1)`.
pub(crate) type Projection<'a> = (&'a Tensor, &'a Tensor);

/// `project?(relu_out?(conv3x3(upsample(xs, out_h, out_w), weight) + bias))` in one pass, for
/// `xs` `(1, c_in, h, w)`, `weight` `(c_out, c_in, 3, 3)` and `bias` `(c_out)`: `(1, c_out,
/// out_h, out_w)`, or `(1, 1, out_h, out_w)` with the projection (the DPT head's output
/// layers). On the CPU (f32) the upsampled input, and with the projection the `c_out`
/// channels, exist one band of rows at a time ([`super::winograd`]); at ViT-S 518×686 they
/// were maps of 30 to 45 MB, written, faulted in and read again. The same arithmetic as the
/// steps apart, but for the order of the projection's sum (channel order here). Other
/// devices: the steps apart.
///
/// # Errors
/// Shape or dtype errors.
#[allow(clippy::too_many_arguments)]
pub(crate) fn upsample_conv3x3(
    xs: &Tensor,
    out_h: usize,
    out_w: usize,
    weight: &Tensor,
    bias: &Tensor,
    relu_out: bool,
    project: Option<Projection<'_>>,
) -> Result<Tensor> {
    let (b, c_in, _, _) = xs.dims4()?;
    let (c_out, wc_in, kh, kw) = weight.dims4()?;
    if !(xs.device().is_cpu() && xs.dtype() == candle_core::DType::F32) {
        let up = upsample_bilinear_align_corners(xs, out_h, out_w)?;
        let fused = ConvFusion {
            relu_out,
            ..ConvFusion::default()
        };
        let y = conv3x3(&up, weight, Some(bias), 1, fused)?;
        return match project {
            Some((w1, b1)) => matmul_row_bias(w1, &y.reshape((c_out, out_h * out_w))?, b1, false)?
                .reshape((1, 1, out_h, out_w)),
            None => Ok(y),
        };
    }
    if b != 1
        || wc_in != c_in
        || kh != 3
        || kw != 3
        || project.is_some_and(|(w1, b1)| w1.elem_count() != c_out || b1.elem_count() != 1)
    {
        candle_core::bail!(
            "upsample-conv3x3: input {:?}, weight {:?}, projection {:?}",
            xs.dims(),
            weight.dims(),
            project.map(|(w1, _)| w1.dims().to_vec())
        );
    }
    let project = match project {
        Some((w1, b1)) => Some((
            w1.flatten_all()?.to_vec1()?,
            b1.flatten_all()?.to_vec1::<f32>()?[0],
        )),
        None => None,
    };
    xs.contiguous()?.apply_op1_no_bwd(&UpsampleConvProject {
        out_h,
        out_w,
        weight: weight.flatten_all()?.to_vec1()?,
        bias: bias.to_vec1()?,
        relu_out,
        project,
    })
}

struct UpsampleConvProject {
    out_h: usize,
    out_w: usize,
    weight: Vec<f32>,
    bias: Vec<f32>,
    relu_out: bool,
    project: Option<(Vec<f32>, f32)>,
}

impl CustomOp1 for UpsampleConvProject {
    fn name(&self) -> &'static str {
        "upsample-conv3x3"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let src = contiguous(storage, layout)?;
        let (_, c_in, h, w) = layout.shape().dims4()?;
        let (oh, ow) = (self.out_h, self.out_w);
        let c_out = self.bias.len();
        if h == 0 || w == 0 || oh == 0 || ow == 0 || self.weight.len() != 9 * c_in * c_out {
            candle_core::bail!("upsample-conv3x3: input {:?} to {oh}×{ow}", layout.dims());
        }
        let fusion = super::winograd::Fusion {
            bias: &self.bias,
            relu_in: false,
            residual: None,
            relu_out: self.relu_out,
            project: self.project.as_ref().map(|(w1, b1)| (&w1[..], *b1)),
        };
        let source = super::winograd::Source::Upsampled {
            src,
            h_s: h,
            w_s: w,
        };
        let dst = super::winograd::conv3x3(source, (c_in, oh, ow), &self.weight, c_out, &fusion);
        let channels = if self.project.is_some() { 1 } else { c_out };
        Ok((
            CpuStorage::F32(dst),
            Shape::from_dims(&[1, channels, oh, ow]),
        ))
    }
}

struct UpsampleBilinearAc {
    out_h: usize,
    out_w: usize,
}

/// Rows `yt` (the taps of consecutive output rows) of one plane `p` (width `w`) upsampled to
/// `xt.len()` columns into `out` (`yt.len()` rows): each source row the rows need is
/// interpolated along x once (into `hx`), then each output row blends two of those.
/// `hy0·(wx0·r0[x0] + wx1·r0[x1]) + hy1·(…r1…)` is evaluated exactly as written (Rust does not
/// contract to FMA): the same bits as a per-pixel loop, with the gathers done once per source
/// row instead of twice per output row.
pub(super) fn upsample_rows(
    p: &[f32],
    w: usize,
    yt: &[(usize, usize, f32, f32)],
    xt: &[(usize, usize, f32, f32)],
    hx: &mut Vec<f32>,
    out: &mut [f32],
) {
    let ow = xt.len();
    let (Some(first), Some(last)) = (yt.first(), yt.last()) else {
        return;
    };
    let (first, last) = (first.0, last.1.max(last.0));
    hx.resize((last - first + 1) * ow, 0.0);
    for (y, hrow) in (first..=last).zip(hx.chunks_exact_mut(ow)) {
        interpolate_row(&p[y * w..(y + 1) * w], xt, hrow);
    }
    for (row, &(y0, y1, hy0, hy1)) in out.chunks_exact_mut(ow).zip(yt) {
        let h0 = &hx[(y0 - first) * ow..(y0 - first + 1) * ow];
        let h1 = &hx[(y1 - first) * ow..(y1 - first + 1) * ow];
        blend_rows(row, h0, h1, hy0, hy1);
    }
}

/// `out[x] = wx0·r[x0] + wx1·r[x1]` for the taps `(x0, x1, wx0, wx1)` of each output column.
fn interpolate_row(r: &[f32], xt: &[(usize, usize, f32, f32)], out: &mut [f32]) {
    for (o, &(x0, x1, wx0, wx1)) in out.iter_mut().zip(xt) {
        *o = wx0 * r[x0] + wx1 * r[x1];
    }
}

simd_dispatch! {
    /// `acc += a·x`, element by element (a product, then a sum: no fused multiply-add).
    pub(super) fn add_scaled(acc: &mut [f32], a: f32, x: &[f32]) {
        for (s, &x) in acc.iter_mut().zip(x) {
            *s += a * x;
        }
    }
}

simd_dispatch! {
    /// `out = a0·h0 + a1·h1`, element by element.
    fn blend_rows(out: &mut [f32], h0: &[f32], h1: &[f32], a0: f32, a1: f32) {
        for ((o, &x0), &x1) in out.iter_mut().zip(h0).zip(h1) {
            *o = a0 * x0 + a1 * x1;
        }
    }
}

impl CustomOp1 for UpsampleBilinearAc {
    fn name(&self) -> &'static str {
        "upsample-bilinear-align-corners"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let src = contiguous(storage, layout)?;
        let (b, c, h, w) = layout.shape().dims4()?;
        let (oh, ow) = (self.out_h, self.out_w);
        if h == 0 || w == 0 {
            candle_core::bail!("upsample: empty input {:?}", layout.dims());
        }
        let yt = crate::preprocess::align_corners_taps(h, oh);
        let xt = crate::preprocess::align_corners_taps(w, ow);
        // Separable ([`upsample_rows`]); tasks: bands of output rows of one plane.
        const BAND: usize = 32;
        let mut dst = zeroed(b * c * oh * ow);
        dst.par_chunks_mut(oh * ow)
            .enumerate()
            .for_each(|(plane, plane_out)| {
                let p = &src[plane * h * w..(plane + 1) * h * w];
                plane_out
                    .par_chunks_mut(BAND * ow)
                    .enumerate()
                    .for_each(|(band, out)| {
                        let taps = &yt[band * BAND..band * BAND + out.len() / ow];
                        upsample_rows(p, w, taps, &xt, &mut Vec::new(), out);
                    });
            });
        Ok((CpuStorage::F32(dst), Shape::from_dims(&[b, c, oh, ow])))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `zeroed` gives `len` zeros whatever the length (one chunk, exact chunks, a remainder),
    /// also where the allocator hands back memory that held other values.
    #[test]
    fn zeroed_is_all_zeros_at_every_length() {
        for len in [0, 1, 1 << 16, (1 << 16) + 1, 3 * (1 << 16) + 7] {
            // dirty the heap with non-zero values of the same size first
            drop(vec![7.5f32; len]);
            let v = zeroed(len);
            assert_eq!(v.len(), len);
            assert!(v.iter().all(|&x| x.to_bits() == 0), "len {len}");
        }
    }

    /// The comparison-based maximum and clamp keep `f32::max`'s and `f32::clamp`'s values:
    /// NaN skipped by the maximum, passed through by `exp`, ±∞ and the clamp bounds exact.
    #[test]
    fn comparison_max_and_clamp_keep_the_float_semantics() {
        let rows: [&[f32]; 5] = [
            &[
                f32::NAN,
                1.0,
                -3.0,
                f32::NAN,
                2.5,
                0.0,
                -0.0,
                7.0,
                6.9,
                f32::NAN,
                1e30,
            ],
            &[f32::NEG_INFINITY; 9],
            &[f32::NAN, -1.0],
            &[
                -5.0,
                f32::INFINITY,
                3.0,
                1.0,
                2.0,
                3.0,
                4.0,
                5.0,
                6.0,
                f32::NAN,
                -7.0,
            ],
            &[],
        ];
        for row in rows {
            let want = row.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            assert_eq!(row_max(row).to_bits(), want.to_bits(), "{row:?}");
        }
        // rows through the 64 lanes (below, at and past one chunk, an attention row of 1 814),
        // the maximum in every position and NaN sprinkled in
        for len in [63usize, 64, 65, 129, 1814] {
            for at in [0, len / 2, len - 1] {
                let row: Vec<f32> = (0..len)
                    .map(|i| match i {
                        _ if i == at => 1e3,
                        _ if i % 17 == 5 => f32::NAN,
                        _ => ((i * 7919) % 1000) as f32 * 0.5 - 250.0,
                    })
                    .collect();
                assert_eq!(row_max(&row), 1e3, "len {len}, maximum at {at}");
            }
        }
        assert!(exp_f32(f32::NAN).is_nan());
        assert_eq!(exp_f32(-1e9), exp_f32(-87.3));
        assert_eq!(exp_f32(1e9), exp_f32(88.0));
        assert_eq!(exp_f32(f32::NEG_INFINITY), exp_f32(-87.3));
        // the largest input stays finite (88.7, the bound before, made 2¹²⁸ = ∞)
        assert!(exp_f32(88.0).is_finite() && exp_f32(88.0) > 1.6e38);
    }

    #[test]
    fn fast_exp_and_erf_are_accurate() {
        let mut worst_exp = 0f64;
        let mut worst_erf = 0f64;
        for i in 0..200_001 {
            let x = f64::from((-80.0 + 100.0 * i as f64 / 200_000.0) as f32);
            let rel = ((exp_f32(x as f32) as f64) - x.exp()).abs() / x.exp();
            worst_exp = worst_exp.max(rel);
            let y = -6.0 + 12.0 * i as f64 / 200_000.0;
            let want = erf_ref(y);
            worst_erf = worst_erf.max(((erf_f32(y as f32) as f64) - want).abs());
        }
        assert!(worst_exp < 5e-7, "exp rel err {worst_exp}");
        assert!(worst_erf < 1e-6, "erf abs err {worst_erf}");
    }

    /// erf by its Taylor series / continued fraction in f64 (reference).
    fn erf_ref(x: f64) -> f64 {
        if x.abs() < 3.0 {
            // Σ (−1)ⁿ x^(2n+1) / (n! (2n+1)) · 2/√π
            let mut sum = 0.0;
            let mut term = x;
            for n in 0..200 {
                sum += term / (2 * n + 1) as f64;
                term *= -x * x / (n + 1) as f64;
            }
            sum * 2.0 / std::f64::consts::PI.sqrt()
        } else {
            // erfc asymptotic continued fraction (Lentz-free, fixed depth).
            let a = x.abs();
            let mut f = 0.0;
            for k in (1..60).rev() {
                f = (k as f64 / 2.0) / (a + f);
            }
            let erfc = (-a * a).exp() / std::f64::consts::PI.sqrt() / (a + f);
            (1.0 - erfc).copysign(x)
        }
    }

    /// The CPU paths of [`conv3x3`] against candle's `conv2d` in f64, with every fusion, on odd
    /// and even sizes (one-pixel rows and columns included) and both strides: Winograd (what
    /// stride 1 runs) and im2col (stride 2, and forced at stride 1).
    #[test]
    fn conv3x3_matches_candle_conv2d() {
        use candle_core::DType;
        let dev = candle_core::Device::Cpu;
        let wave = |n: usize, f: f64| -> Vec<f32> {
            (0..n)
                .map(|i| ((i as f64 * f).sin() * 1.7) as f32)
                .collect()
        };
        for (c_in, c_out, h, w) in [
            (3, 5, 7, 9),
            (8, 4, 6, 5),
            (16, 16, 11, 14),
            (4, 130, 5, 6),
            (2, 3, 1, 1),
            (3, 2, 1, 6),
            (5, 3, 7, 1),
        ] {
            let x = Tensor::from_vec(wave(c_in * h * w, 0.37), (1, c_in, h, w), &dev).unwrap();
            let wt =
                Tensor::from_vec(wave(c_out * c_in * 9, 0.71), (c_out, c_in, 3, 3), &dev).unwrap();
            let bias = Tensor::from_vec(wave(c_out, 1.3), c_out, &dev).unwrap();
            for stride in [1, 2] {
                let (oh, ow) = ((h - 1) / stride + 1, (w - 1) / stride + 1);
                let res = Tensor::from_vec(wave(c_out * oh * ow, 0.53), (1, c_out, oh, ow), &dev)
                    .unwrap();
                for (relu_in, relu_out, with_res) in [
                    (false, false, false),
                    (true, false, true),
                    (true, true, false),
                ] {
                    let f64_ = |t: &Tensor| t.to_dtype(DType::F64).unwrap();
                    let xin = if relu_in {
                        f64_(&x).relu().unwrap()
                    } else {
                        f64_(&x)
                    };
                    let mut want = xin
                        .conv2d(&f64_(&wt), 1, stride, 1, 1)
                        .unwrap()
                        .broadcast_add(&f64_(&bias).reshape((1, (), 1, 1)).unwrap())
                        .unwrap();
                    if with_res {
                        want = (want + f64_(&res)).unwrap();
                    }
                    if relu_out {
                        want = want.relu().unwrap();
                    }
                    let want: Vec<f64> = want.flatten_all().unwrap().to_vec1().unwrap();
                    let fused = ConvFusion {
                        relu_in,
                        residual: with_res.then_some(&res),
                        relu_out,
                    };
                    let paths: &[ConvPath] = if stride == 1 {
                        &[ConvPath::Auto, ConvPath::Winograd, ConvPath::Im2col]
                    } else {
                        &[ConvPath::Auto, ConvPath::Im2col]
                    };
                    for &path in paths {
                        let got = conv3x3_path(&x, &wt, Some(&bias), stride, fused, path).unwrap();
                        assert_eq!(got.dims(), &[1, c_out, oh, ow]);
                        let got: Vec<f32> = got.flatten_all().unwrap().to_vec1().unwrap();
                        let err = got
                            .iter()
                            .zip(&want)
                            .map(|(&g, &w)| (f64::from(g) - w).abs())
                            .fold(0.0, f64::max);
                        // f32 round-off of a 9·c_in-term sum of products of magnitude ≤ 2.9
                        // (Winograd: of 16 transformed terms per channel, ≤ 4× larger)
                        let tol = 1e-6 * (9 * c_in) as f64;
                        assert!(
                            err < tol,
                            "{path:?} c{c_in}->{c_out} {h}x{w} s{stride} relu_in {relu_in} \
                             relu_out {relu_out} residual {with_res}: max err {err} (tol {tol})"
                        );
                    }
                }
            }
        }
    }

    /// Winograd's output bands are fixed by the shape, each computed serially: the same bits
    /// on 1 and 3 threads, with several bands (a tall input), and stride 2 refused.
    #[test]
    fn winograd_gives_the_same_bits_on_any_thread_count() {
        let dev = candle_core::Device::Cpu;
        let (c_in, c_out, h, w) = (24, 40, 301, 23);
        let mut st = 0.1f32;
        let mut next = || {
            st = (st * 3.7 + 0.31).fract();
            st * 2.0 - 1.0
        };
        let x = Tensor::from_vec(
            (0..c_in * h * w).map(|_| next()).collect(),
            (1, c_in, h, w),
            &dev,
        )
        .unwrap();
        let wt = Tensor::from_vec(
            (0..c_out * c_in * 9).map(|_| next()).collect(),
            (c_out, c_in, 3, 3),
            &dev,
        )
        .unwrap();
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    conv3x3_path(&x, &wt, None, 1, ConvFusion::default(), ConvPath::Winograd)
                        .unwrap()
                        .flatten_all()
                        .unwrap()
                        .to_vec1::<f32>()
                        .unwrap()
                })
        };
        assert_eq!(run(1), run(3));
        let stride2 = conv3x3_path(&x, &wt, None, 2, ConvFusion::default(), ConvPath::Winograd);
        assert!(stride2.is_err());
    }

    /// The separable bilinear upsampling (`align_corners = true`) against candle's in f64, up
    /// and down, one-pixel sources and targets included.
    #[test]
    fn upsample_matches_candle() {
        use candle_core::DType;
        let dev = candle_core::Device::Cpu;
        for (c, h, w, oh, ow) in [
            (3, 5, 7, 9, 13),
            (2, 37, 49, 74, 98),
            (1, 8, 6, 3, 4),
            (2, 1, 1, 4, 5),
            (1, 4, 5, 1, 1),
            (2, 45, 3, 100, 2),
        ] {
            let x: Vec<f32> = (0..c * h * w).map(|i| ((i as f32) * 0.37).sin()).collect();
            let x = Tensor::from_vec(x, (1, c, h, w), &dev).unwrap();
            let want: Vec<f64> = x
                .to_dtype(DType::F64)
                .unwrap()
                .upsample_bilinear2d(oh, ow, true)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let got = upsample_bilinear_align_corners(&x, oh, ow).unwrap();
            assert_eq!(got.dims(), &[1, c, oh, ow]);
            let got: Vec<f32> = got.flatten_all().unwrap().to_vec1().unwrap();
            let err = got
                .iter()
                .zip(&want)
                .map(|(&g, &w)| (f64::from(g) - w).abs())
                .fold(0.0, f64::max);
            assert!(err < 1e-5, "{c}×{h}×{w} → {oh}×{ow}: {err}");
        }
    }

    /// [`upsample_conv3x3`] against its steps in candle, in f64: upsample (`align_corners`),
    /// 3×3 convolution + bias (+ ReLU, 1×1 projection to one channel); odd and even sizes,
    /// several bands.
    #[test]
    fn upsample_conv_project_matches_its_three_steps() {
        use candle_core::DType;
        let dev = candle_core::Device::Cpu;
        let wave = |n: usize, f: f64| -> Vec<f32> {
            (0..n)
                .map(|i| ((i as f64 * f).sin() * 1.3) as f32)
                .collect()
        };
        for (c_in, c_out, h, w, oh, ow) in [
            (4, 6, 5, 7, 9, 13),
            (8, 5, 37, 9, 301, 17),
            (3, 2, 2, 2, 1, 5),
        ] {
            let x = Tensor::from_vec(wave(c_in * h * w, 0.37), (1, c_in, h, w), &dev).unwrap();
            let wt =
                Tensor::from_vec(wave(c_out * c_in * 9, 0.71), (c_out, c_in, 3, 3), &dev).unwrap();
            let bias = Tensor::from_vec(wave(c_out, 1.3), c_out, &dev).unwrap();
            let w1 = Tensor::from_vec(wave(c_out, 0.9), (1, c_out), &dev).unwrap();
            let b1 = Tensor::from_vec(vec![0.25f32], (1, 1), &dev).unwrap();
            let f = |t: &Tensor| t.to_dtype(DType::F64).unwrap();
            let y = f(&x)
                .upsample_bilinear2d(oh, ow, true)
                .unwrap()
                .conv2d(&f(&wt), 1, 1, 1, 1)
                .unwrap()
                .broadcast_add(&f(&bias).reshape((1, (), 1, 1)).unwrap())
                .unwrap()
                .relu()
                .unwrap()
                .reshape((c_out, oh * ow))
                .unwrap();
            let want: Vec<f64> = f(&w1)
                .matmul(&y)
                .unwrap()
                .broadcast_add(&f(&b1))
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let got = upsample_conv3x3(&x, oh, ow, &wt, &bias, true, Some((&w1, &b1))).unwrap();
            assert_eq!(got.dims(), &[1, 1, oh, ow]);
            // without the projection and the ReLU: the convolution's channels
            let conv: Vec<f64> = f(&x)
                .upsample_bilinear2d(oh, ow, true)
                .unwrap()
                .conv2d(&f(&wt), 1, 1, 1, 1)
                .unwrap()
                .broadcast_add(&f(&bias).reshape((1, (), 1, 1)).unwrap())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            let plain = upsample_conv3x3(&x, oh, ow, &wt, &bias, false, None).unwrap();
            assert_eq!(plain.dims(), &[1, c_out, oh, ow]);
            let plain: Vec<f32> = plain.flatten_all().unwrap().to_vec1().unwrap();
            let err = plain
                .iter()
                .zip(&conv)
                .map(|(&g, &w)| (f64::from(g) - w).abs())
                .fold(0.0, f64::max);
            assert!(err < 1e-6 * (9 * c_in) as f64, "no projection: {err}");
            let got: Vec<f32> = got.flatten_all().unwrap().to_vec1().unwrap();
            let err = got
                .iter()
                .zip(&want)
                .map(|(&g, &w)| (f64::from(g) - w).abs())
                .fold(0.0, f64::max);
            // f32 round-off of 9·c_in products per channel, summed over c_out channels
            let tol = 1e-6 * (9 * c_in * c_out) as f64;
            assert!(
                err < tol,
                "{c_in}->{c_out} {h}x{w} -> {oh}x{ow}: {err} (tol {tol})"
            );
        }
    }

    /// The int8 attention's softmax in bytes against `round(255·exp(scale·(x − max)))` in f64:
    /// each byte within one level (the polynomial moves values within 0.0007 of a level across
    /// a rounding boundary), 255 at each row's maximum, zero padding, and `inv` = 255 / Σ q.
    #[test]
    fn softmax_u8_matches_the_rounded_exponential() {
        let (rows, n, kp) = (5, 1815, 1816);
        let scale = 0.125f32;
        let s: Vec<f32> = (0..rows * n)
            .map(|i| (i as f32 * 0.7131).sin() * 40.0 + (i / n) as f32 * 3.0)
            .collect();
        let mut q = vec![7u8; rows * kp];
        let mut inv = vec![0f32; rows];
        softmax_u8(&s, n, scale, &mut q, kp, &mut inv);
        let mut off_by_one = 0;
        for r in 0..rows {
            let row = &s[r * n..(r + 1) * n];
            let max = row.iter().copied().fold(f32::MIN, f32::max);
            let qr = &q[r * kp..(r + 1) * kp];
            assert_eq!(qr[n], 0, "padding");
            let mut sum = 0u32;
            for (&v, &b) in row.iter().zip(qr) {
                let want = (255.0 * (f64::from(scale) * (f64::from(v) - f64::from(max))).exp())
                    .round_ties_even();
                let d = (f64::from(b) - want).abs();
                assert!(d <= 1.0, "{v}: {b} vs {want}");
                off_by_one += usize::from(d > 0.0);
                sum += u32::from(b);
                if v == max {
                    assert_eq!(b, 255);
                }
            }
            assert!((inv[r] - 255.0 / sum as f32).abs() <= 1e-6 * inv[r]);
        }
        assert!(
            off_by_one * 100 < rows * n,
            "{off_by_one} bytes off by one level"
        );
    }

    #[test]
    fn softmax_and_gelu_match_candle() {
        let dev = candle_core::Device::Cpu;
        let x = Tensor::arange(0u32, 3000, &dev)
            .unwrap()
            .to_dtype(candle_core::DType::F32)
            .unwrap();
        let x = ((x * 0.013).unwrap().sin().unwrap() * 9.0)
            .unwrap()
            .reshape((3, 1000))
            .unwrap();
        let a = softmax_last_dim(&x, 0.125).unwrap();
        let b = candle_nn::ops::softmax_last_dim(&(&x * 0.125).unwrap()).unwrap();
        let d = (a - &b)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(d < 1e-8, "softmax diff {d}");
        let a = gelu_erf(&x).unwrap();
        let b = x.gelu_erf().unwrap();
        let d = (a - &b)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(d < 5e-6, "gelu diff {d}");
    }
}
