//! Stride-1 3×3 convolutions by Winograd's minimal filtering F(2×2, 3×3) (Lavin and Gray,
//! "Fast Algorithms for Convolutional Neural Networks", CVPR 2016): each 2×2 block of output
//! pixels ("tile") takes 16 multiply-adds per (input, output) channel pair instead of 36.
//!
//! With the 4×4 input patch `d` of a tile and a 3×3 kernel `g`:
//! `Y = Aᵀ [(G g Gᵀ) ⊙ (Bᵀ d B)] A`, where
//! `Bᵀ = [[1, 0, −1, 0], [0, 1, 1, 0], [0, −1, 1, 0], [0, 1, 0, −1]]`,
//! `G = [[1, 0, 0], [½, ½, ½], [½, −½, ½], [0, 0, 1]]` and `Aᵀ = [[1, 1, 1, 0], [0, 1, −1, −1]]`.
//! Summed over the input channels, the `⊙` becomes 16 matrix products (one per position `ξ` of
//! the 4×4 transformed patch): `M[ξ] (c_out × tiles) = U[ξ] (c_out × c_in) · V[ξ] (c_in × tiles)`,
//! run by `gemm`. Every coefficient is 0, ±1 or ±½ (exact in binary), so the result differs
//! from the direct sum by f32 round-off of a few more additions (tested against candle's
//! `conv2d` in f64).
//!
//! Written here because neither `gemm` nor candle has a Winograd convolution. Measured at the
//! DPT head's shapes against im2col (`cargo run --release -p moma-depth --example
//! cpu_kernels`) and, before its removal, the channels-last direct convolution it replaced
//! (0.5–0.96× its time; docs/depth-model.md).
//!
//! The output is computed in bands of tile rows, each band serially (input transform, 16
//! products, output transform) and the bands in parallel: a band's bits do not depend on the
//! thread count.

use rayon::prelude::*;

use super::ops::{MatRef, SendPtr, sgemm};

/// Bytes of one band's transformed input and products (`16·(c_in + c_out)·tiles` floats):
/// bounds the scratch memory and keeps it in cache.
const BAND_BYTES: usize = 2 << 20;

/// Fewest tile rows per band with an upsampled input ([`Source::Upsampled`]).
const UPSAMPLED_BAND_ROWS: usize = 4;

/// `U[ξ][co][ci] = (G g Gᵀ)[ξ]` for `weight` `(c_out, c_in, 3, 3)`: `(16, c_out, c_in)`.
fn transform_weights(weight: &[f32], c_out: usize, c_in: usize) -> Vec<f32> {
    const G: [[f64; 3]; 4] = [
        [1.0, 0.0, 0.0],
        [0.5, 0.5, 0.5],
        [0.5, -0.5, 0.5],
        [0.0, 0.0, 1.0],
    ];
    let mut u = vec![0f32; 16 * c_out * c_in];
    for co in 0..c_out {
        for ci in 0..c_in {
            let g = &weight[(co * c_in + ci) * 9..(co * c_in + ci + 1) * 9];
            // G g (4 × 3), then (G g) Gᵀ (4 × 4), in f64, rounded once to f32
            let mut gg = [[0f64; 3]; 4];
            for (i, row) in gg.iter_mut().enumerate() {
                for (j, v) in row.iter_mut().enumerate() {
                    *v = (0..3).map(|k| G[i][k] * f64::from(g[k * 3 + j])).sum();
                }
            }
            for (i, row) in gg.iter().enumerate() {
                for (j, gj) in G.iter().enumerate() {
                    let v: f64 = (0..3).map(|k| row[k] * gj[k]).sum();
                    u[((i * 4 + j) * c_out + co) * c_in + ci] = v as f32;
                }
            }
        }
    }
    u
}

/// A thread's scratch: the transformed input `V` (`16 · c_in · tiles`), the products `M`
/// (`16 · c_out · tiles`) and four input rows split by column parity.
#[derive(Default)]
struct Scratch {
    v: Vec<f32>,
    m: Vec<f32>,
    rows: Vec<f32>,
    y: Vec<f32>,
    /// [`Source::Upsampled`]: source rows interpolated along x, and the band's input rows.
    hx: Vec<f32>,
    up: Vec<f32>,
    /// [`Fusion::project`]: one channel's output rows, and their weighted sum.
    band: Vec<f32>,
    proj: Vec<f32>,
}

thread_local! {
    static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::new(Scratch::default());
}

/// What [`conv3x3`] fuses around the convolution: `project?(relu_out?(conv(relu_in?(x)) +
/// bias + residual?))`.
pub(super) struct Fusion<'a> {
    pub bias: &'a [f32],
    pub relu_in: bool,
    pub residual: Option<&'a [f32]>,
    pub relu_out: bool,
    /// A 1×1 convolution to one channel after everything else: `Σ_co weight[co]·y[co] + bias`
    /// (the DPT head's last layer). The output is then `(1, h, w)`, and the `c_out` channels
    /// are never stored.
    pub project: Option<(&'a [f32], f32)>,
}

/// Where [`conv3x3`]'s input rows come from.
#[derive(Clone, Copy)]
pub(super) enum Source<'a> {
    /// The `(c_in, h, w)` planes.
    Planes(&'a [f32]),
    /// `(c_in, h_s, w_s)` planes upsampled bilinearly to `(h, w)` on the fly, band by band
    /// (`align_corners = true`; the vertical and horizontal taps of
    /// [`super::ops::upsample_bilinear_align_corners`], whose rows this computes bit for bit):
    /// the upsampled planes are never stored.
    Upsampled {
        src: &'a [f32],
        h_s: usize,
        w_s: usize,
    },
}

/// The stride-1, padding-1 3×3 convolution of `src` (`(c_in, h, w)` planes, or planes
/// upsampled to that size) with `weight` `(c_out, c_in, 3, 3)` and what `fusion` adds:
/// `(c_out, h, w)`, or `(1, h, w)` with [`Fusion::project`]. The caller checks the sizes
/// (`src`, `weight` `9·c_in·c_out`, `bias` `c_out`, `residual` `c_out·h·w`).
pub(super) fn conv3x3(
    src: Source<'_>,
    (c_in, h, w): (usize, usize, usize),
    weight: &[f32],
    c_out: usize,
    fusion: &Fusion<'_>,
) -> Vec<f32> {
    let u = transform_weights(weight, c_out, c_in);
    let (tiles_y, tiles_x) = (h.div_ceil(2), w.div_ceil(2));
    let per_tile = 16 * (c_in + c_out) * 4;
    let band_rows = (BAND_BYTES / (per_tile * tiles_x)).clamp(1, tiles_y);
    // an upsampled input interpolates the source rows a band needs along x: at least
    // UPSAMPLED_BAND_ROWS tile rows, so that bands share few source rows (each interpolated
    // by both bands that read it)
    let band_rows = match src {
        Source::Planes(_) => band_rows,
        Source::Upsampled { .. } => band_rows.max(UPSAMPLED_BAND_ROWS).min(tiles_y),
    };
    let channels = if fusion.project.is_some() { 1 } else { c_out };
    let mut dst = super::ops::zeroed(channels * h * w);
    let out = SendPtr(dst.as_mut_ptr());
    let bands = tiles_y.div_ceil(band_rows);
    let taps = match src {
        Source::Planes(_) => None,
        Source::Upsampled { h_s, w_s, .. } => Some((
            crate::preprocess::align_corners_taps(h_s, h),
            crate::preprocess::align_corners_taps(w_s, w),
        )),
    };
    (0..bands).into_par_iter().for_each(|b| {
        let ty0 = b * band_rows;
        let ty1 = (ty0 + band_rows).min(tiles_y);
        SCRATCH.with(|cell| {
            let s = &mut *cell.borrow_mut();
            let input = Input {
                src,
                taps: taps.as_ref().map(|(y, x)| (&y[..], &x[..])),
                c_in,
                h,
                w,
            };
            band(s, &input, &u, c_out, fusion, (ty0, ty1), out);
        });
    });
    dst
}

/// A band's view of [`conv3x3`]'s input.
struct Input<'a> {
    src: Source<'a>,
    /// The vertical and horizontal taps of [`Source::Upsampled`].
    taps: Option<(&'a [Taps], &'a [Taps])>,
    c_in: usize,
    h: usize,
    w: usize,
}

/// `(i0, i1, w0, w1)`: one output coordinate of an `align_corners` bilinear resize.
type Taps = (usize, usize, f32, f32);

/// Tile rows `ty0..ty1` of [`conv3x3`]: output rows `2·ty0 .. min(2·ty1, h)` of every channel.
#[allow(clippy::too_many_arguments)]
fn band(
    s: &mut Scratch,
    input: &Input<'_>,
    u: &[f32],
    c_out: usize,
    fusion: &Fusion<'_>,
    (ty0, ty1): (usize, usize),
    out: SendPtr,
) {
    let (c_in, h, w) = (input.c_in, input.h, input.w);
    let tiles_x = w.div_ceil(2);
    let tiles = (ty1 - ty0) * tiles_x;
    // Four input rows, each split by the parity of its padded column p = x + 1 (zero outside
    // 0..w): `e[k]` holds input column 2k − 1 and `o[k]` column 2k, k ≤ tiles_x. A tile's
    // four columns 2tx − 1 .. 2tx + 2 are then e[tx], o[tx], e[tx + 1], o[tx + 1]: every step
    // below reads and writes contiguous slices, which vectorises.
    let half = tiles_x + 1;
    s.v.resize(16 * c_in * tiles, 0.0);
    s.m.resize(16 * c_out * tiles, 0.0);
    s.rows.resize(8 * half, 0.0);
    let (v, m, rows) = (&mut s.v[..16 * c_in * tiles], &mut s.m, &mut s.rows);

    // V[ξ][ci][t] = (Bᵀ d B)[ξ] of tile t's 4×4 input patch d; the band reads input rows
    // 2·ty0 − 1 ..= 2·ty1 (those inside the image)
    let (y_lo, y_hi) = ((2 * ty0).saturating_sub(1), (2 * ty1 + 1).min(h));
    for ci in 0..c_in {
        let plane: &[f32] = match (input.src, input.taps) {
            (Source::Planes(src), _) => &src[ci * h * w..(ci + 1) * h * w],
            (Source::Upsampled { src, h_s, w_s }, Some((yt, xt))) => {
                // rows y_lo..y_hi of the upsampled plane, row y at (y − y_lo)·w
                let p = &src[ci * h_s * w_s..(ci + 1) * h_s * w_s];
                s.up.resize((y_hi - y_lo) * w, 0.0);
                super::ops::upsample_rows(p, w_s, &yt[y_lo..y_hi], xt, &mut s.hx, &mut s.up);
                &s.up[..]
            }
            (Source::Upsampled { .. }, None) => unreachable!("conv3x3 sets the taps"),
        };
        let row_at = |y: usize| match input.src {
            Source::Planes(_) => y * w,
            Source::Upsampled { .. } => (y - y_lo) * w,
        };
        for ty in ty0..ty1 {
            let rows4: [&[f32]; 4] = std::array::from_fn(|i| {
                let y = (2 * ty + i).wrapping_sub(1);
                if y < h {
                    &plane[row_at(y)..row_at(y) + w]
                } else {
                    &[]
                }
            });
            let at = (ci * tiles + (ty - ty0) * tiles_x, c_in * tiles);
            input_tiles(rows4, fusion.relu_in, rows, v, at, tiles_x);
        }
    }

    // M[ξ] = U[ξ] · V[ξ]
    for xi in 0..16 {
        // SAFETY: U[ξ] is c_out × c_in (row stride c_in), V[ξ] c_in × tiles and M[ξ]
        // c_out × tiles (row stride tiles), all inside their buffers; M does not alias them.
        unsafe {
            sgemm(
                c_out,
                tiles,
                c_in,
                m.as_mut_ptr().add(xi * c_out * tiles),
                tiles as isize,
                false,
                MatRef {
                    ptr: u.as_ptr().add(xi * c_out * c_in),
                    rs: c_in as isize,
                    cs: 1,
                },
                MatRef {
                    ptr: v.as_ptr().add(xi * c_in * tiles),
                    rs: tiles as isize,
                    cs: 1,
                },
                false,
            );
        }
    }

    // Y = Aᵀ M A per tile, plus the bias, residual and ReLU, into output rows 2ty, 2ty + 1
    s.y.resize(4 * tiles_x, 0.0);
    let (oy0, oy1) = (2 * ty0, (2 * ty1).min(h));
    if let Some((weight, bias)) = fusion.project {
        // each channel's rows into `s.band`, summed into `s.proj` in channel order
        s.band.resize((oy1 - oy0) * w, 0.0);
        s.proj.clear();
        s.proj.resize((oy1 - oy0) * w, 0.0);
        for (co, &wc) in weight.iter().enumerate().take(c_out) {
            for ty in ty0..ty1 {
                let (oy, end) = (2 * ty, (2 * ty + 2).min(h));
                let d = &mut s.band[(oy - oy0) * w..(end - oy0) * w];
                let mat = (co * tiles + (ty - ty0) * tiles_x, c_out * tiles);
                output_tiles(
                    m,
                    mat,
                    &mut s.y,
                    fusion.bias[co],
                    &[],
                    fusion.relu_out,
                    d,
                    w,
                );
            }
            super::ops::add_scaled(&mut s.proj, wc, &s.band);
        }
        // SAFETY: rows oy0..oy1 of the one output plane: this band's, written by this task only.
        let d = unsafe { std::slice::from_raw_parts_mut(out.get().add(oy0 * w), (oy1 - oy0) * w) };
        for (d, &p) in d.iter_mut().zip(&s.proj) {
            *d = p + bias;
        }
        return;
    }
    for co in 0..c_out {
        for ty in ty0..ty1 {
            let (oy, end) = (2 * ty, (2 * ty + 2).min(h));
            let at = (co * h + oy) * w;
            let len = (end - oy) * w;
            // SAFETY: rows oy..end of channel co: this band's rows, written by this task only.
            let d = unsafe { std::slice::from_raw_parts_mut(out.get().add(at), len) };
            let res = fusion.residual.map_or(&[][..], |r| &r[at..at + len]);
            let mat = (co * tiles + (ty - ty0) * tiles_x, c_out * tiles);
            output_tiles(
                m,
                mat,
                &mut s.y,
                fusion.bias[co],
                res,
                fusion.relu_out,
                d,
                w,
            );
        }
    }
}

super::ops::simd_dispatch! {
    /// One row of tiles of one input channel: `input` holds the four input rows `2ty − 1 ..
    /// 2ty + 2` (empty outside the image), `rows` is scratch of `8·(tiles_x + 1)` values, and
    /// `v[at.0 + ξ·at.1 + tx]` receives `(Bᵀ d B)[ξ]` of tile `tx`.
    fn input_tiles(
        input: [&[f32]; 4],
        relu_in: bool,
        rows: &mut [f32],
        v: &mut [f32],
        at: (usize, usize),
        tiles_x: usize,
    ) {
        // Each row split by the parity of its padded column p = x + 1 (zero outside 0..w):
        // `e[k]` holds input column 2k − 1 and `o[k]` column 2k, k ≤ tiles_x. A tile's four
        // columns 2tx − 1 .. 2tx + 2 are then e[tx], o[tx], e[tx + 1], o[tx + 1]: every step
        // below reads and writes contiguous slices, which vectorises.
        let half = tiles_x + 1;
        for (from, eo) in input.iter().zip(rows.chunks_exact_mut(2 * half)) {
            eo.fill(0.0);
            let (e, o) = eo.split_at_mut(half);
            let relu = |v: f32| if relu_in && v < 0.0 { 0.0 } else { v };
            for (k, pair) in from.chunks_exact(2).enumerate() {
                o[k] = relu(pair[0]);
                e[k + 1] = relu(pair[1]);
            }
            if from.len() % 2 == 1 {
                o[from.len() / 2] = relu(from[from.len() - 1]);
            }
        }
        // Bᵀ d, row combinations, in place: t0 = d0 − d2, t1 = d1 + d2, t2 = d2 − d1,
        // t3 = d1 − d3
        let (d01, d23) = rows[..8 * half].split_at_mut(4 * half);
        let (d0, d1) = d01.split_at_mut(2 * half);
        let (d2, d3) = d23.split_at_mut(2 * half);
        for p in 0..2 * half {
            let (a, b, c, d) = (d0[p], d1[p], d2[p], d3[p]);
            d0[p] = a - c;
            d1[p] = b + c;
            d2[p] = c - b;
            d3[p] = b - d;
        }
        // (Bᵀ d) B, column combinations
        let (base, stride) = at;
        for (i, t) in [&*d0, &*d1, &*d2, &*d3].into_iter().enumerate() {
            let (e, o) = t.split_at(half);
            let (v0, rest) = v[base + 4 * i * stride..].split_at_mut(stride);
            let (v1, rest) = rest.split_at_mut(stride);
            let (v2, v3) = rest.split_at_mut(stride);
            let (v0, v1, v2, v3) = (
                &mut v0[..tiles_x],
                &mut v1[..tiles_x],
                &mut v2[..tiles_x],
                &mut v3[..tiles_x],
            );
            for tx in 0..tiles_x {
                let (a, b, c, d) = (e[tx], o[tx], e[tx + 1], o[tx + 1]);
                v0[tx] = a - c;
                v1[tx] = b + c;
                v2[tx] = c - b;
                v3[tx] = b - d;
            }
        }
    }
}

super::ops::simd_dispatch! {
    /// One row of tiles of one output channel: `m[at.0 + ξ·at.1 + tx]` holds `M[ξ]` of tile
    /// `tx`, `y` is scratch of `4·tiles_x` values; `d` receives output rows `2ty` and `2ty + 1`
    /// (one row at an odd height's last tile row) of width `w`: `Aᵀ M A + bias [+ residual]`,
    /// `ReLU`-ed when `relu_out`. `residual` is empty or of `d`'s length.
    fn output_tiles(
        m: &[f32],
        at: (usize, usize),
        y: &mut [f32],
        bias: f32,
        residual: &[f32],
        relu_out: bool,
        d: &mut [f32],
        w: usize,
    ) {
        let tiles_x = w.div_ceil(2);
        let (base, stride) = at;
        let mm: [&[f32]; 16] = std::array::from_fn(|xi| &m[base + xi * stride..][..tiles_x]);
        let (y00, rest) = y.split_at_mut(tiles_x);
        let (y01, rest) = rest.split_at_mut(tiles_x);
        let (y10, y11) = rest.split_at_mut(tiles_x);
        for tx in 0..tiles_x {
            // Aᵀ M: s0 = m0 + m1 + m2 and s1 = m1 − m2 − m3 over the rows of the 4×4; then
            // the same over its columns
            let s0: [f32; 4] = std::array::from_fn(|j| mm[j][tx] + mm[4 + j][tx] + mm[8 + j][tx]);
            let s1: [f32; 4] =
                std::array::from_fn(|j| mm[4 + j][tx] - mm[8 + j][tx] - mm[12 + j][tx]);
            y00[tx] = s0[0] + s0[1] + s0[2];
            y01[tx] = s0[1] - s0[2] - s0[3];
            y10[tx] = s1[0] + s1[1] + s1[2];
            y11[tx] = s1[1] - s1[2] - s1[3];
        }
        let finish = |v: f32| {
            let v = v + bias;
            if relu_out && v < 0.0 { 0.0 } else { v }
        };
        let finish_res = |v: f32, r: f32| {
            let v = v + bias + r;
            if relu_out && v < 0.0 { 0.0 } else { v }
        };
        let ys = [(&*y00, &*y01), (&*y10, &*y11)];
        for (ri, (row, (ya, yb))) in d.chunks_mut(w).zip(ys).enumerate() {
            // even columns from ya, odd ones from yb
            let pairs = w / 2;
            if residual.is_empty() {
                for ((p, &a), &b) in row.chunks_exact_mut(2).zip(&ya[..pairs]).zip(&yb[..pairs]) {
                    p[0] = finish(a);
                    p[1] = finish(b);
                }
                if w % 2 == 1 {
                    row[w - 1] = finish(ya[pairs]);
                }
            } else {
                let r = &residual[ri * w..(ri + 1) * w];
                for (((p, r), &a), &b) in row
                    .chunks_exact_mut(2)
                    .zip(r.chunks_exact(2))
                    .zip(&ya[..pairs])
                    .zip(&yb[..pairs])
                {
                    p[0] = finish_res(a, r[0]);
                    p[1] = finish_res(b, r[1]);
                }
                if w % 2 == 1 {
                    row[w - 1] = finish_res(ya[pairs], r[w - 1]);
                }
            }
        }
    }
}
