//! What LWLR ([`super::lwlr`]) and the local correction ([`super::local`]) share: grid nodes,
//! separable Gaussian weight tables and the weighted node sums, the half-pixel-centre bilinear
//! resize of node values to full size (OpenCV `INTER_LINEAR` semantics) and the lazily computed,
//! cached full-size maps.

use std::sync::{Arc, OnceLock};

use ndarray::Array2;
use rayon::prelude::*;

use crate::image::ImageSize;
use crate::kernels::{LWLR_BLOCK, lwlr_row_sums};

/// Grid node positions (columns, rows), pixels: `offset + step·i` below the image size (at least
/// one node per axis, at `offset`); `step` 0 counts as 1.
pub(crate) fn grid_nodes(
    step_px: usize,
    offset_px: usize,
    size: ImageSize,
) -> (Vec<f64>, Vec<f64>) {
    let step = step_px.max(1);
    let axis = |len: usize| -> Vec<f64> {
        let v: Vec<f64> = (offset_px..len).step_by(step).map(|x| x as f64).collect();
        if v.is_empty() {
            vec![offset_px as f64]
        } else {
            v
        }
    };
    (axis(size.width), axis(size.height))
}

/// Half-pixel-centre source position of output coordinate `x` when resizing `n` nodes to `len`
/// pixels: `(x + ½)·n/len − ½`, clamped to `[0, n − 1]`; returns `(i0, i1, frac)`.
#[inline]
pub(crate) fn half_pixel_source(x: f64, n: usize, len: usize) -> (usize, usize, f64) {
    let src = (x + 0.5) * n as f64 / len as f64 - 0.5;
    if src <= 0.0 || n == 1 {
        return (0, 0, 0.0);
    }
    let i0 = src.floor() as usize;
    if i0 >= n - 1 {
        return (n - 1, n - 1, 0.0);
    }
    (i0, i0 + 1, src - i0 as f64)
}

/// The value at pixel `(u, v)` of the row-major `ny × nx` node map `m` resized to `size` as
/// [`resize_bilinear`] does, in f64.
pub(crate) fn interpolate_nodes(
    m: &[f64],
    nx: usize,
    ny: usize,
    size: ImageSize,
    u: f64,
    v: f64,
) -> f64 {
    let (x0, x1, fx) = half_pixel_source(u, nx, size.width);
    let (y0, y1, fy) = half_pixel_source(v, ny, size.height);
    let top = m[y0 * nx + x0] * (1.0 - fx) + m[y0 * nx + x1] * fx;
    let bot = m[y1 * nx + x0] * (1.0 - fx) + m[y1 * nx + x1] * fx;
    top * (1.0 - fy) + bot * fy
}

/// Bilinear resize of a row-major `ny × nx` f64 grid to `h × w` f32 (half-pixel centres, clamped).
/// Horizontal pass on the node rows first, then a vectorised vertical blend per output row.
pub(crate) fn resize_bilinear(
    src: &[f64],
    nx: usize,
    ny: usize,
    w: usize,
    h: usize,
) -> Array2<f32> {
    let xs: Vec<(usize, usize, f64)> = (0..w).map(|x| half_pixel_source(x as f64, nx, w)).collect();
    let mut rows = vec![0.0f32; ny * w];
    for r in 0..ny {
        let s = &src[r * nx..(r + 1) * nx];
        for (o, &(x0, x1, f)) in rows[r * w..(r + 1) * w].iter_mut().zip(&xs) {
            *o = (s[x0] * (1.0 - f) + s[x1] * f) as f32;
        }
    }
    let mut out = vec![0.0f32; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, orow)| {
        let (y0, y1, fy) = half_pixel_source(y as f64, ny, h);
        let (a, b) = (&rows[y0 * w..(y0 + 1) * w], &rows[y1 * w..(y1 + 1) * w]);
        let (wa, wb) = ((1.0 - fy) as f32, fy as f32);
        for ((o, &p), &q) in orow.iter_mut().zip(a).zip(b) {
            *o = p * wa + q * wb;
        }
    });
    Array2::from_shape_vec((h, w), out).unwrap_or_default()
}

/// Separable Gaussian weights of `n` samples at the nodes of a lattice `cols × rows`:
/// `w_k(i, j) = wu[k·stride + j] · wv[k·ny + i]`, `wu = exp(−(u_j − u_k)²/2b²)` (zero-padded to
/// a multiple of [`LWLR_BLOCK`] columns for the row-sum kernel), `wv` likewise in `v`.
pub(crate) struct WeightTables {
    /// Padded column count (multiple of [`LWLR_BLOCK`]).
    pub stride: usize,
    /// Rows.
    pub ny: usize,
    wu: Vec<f64>,
    wv: Vec<f64>,
}

impl WeightTables {
    /// Tables for samples at `uv` (pixels) and bandwidth given as `inv_2b2 = 1/(2b²)`.
    pub fn new(
        uv: impl ExactSizeIterator<Item = (f64, f64)> + Clone,
        cols: &[f64],
        rows: &[f64],
        inv_2b2: f64,
    ) -> Self {
        let n = uv.len();
        let nx = cols.len();
        let stride = nx.div_ceil(LWLR_BLOCK) * LWLR_BLOCK;
        let mut wu = vec![0.0f64; n * stride];
        for (k, (uk, _)) in uv.clone().enumerate() {
            for (j, &u) in cols.iter().enumerate() {
                let d = u - uk;
                wu[k * stride + j] = (-d * d * inv_2b2).exp();
            }
        }
        let ny = rows.len();
        let mut wv = vec![0.0f64; n * ny];
        for (k, (_, vk)) in uv.enumerate() {
            for (i, &v) in rows.iter().enumerate() {
                let d = v - vk;
                wv[k * ny + i] = (-d * d * inv_2b2).exp();
            }
        }
        Self { stride, ny, wu, wv }
    }

    /// Weight of sample `k` at node (row `i`, column `j`).
    #[inline]
    pub fn weight(&self, k: usize, i: usize, j: usize) -> f64 {
        self.wu[k * self.stride + j] * self.wv[k * self.ny + i]
    }

    /// The five weighted sums of node row `i`: `sums[m][j] = Σ_k coef_k[m]·wu[k·stride + j]`
    /// with `coef_k = fill(k, wv_k(i))` (e.g. `w·(1, x, x², y, x·y)`); `coef` has one entry per
    /// sample, each `sums[m]` length [`WeightTables::stride`].
    #[inline]
    pub fn row_sums(
        &self,
        i: usize,
        fill: impl Fn(usize, f64) -> [f64; 5],
        coef: &mut [[f64; 5]],
        sums: &mut [Vec<f64>; 5],
    ) {
        for (k, c) in coef.iter_mut().enumerate() {
            *c = fill(k, self.wv[k * self.ny + i]);
        }
        lwlr_row_sums(&self.wu, self.stride, coef, sums);
    }
}

/// Full-size maps computed on first use and cached. Not serialised; equality and `Debug`
/// ignore the cache (it follows from the fitted quantities), so models holding one can derive
/// both.
#[derive(Clone)]
pub(crate) struct MapCache<T>(OnceLock<Arc<T>>);

impl<T> Default for MapCache<T> {
    fn default() -> Self {
        Self(OnceLock::new())
    }
}

impl<T> MapCache<T> {
    /// The cached maps, computed by `init` on first use.
    pub fn get_or_init(&self, init: impl FnOnce() -> T) -> &T {
        self.0.get_or_init(|| Arc::new(init()))
    }

    /// Whether the maps have been computed.
    pub fn is_cached(&self) -> bool {
        self.0.get().is_some()
    }
}

impl<T> std::fmt::Debug for MapCache<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "MapCache {{ cached: {} }}", self.is_cached())
    }
}

impl<T> PartialEq for MapCache<T> {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}
