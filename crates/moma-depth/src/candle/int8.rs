//! int8 linear layers on the CPU (`--dtype int8`): `y = x·W + b` with per-output-channel
//! symmetric weight scales (fixed at load time) and dynamic per-token asymmetric activation
//! scales (each row of `x` at run time), products accumulated exactly in `i32`.
//!
//! Weights `q_w = round(W / s_w[j])` in [−127, 127] with `s_w[j] = max_k |W[k, j]| / 127`;
//! activations `q_x = round(x / s_x[i]) + z[i]` in [0, 255] (unsigned bytes, as `vpdpbusd`
//! wants) with `s_x[i] = (max(x_i, 0) − min(x_i, 0)) / 255` and the zero point
//! `z[i] = round(−min(x_i, 0) / s_x[i])`: the whole byte range covers the row's values, which
//! matters after a GELU (almost no negative values), where a symmetric range would waste half
//! of it (2.9 % of the output range against 1.1 % on the ViT-S reference). The zero point is
//! removed with the weights' column sums: `Σ_k q_x·q_w − z[i]·Σ_k q_w`, and
//! `y[i, j] = s_x[i]·s_w[j]·(Σ_k q_x·q_w − z[i]·Σ_k q_w) + b[j]`.
//!
//! Outlier channels (LLM.int8's decomposition): within each chunk of rows, an input channel
//! whose largest `|x|` exceeds [`OUTLIER_RATIO`] × the median channel's (at most one channel in
//! [`OUTLIER_SHARE`]) is left out of the quantised rows and multiplied in f32 with its weight
//! row as quantised, so that it no longer sets every token's scale. Rows without such channels
//! (every random-weight reference here) give the plain product, bit for bit.
//!
//! Kernel: AVX512-VNNI `vpdpbusd` (64 multiply-adds of bytes per instruction) where the CPU has
//! it, found at run time; a portable loop otherwise. Both give the same `i32` sums (integer
//! arithmetic is exact) and share the `f32` epilogue, so every CPU and every thread count gives
//! the same bits. Written here because neither of the crates moma builds on has such a kernel:
//! `gemm` multiplies floats only, and candle's quantised matmuls (ggml's `Q8_0`) are slower than
//! f32 on the encoder's shapes (0.9–7.8× the f32 time, where this kernel takes 0.21–0.56×:
//! `cargo run --release -p moma-depth --example cpu_kernels`).

/// Rows of `x` per micro-kernel call.
const MR: usize = 8;
/// Output columns per micro-kernel call (two 16-lane `i32` vectors).
const NR: usize = 32;
/// Rows of `x` per call of the row loop.
const CHUNK: usize = super::ops::PACKED_CHUNK;

/// A linear layer quantised to int8 (module documentation).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct QuantLinear {
    /// Input features.
    k: usize,
    /// Output features.
    n: usize,
    /// `k` rounded up to a multiple of 4 (one `vpdpbusd` lane takes 4 bytes).
    kp: usize,
    /// `n` rounded up to a multiple of [`NR`].
    np: usize,
    /// `q_w` in blocks of 16 columns: block `jb` holds, for each group of 4 rows `kb`, 16 × 4
    /// bytes (`[j][kk]` = `q_w[4·kb + kk, 16·jb + j]`); zero outside `k × n`.
    packed: Vec<i8>,
    /// `s_w`, one per output column (`np`; 0 in the padding).
    scale: Vec<f32>,
    /// `Σ_k q_w[k, j]` (`np`).
    colsum: Vec<i32>,
    /// `b` (`n`).
    bias: Vec<f32>,
}

impl QuantLinear {
    /// Quantises `weight_t` (`k × n`, row-major: `x·weight_t`) and keeps `bias` (`n`).
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
                "int8 linear: weight of {} values for {k}×{n}, bias of {}",
                weight_t.len(),
                bias.len()
            );
        }
        Self::from_rows(weight_t, n, k, n, bias.to_vec())
    }

    /// The layer from its packed bytes, scales and column sums (`np` each) and bias (`n`).
    fn from_parts(
        k: usize,
        n: usize,
        packed: Vec<i8>,
        scale: Vec<f32>,
        colsum: Vec<i32>,
        bias: Vec<f32>,
    ) -> Self {
        Self {
            k,
            n,
            kp: k.div_ceil(4) * 4,
            np: n.div_ceil(NR) * NR,
            packed,
            scale,
            colsum,
            bias,
        }
    }

    /// [`Self::new`] of `Xᵀ` (`k × n`, zero bias), row `j` of `X` at `src[j·stride..][..k]`
    /// (an attention head's keys): each column's scale and bytes come from one contiguous row,
    /// and its groups of 4 bytes are stored as they are packed. The same layer, bit for bit.
    fn from_transposed_rows(
        src: &[f32],
        stride: usize,
        n: usize,
        k: usize,
    ) -> candle_core::Result<Self> {
        let (kp, np) = (k.div_ceil(4) * 4, n.div_ceil(NR) * NR);
        let mut packed = vec![0i8; np * kp];
        let mut scale = vec![0f32; np];
        let mut colsum = vec![0i32; np];
        let mut q = vec![0i8; kp];
        for j in 0..n {
            let row = &src[j * stride..j * stride + k];
            let s = weight_scale(abs_max(row).ok_or_else(not_finite)?);
            scale[j] = s;
            colsum[j] = quantise_column(row, 1.0 / s, &mut q[..k]);
            for (kb, q4) in q.chunks_exact(4).enumerate() {
                let at = packed_index(kp, 4 * kb, j);
                packed[at..at + 4].copy_from_slice(q4);
            }
        }
        Ok(Self::from_parts(k, n, packed, scale, colsum, vec![0.0; n]))
    }

    /// The layer `x·X + bias` for `X` (`k × n`) with row `i` at `src[i·stride..][..n]` (a
    /// weight matrix, `stride = n`; an attention head's values inside the `qkv` rows): rows
    /// quantised four at a time and their bytes interleaved as they are packed.
    ///
    /// # Errors
    /// A value of `X` that is not finite.
    fn from_rows(
        src: &[f32],
        stride: usize,
        k: usize,
        n: usize,
        bias: Vec<f32>,
    ) -> candle_core::Result<Self> {
        let (kp, np) = (k.div_ceil(4) * 4, n.div_ceil(NR) * NR);
        let row = |i: usize| &src[i * stride..i * stride + n];
        let mut amax = vec![0f32; n];
        for i in 0..k {
            column_abs_max(row(i), &mut amax).ok_or_else(not_finite)?;
        }
        let mut scale = vec![0f32; np];
        for (s, &a) in scale.iter_mut().zip(&amax) {
            *s = weight_scale(a);
        }
        let inv: Vec<f32> = scale[..n].iter().map(|s| 1.0 / s).collect();
        let mut packed = vec![0i8; np * kp];
        let mut colsum = vec![0i32; np];
        let mut q = vec![0i8; 4 * n];
        for kb in 0..kp / 4 {
            for (kk, q) in q.chunks_exact_mut(n).enumerate() {
                let i = 4 * kb + kk;
                if i < k {
                    quantise_weights(row(i), &inv, q, &mut colsum[..n]);
                } else {
                    q.fill(0);
                }
            }
            for j in 0..n {
                let at = packed_index(kp, 4 * kb, j);
                for kk in 0..4 {
                    packed[at + kk] = q[kk * n + j];
                }
            }
        }
        Ok(Self::from_parts(k, n, packed, scale, colsum, bias))
    }

    /// `PackedLinear::run_chunk` with the VNNI kernel or (`vnni` false) the portable one.
    fn run_chunk_with(
        &self,
        x: &[f32],
        rows: usize,
        residual: Option<&[f32]>,
        out: &mut [f32],
        vnni: bool,
    ) {
        let (k, kp) = (self.k, self.kp);
        let padded = rows.div_ceil(MR) * MR;
        let outliers = outlier_channels(&x[..rows * k], k);
        QUANT.with(|cell| {
            let mut buf = cell.borrow_mut();
            let (q, inliers) = buf.parts(padded * kp, k);
            // Quantised rows (0 in the padding: the weights there are 0 too), their scales
            // and zero points; outlier channels as zeros (their products follow in f32).
            let mut sx = [0f32; CHUNK];
            let mut zx = [0i32; CHUNK];
            q[rows * kp..].fill(0);
            for (i, (row, q)) in x.chunks_exact(k).zip(q.chunks_exact_mut(kp)).enumerate() {
                let row = if outliers.is_empty() {
                    row
                } else {
                    inliers.copy_from_slice(row);
                    for &j in &outliers {
                        inliers[j] = 0.0;
                    }
                    &inliers[..]
                };
                (sx[i], zx[i]) = quantise_row(row, &mut q[..k]);
                q[k..].fill(0);
            }
            self.multiply(q, &sx, &zx, rows, residual, out, vnni);
        });
        self.add_outlier_products(x, rows, &outliers, out);
    }

    /// `out += x[:, j] · W[j, :]` for the outlier channels `j` of `x` (`rows × k`), with the
    /// weights' row `j` as quantised (`q_w · s_w`): the activations of those channels keep
    /// f32, so they no longer set every token's scale.
    fn add_outlier_products(&self, x: &[f32], rows: usize, outliers: &[usize], out: &mut [f32]) {
        let (k, n, kp) = (self.k, self.n, self.kp);
        let mut w = vec![0f32; n];
        for &j in outliers {
            for (col, w) in w.iter_mut().enumerate() {
                *w = f32::from(self.packed[packed_index(kp, j, col)]) * self.scale[col];
            }
            for (i, o) in out.chunks_exact_mut(n).enumerate().take(rows) {
                super::ops::add_scaled(o, x[i * k + j], &w);
            }
        }
    }

    /// `out` (`rows × n`) from rows already quantised: `q` holds `rows` rounded up to a
    /// multiple of 8 rows of `kp` bytes (`q_x`, zero in the padding), `sx` and `zx` their
    /// scales and zero points; at most [`CHUNK`] rows. For producers that know their rows'
    /// range in advance (the attention's probabilities, in [0, 1]).
    pub(crate) fn forward_quantised(
        &self,
        q: &[u8],
        sx: &[f32],
        zx: &[i32],
        rows: usize,
        out: &mut [f32],
    ) {
        debug_assert!(rows <= CHUNK && q.len() >= rows.div_ceil(MR) * MR * self.kp);
        self.multiply(q, sx, zx, rows, None, out, has_vnni());
    }

    /// The products of quantised rows `q` with the packed weights, each 8 × 32 tile
    /// dequantised into `out` as soon as its sums are known (while they are in cache).
    #[allow(clippy::too_many_arguments)]
    fn multiply(
        &self,
        q: &[u8],
        sx: &[f32],
        zx: &[i32],
        rows: usize,
        residual: Option<&[f32]>,
        out: &mut [f32],
        vnni: bool,
    ) {
        let (n, kp, np) = (self.n, self.kp, self.np);
        let mut tile = [[0i32; NR]; MR];
        for jb2 in 0..np / NR {
            let w = &self.packed[jb2 * 2 * kp * 16..(jb2 + 1) * 2 * kp * 16];
            let cols = jb2 * NR..(jb2 * NR + NR).min(n);
            for r0 in (0..rows).step_by(MR) {
                let a = &q[r0 * kp..(r0 + MR) * kp];
                if vnni {
                    #[cfg(target_arch = "x86_64")]
                    // SAFETY: `has_vnni` found the features; `a` holds MR rows of `kp` bytes
                    // and `w` two column blocks of `kp · 16` bytes.
                    unsafe {
                        kernel_vnni(a, w, kp, &mut tile);
                    }
                } else {
                    kernel_portable(a, w, kp, &mut tile);
                }
                let tile_rows = r0..(r0 + MR).min(rows);
                dequantise_tile(
                    &tile,
                    Epilogue {
                        sx: &sx[tile_rows.clone()],
                        zx: &zx[tile_rows.clone()],
                        colsum: &self.colsum[cols.clone()],
                        scale: &self.scale[cols.clone()],
                        bias: &self.bias[cols.clone()],
                    },
                    &mut out[r0 * n..],
                    residual.map(|r| &r[r0 * n..]),
                    n,
                    cols.start,
                );
            }
        }
    }
}

/// What [`dequantise_tile`] needs of a tile's rows (`sx`, `zx`) and columns (`colsum`,
/// `scale`, `bias`).
#[derive(Clone, Copy)]
struct Epilogue<'a> {
    sx: &'a [f32],
    zx: &'a [i32],
    colsum: &'a [i32],
    scale: &'a [f32],
    bias: &'a [f32],
}

super::ops::simd_dispatch! {
    /// `out[r·n + j0 + j] = (a − z·colsum)·s·scale + bias [+ residual]` for the tile's
    /// `e.sx.len()` rows and `e.scale.len()` columns (`out` and `residual` start at the tile's
    /// first row; row stride `n`).
    fn dequantise_tile(
        tile: &[[i32; NR]; MR],
        e: Epilogue<'_>,
        out: &mut [f32],
        residual: Option<&[f32]>,
        n: usize,
        j0: usize
    ) {
        let w = e.scale.len();
        let (colsum, scale, bias) = (&e.colsum[..w], &e.scale[..w], &e.bias[..w]);
        for (r, ((a, &s), &z)) in tile.iter().zip(e.sx).zip(e.zx).enumerate() {
            let o = &mut out[r * n + j0..r * n + j0 + w];
            let a = &a[..w];
            for j in 0..w {
                o[j] = (a[j] - z * colsum[j]) as f32 * (s * scale[j]) + bias[j];
            }
            if let Some(res) = residual {
                for (o, &r) in o.iter_mut().zip(&res[r * n + j0..r * n + j0 + w]) {
                    *o += r;
                }
            }
        }
    }
}

impl super::ops::PackedLinear for QuantLinear {
    fn run_chunk(&self, x: &[f32], rows: usize, residual: Option<&[f32]>, out: &mut [f32]) {
        self.run_chunk_with(x, rows, residual, out, has_vnni());
    }

    fn pack(weight_t: &[f32], k: usize, n: usize, bias: &[f32]) -> candle_core::Result<Self> {
        Self::new(weight_t, k, n, bias)
    }

    fn pack_transposed_rows(
        src: &[f32],
        stride: usize,
        n: usize,
        k: usize,
    ) -> candle_core::Result<Self> {
        Self::from_transposed_rows(src, stride, n, k)
    }

    fn pack_rows(src: &[f32], stride: usize, k: usize, n: usize) -> candle_core::Result<Self> {
        Self::from_rows(src, stride, k, n, vec![0.0; n])
    }

    /// Input features.
    fn in_features(&self) -> usize {
        self.k
    }

    /// Output features.
    fn out_features(&self) -> usize {
        self.n
    }

    /// The softmax straight into bytes with its known scale (1/255, zero point 0)
    /// ([`super::ops::softmax_u8`]); `inv` becomes `255 / Σ q`, so that the quantised weights
    /// sum to one.
    fn weigh_scores(
        &self,
        s: &mut [f32],
        rows: usize,
        scale: f32,
        out: &mut [f32],
        inv: &mut [f32],
    ) {
        let (n, kp) = (self.k, self.kp);
        QUANT.with(|cell| {
            let mut buf = cell.borrow_mut();
            // softmax_u8 writes every byte of the `rows` rows; the padding rows up to a
            // multiple of MR are zero
            let (p, _) = buf.parts(rows.div_ceil(MR) * MR * kp, 0);
            p[rows * kp..].fill(0);
            super::ops::softmax_u8(s, n, scale, p, kp, &mut inv[..rows]);
            let sx = [1.0 / 255.0; super::ops::PACKED_CHUNK];
            let zx = [0i32; super::ops::PACKED_CHUNK];
            self.forward_quantised(p, &sx[..rows], &zx[..rows], rows, out);
        });
    }
}

/// A weight's scale from its column's largest `|w|`: `max / 127`, or 1 for a zero column.
fn weight_scale(amax: f32) -> f32 {
    if amax > 0.0 { amax / 127.0 } else { 1.0 }
}

/// `w / s_w` rounded half away from zero by truncation (`|w / s_w| ≤ 127` by the scale).
#[inline(always)]
fn round_weight(v: f32) -> i8 {
    (v + if v < 0.0 { -0.5 } else { 0.5 }) as i8
}

/// Where `q_w[i, j]` lies in [`QuantLinear::packed`] (column blocks of 16, groups of 4 rows).
fn packed_index(kp: usize, i: usize, j: usize) -> usize {
    (j / 16) * kp * 16 + (i / 4) * 64 + (j % 16) * 4 + i % 4
}

/// The error of a weight matrix that holds a value that is not finite.
fn not_finite() -> candle_core::Error {
    candle_core::Error::Msg("int8 linear: the weights hold a value that is not finite".into())
}

super::ops::simd_dispatch! {
    /// `q[j] = round(w[j] · inv[j])` (half away from zero; `|w · inv| ≤ 127` by the scales),
    /// added to `colsum[j]`.
    fn quantise_weights(w: &[f32], inv: &[f32], q: &mut [i8], colsum: &mut [i32]) {
        for (((q, &w), &inv), c) in q.iter_mut().zip(w).zip(inv).zip(colsum.iter_mut()) {
            *q = round_weight(w * inv);
            *c += i32::from(*q);
        }
    }
}

super::ops::simd_dispatch! {
    /// [`quantise_weights`] of one column of `W` (one scale): its bytes and their sum.
    fn quantise_column(w: &[f32], inv: f32, q: &mut [i8]) -> i32 {
        let mut sum = 0i32;
        for (q, &w) in q.iter_mut().zip(w) {
            *q = round_weight(w * inv);
            sum += i32::from(*q);
        }
        sum
    }
}

super::ops::simd_dispatch! {
    /// `max |x|`, or `None` when a value is not finite.
    fn abs_max(x: &[f32]) -> Option<f32> {
        let mut m = [0f32; 16];
        let mut bad = false;
        let mut chunks = x.chunks_exact(16);
        for c in &mut chunks {
            for l in 0..16 {
                let a = c[l].abs();
                m[l] = if a > m[l] { a } else { m[l] };
                bad |= !c[l].is_finite();
            }
        }
        for &v in chunks.remainder() {
            m[0] = if v.abs() > m[0] { v.abs() } else { m[0] };
            bad |= !v.is_finite();
        }
        (!bad).then(|| m.iter().fold(0f32, |a, &v| if v > a { v } else { a }))
    }
}

super::ops::simd_dispatch! {
    /// `amax[j] = max(amax[j], |row[j]|)`, or `None` when a value is not finite.
    fn column_abs_max(row: &[f32], amax: &mut [f32]) -> Option<()> {
        let mut bad = false;
        for (m, &v) in amax.iter_mut().zip(row) {
            let a = v.abs();
            *m = if a > *m { a } else { *m };
            bad |= !v.is_finite();
        }
        (!bad).then_some(())
    }
}

/// A thread's scratch of [`QuantLinear::run_chunk`]: the quantised rows and one row without
/// its outlier channels, kept between calls (a layer runs ~30 chunks per frame and per thread).
#[derive(Default)]
struct Scratch {
    q: Vec<u8>,
    row: Vec<f32>,
}

impl Scratch {
    /// The buffers, of these lengths (`q` at least).
    fn parts(&mut self, q: usize, row: usize) -> (&mut [u8], &mut [f32]) {
        if self.q.len() < q {
            self.q.resize(q, 0);
        }
        self.row.resize(row, 0.0);
        (&mut self.q[..q], &mut self.row[..])
    }
}

/// An input channel is an outlier when its largest `|x|` over a chunk's rows exceeds this
/// multiple of the median channel's (trained ViTs carry a few channels 10–100× larger than the
/// rest; in a row quantised as a whole they set the scale and leave every other channel a few
/// levels: `outlier_channels_widen_the_error_of_every_other_channel`).
const OUTLIER_RATIO: f32 = 6.0;

/// At most one input channel in this many is treated as an outlier (the largest ones).
const OUTLIER_SHARE: usize = 32;

/// The outlier channels of the rows `x` (`k` values each), largest first: LLM.int8's
/// decomposition (Dettmers et al. 2022), with the threshold relative to the median channel
/// instead of an absolute 6. Empty for rows without outliers (then the int8 product is the
/// plain one, bit for bit) and for rows with values that are not finite (the quantisation
/// gives those NaN).
fn outlier_channels(x: &[f32], k: usize) -> Vec<usize> {
    let mut amax = vec![0f32; k];
    for row in x.chunks_exact(k) {
        if column_abs_max(row, &mut amax).is_none() {
            return Vec::new();
        }
    }
    let mut sorted = amax.clone();
    let mid = k / 2;
    let (_, median, _) = sorted.select_nth_unstable_by(mid, f32::total_cmp);
    let limit = *median * OUTLIER_RATIO;
    if limit <= 0.0 {
        return Vec::new();
    }
    let mut out: Vec<usize> = (0..k).filter(|&j| amax[j] > limit).collect();
    out.sort_by(|&a, &b| amax[b].total_cmp(&amax[a]).then(a.cmp(&b)));
    out.truncate(k / OUTLIER_SHARE);
    out
}

thread_local! {
    static QUANT: std::cell::RefCell<Scratch> = std::cell::RefCell::new(Scratch::default());
}

super::ops::simd_dispatch! {
/// Quantises `row` into `q` and returns its scale `s_x` and zero point `z`; a NaN scale when
/// a value is not finite (the row's outputs are then NaN, as in f32).
fn quantise_row(row: &[f32], q: &mut [u8]) -> (f32, i32) {
    // min, max and NaN in 16 lanes (`<`/`>` selects vectorise; `f32::min` does not)
    let (mut lo, mut hi, mut nan) = ([0f32; 16], [0f32; 16], [false; 16]);
    let mut chunks = row.chunks_exact(16);
    for c in &mut chunks {
        for l in 0..16 {
            let v = c[l];
            lo[l] = if v < lo[l] { v } else { lo[l] };
            hi[l] = if v > hi[l] { v } else { hi[l] };
            nan[l] |= v.is_nan();
        }
    }
    for &v in chunks.remainder() {
        lo[0] = if v < lo[0] { v } else { lo[0] };
        hi[0] = if v > hi[0] { v } else { hi[0] };
        nan[0] |= v.is_nan();
    }
    let lo = lo.iter().fold(0f32, |a, &v| if v < a { v } else { a });
    let hi = hi.iter().fold(0f32, |a, &v| if v > a { v } else { a });
    if nan.contains(&true) || !(lo.is_finite() && hi.is_finite()) {
        q.fill(0);
        return (f32::NAN, 0);
    }
    let s = if hi > lo { (hi - lo) / 255.0 } else { 1.0 };
    let inv = 1.0 / s;
    let z = (-lo * inv).round().clamp(0.0, 255.0);
    // A value clamped to [0, 255] plus 1.5·2²³ holds it rounded (to nearest, ties to even) in
    // the low bits of its mantissa: read with a mask, this vectorises, where `f32::round` is a
    // libm call per value on baseline x86-64 and a cast saturates lane by lane.
    const ROUND: f32 = 12_582_912.0;
    for (q, &v) in q.iter_mut().zip(row) {
        *q = (((v * inv + z).clamp(0.0, 255.0) + ROUND).to_bits() & 0xFF) as u8;
    }
    (s, z as i32)
}
}

/// Whether the CPU has AVX512-VNNI (with AVX512F), checked once.
pub(crate) fn has_vnni() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        static VNNI: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
        *VNNI.get_or_init(|| {
            std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512vnni")
        })
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// `acc[r][j] = Σ_k a[r, k] · w[k, j]` over [`MR`] rows of `a` (`kp` unsigned bytes each) and
/// two packed column blocks `w` (module layout), without VNNI.
fn kernel_portable(a: &[u8], w: &[i8], kp: usize, acc: &mut [[i32; NR]; MR]) {
    for (r, acc) in acc.iter_mut().enumerate() {
        *acc = [0; NR];
        let row = &a[r * kp..(r + 1) * kp];
        for (half, acc) in acc.chunks_exact_mut(16).enumerate() {
            let w = &w[half * kp * 16..(half + 1) * kp * 16];
            for (kb, a4) in row.chunks_exact(4).enumerate() {
                let w = &w[kb * 64..kb * 64 + 64];
                for (j, acc) in acc.iter_mut().enumerate() {
                    let w4 = &w[j * 4..j * 4 + 4];
                    *acc += (0..4)
                        .map(|kk| i32::from(a4[kk]) * i32::from(w4[kk]))
                        .sum::<i32>();
                }
            }
        }
    }
}

/// [`kernel_portable`] with `vpdpbusd`: per group of 4 rows of `w`, one 64-byte load per column
/// block, and per row of `a` its 4 bytes broadcast and multiplied into 2 × 16 lanes.
///
/// # Safety
/// The CPU must have AVX512F and AVX512-VNNI; `a` must hold [`MR`] · `kp` bytes and `w`
/// 2 · `kp` · 16.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vnni")]
unsafe fn kernel_vnni(a: &[u8], w: &[i8], kp: usize, acc: &mut [[i32; NR]; MR]) {
    use std::arch::x86_64::*;
    debug_assert!(a.len() >= MR * kp && w.len() >= 2 * kp * 16);
    let mut s = [[_mm512_setzero_si512(); 2]; MR];
    let a = a.as_ptr();
    let w0 = w.as_ptr();
    // SAFETY: every read is inside `a` (row r < MR, byte 4·kb + 3 < kp) and `w` (two blocks of
    // kp · 16 bytes), as the caller guarantees.
    unsafe {
        let w1 = w0.add(kp * 16);
        for kb in 0..kp / 4 {
            let b0 = _mm512_loadu_si512(w0.add(kb * 64).cast());
            let b1 = _mm512_loadu_si512(w1.add(kb * 64).cast());
            for (r, s) in s.iter_mut().enumerate() {
                let x = _mm512_set1_epi32(a.add(r * kp + kb * 4).cast::<i32>().read_unaligned());
                s[0] = _mm512_dpbusd_epi32(s[0], x, b0);
                s[1] = _mm512_dpbusd_epi32(s[1], x, b1);
            }
        }
        for (acc, s) in acc.iter_mut().zip(&s) {
            _mm512_storeu_si512(acc.as_mut_ptr().cast(), s[0]);
            _mm512_storeu_si512(acc.as_mut_ptr().add(16).cast(), s[1]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::candle::ops::PackedLinear;

    /// A seeded uniform value in [-1, 1).
    fn uniform(state: &mut u64) -> f32 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }

    fn reference(x: &[f32], m: usize, w: &[f32], k: usize, n: usize, b: &[f32]) -> Vec<f64> {
        let mut y = vec![0f64; m * n];
        for i in 0..m {
            for j in 0..n {
                y[i * n + j] = f64::from(b[j])
                    + (0..k)
                        .map(|t| f64::from(x[i * k + t]) * f64::from(w[t * n + j]))
                        .sum::<f64>();
            }
        }
        y
    }

    #[test]
    fn integer_sums_equal_the_exact_product_of_the_quantised_values() {
        // sizes that are not multiples of the blocks (k % 4, n % 32, m % 8)
        let (m, k, n) = (13, 37, 45);
        let mut st = 7;
        let x: Vec<f32> = (0..m * k).map(|_| uniform(&mut st)).collect();
        let w: Vec<f32> = (0..k * n).map(|_| uniform(&mut st)).collect();
        let b: Vec<f32> = (0..n).map(|_| uniform(&mut st)).collect();
        let q = QuantLinear::new(&w, k, n, &b).unwrap();
        let y = q.forward(&x, m, None);
        // independent expectation: quantise by the formulas, multiply in f64
        for i in 0..m {
            let row = &x[i * k..(i + 1) * k];
            let lo = row.iter().fold(0f32, |a, &v| a.min(v));
            let hi = row.iter().fold(0f32, |a, &v| a.max(v));
            let sx = (hi - lo) / 255.0;
            let z = (-lo / sx).round();
            for j in 0..n {
                let sw = (0..k).fold(0f32, |a, t| a.max(w[t * n + j].abs())) / 127.0;
                let dot: f64 = (0..k)
                    .map(|t| {
                        let qx = (row[t] / sx + z).round_ties_even().clamp(0.0, 255.0) - z;
                        let qw = (w[t * n + j] / sw).round().clamp(-127.0, 127.0);
                        f64::from(qx) * f64::from(qw)
                    })
                    .sum();
                let want = dot * f64::from(sx) * f64::from(sw) + f64::from(b[j]);
                let got = f64::from(y[i * n + j]);
                assert!(
                    (got - want).abs() < 1e-5 * (1.0 + want.abs()),
                    "{i},{j}: {got} vs {want}"
                );
            }
        }
        // and close to the float product: per-channel / per-token int8 loses ~1 % of a row's
        // range at most
        let exact = reference(&x, m, &w, k, n, &b);
        let worst = y
            .iter()
            .zip(&exact)
            .map(|(a, e)| (f64::from(*a) - e).abs())
            .fold(0.0, f64::max);
        assert!(worst < 0.05 * (k as f64).sqrt(), "worst error {worst}");
    }

    #[test]
    fn vnni_and_portable_kernels_agree_bit_for_bit_on_any_thread_count() {
        let (m, k, n) = (150, 384, 96);
        let mut st = 11;
        let mut x: Vec<f32> = (0..m * k).map(|_| uniform(&mut st) * 3.0).collect();
        // two outlier channels in the rows of the second chunk only: the split is per chunk
        for row in x.chunks_exact_mut(k).skip(CHUNK).take(CHUNK) {
            row[5] *= 50.0;
            row[300] *= 40.0;
        }
        let w: Vec<f32> = (0..k * n).map(|_| uniform(&mut st) * 0.1).collect();
        let b: Vec<f32> = (0..n).map(|_| uniform(&mut st)).collect();
        let r: Vec<f32> = (0..m * n).map(|_| uniform(&mut st)).collect();
        let q = QuantLinear::new(&w, k, n, &b).unwrap();
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| q.forward(&x, m, Some(&r)))
        };
        let one = run(1);
        assert_eq!(one, run(3));
        // the portable kernel on the same rows
        let mut portable = vec![0f32; m * n];
        for (c, out) in portable.chunks_mut(CHUNK * n).enumerate() {
            let rows = out.len() / n;
            q.run_chunk_with(
                &x[c * CHUNK * k..(c * CHUNK + rows) * k],
                rows,
                Some(&r[c * CHUNK * n..(c * CHUNK + rows) * n]),
                out,
                false,
            );
        }
        assert_eq!(one, portable, "VNNI on this CPU: {}", has_vnni());
    }

    /// `|y − y_f32| ≤ Σ_k (|Δx_k|·|w_k| + |x_k|·|Δw_k| + |Δx_k|·|Δw_k|)` with the rounding
    /// steps `|Δw| ≤ s_w/2` and `|Δx| ≤ s_x/2`, where the row's scale `s_x` spans the channels
    /// that are quantised, and the `outliers` (multiplied in f32) have `Δx = 0`: the bound,
    /// written from the scales alone.
    fn bound(row: &[f32], outliers: &[usize], w: &[f32], k: usize, n: usize, j: usize) -> f64 {
        let quantised = || (0..k).filter(|t| !outliers.contains(t)).map(|t| row[t]);
        let lo = quantised().fold(0f32, f32::min);
        let hi = quantised().fold(0f32, f32::max);
        let dx = f64::from((hi - lo) / 255.0) / 2.0;
        let sw = (0..k).fold(0f32, |a, t| a.max(w[t * n + j].abs())) / 127.0;
        let dw = f64::from(sw) / 2.0;
        (0..k)
            .map(|t| {
                let dx = if outliers.contains(&t) { 0.0 } else { dx };
                dx * f64::from(w[t * n + j].abs()) + f64::from(row[t].abs()) * dw + dx * dw
            })
            .sum::<f64>()
            * 1.001
            + 1e-6
    }

    #[test]
    fn outlier_channels_are_multiplied_apart() {
        // Trained ViTs carry a few activation channels 10–100× larger than the rest; random
        // weights do not. Quantised with the rest, they would set every token's scale and leave
        // the other channels a few levels (the error grew more than tenfold here). Found per
        // chunk and multiplied in f32, they leave the error near the plain one, within the
        // bound of the scale without them.
        let (m, k, n) = (16, 384, 64);
        let mut st = 5;
        let x: Vec<f32> = (0..m * k).map(|_| uniform(&mut st)).collect();
        let w: Vec<f32> = (0..k * n).map(|_| uniform(&mut st) * 0.05).collect();
        let b = vec![0f32; n];
        let q = QuantLinear::new(&w, k, n, &b).unwrap();
        let error = |x: &[f32], outliers: &[usize]| {
            let y = q.forward(x, m, None);
            let exact = reference(x, m, &w, k, n, &b);
            let mut worst = 0f64;
            for i in 0..m {
                for j in 0..n {
                    let e = (f64::from(y[i * n + j]) - exact[i * n + j]).abs();
                    let row = &x[i * k..(i + 1) * k];
                    assert!(e <= bound(row, outliers, &w, k, n, j), "{i},{j}: {e}");
                    worst = worst.max(e);
                }
            }
            worst
        };
        assert!(outlier_channels(&x, k).is_empty());
        let plain = error(&x, &[]);
        let mut with_outliers = x.clone();
        for row in with_outliers.chunks_exact_mut(k) {
            row[7] *= 60.0;
            row[200] *= -60.0;
        }
        let found = outlier_channels(&with_outliers, k);
        assert_eq!(found.len(), 2);
        assert!(found.contains(&7) && found.contains(&200), "{found:?}");
        let with = error(&with_outliers, &found);
        assert!(
            with < 5.0 * plain,
            "outliers: {with:.3e}, without: {plain:.3e}"
        );
        // at most one channel in OUTLIER_SHARE, the largest: a row of growing values
        let ramp: Vec<f32> = (0..k)
            .map(|t| if t % 50 == 0 { 100.0 + t as f32 } else { 1.0 })
            .collect();
        let found = outlier_channels(&ramp, k);
        assert_eq!(found.len(), (k / 50 + 1).min(k / OUTLIER_SHARE));
        assert_eq!(found[0], 350);
        // a non-finite value: no split (the row's outputs are NaN either way)
        let mut bad = x.clone();
        bad[3] = f32::NAN;
        assert!(outlier_channels(&bad, k).is_empty());
    }

    #[test]
    fn attention_heads_packed_from_the_qkv_rows_equal_the_gathered_matrices() {
        // one head's keys and values inside wider rows (stride 50, offset 7), head sizes with
        // and without a multiple of 4, token counts that are not multiples of the blocks
        let (n, stride, at) = (37, 50, 7);
        let mut st = 3;
        let mut src: Vec<f32> = (0..n * stride).map(|_| uniform(&mut st) * 2.0).collect();
        src[at + 5 * stride] = 0.0;
        for hd in [10, 16] {
            let kt: Vec<f32> = (0..hd)
                .flat_map(|d| (0..n).map(move |j| (j, d)))
                .map(|(j, d)| src[at + j * stride + d])
                .collect();
            let v: Vec<f32> = (0..n)
                .flat_map(|j| src[at + j * stride..at + j * stride + hd].to_vec())
                .collect();
            let keys = QuantLinear::from_transposed_rows(&src[at..], stride, n, hd).unwrap();
            assert_eq!(keys, QuantLinear::new(&kt, hd, n, &vec![0.0; n]).unwrap());
            let values = QuantLinear::from_rows(&src[at..], stride, n, hd, vec![0.0; hd]).unwrap();
            assert_eq!(values, QuantLinear::new(&v, n, hd, &vec![0.0; hd]).unwrap());
        }
        src[at + 3 * stride + 2] = f32::NAN;
        assert!(QuantLinear::from_transposed_rows(&src[at..], stride, n, 10).is_err());
        assert!(QuantLinear::from_rows(&src[at..], stride, n, 10, vec![0.0; 10]).is_err());
    }

    #[test]
    fn bad_rows_and_weights() {
        let q = QuantLinear::new(&[1.0, 2.0, 3.0, 4.0], 2, 2, &[0.0, 0.0]).unwrap();
        let y = q.forward(&[f32::NAN, 1.0, 0.0, 0.0], 2, None);
        assert!(y[0].is_nan() && y[1].is_nan());
        assert_eq!(&y[2..], &[0.0, 0.0], "a zero row gives the bias");
        assert!(QuantLinear::new(&[1.0, f32::INFINITY], 1, 2, &[0.0, 0.0]).is_err());
        assert!(QuantLinear::new(&[1.0, 2.0], 1, 2, &[0.0]).is_err());
        assert_eq!((q.in_features(), q.out_features()), (2, 2));
    }
}
