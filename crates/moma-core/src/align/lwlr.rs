//! LWLR — locally weighted linear regression (Xu et al., BoostingDepth; docs/method.md §2).
//!
//! For a pixel `(u, v)` the local model is a weighted least-squares fit of `z` on `[x, 1]`,
//!
//! `min_{a,c} Σ_k w_k (z_k − (a x_k + c))² + λ c²`,  `w_k = exp(−d_k²/(2b²))`,
//!
//! with `d_k` the pixel distance from `(u, v)` to sample `k`, `b` the bandwidth (pixels), `λ` a ridge
//! on the shift only, and `x_k` the sample's normalised prediction — after a global scale-shift
//! pre-fit `x = s_g ẑ + t_g` when `global_prefit` is on (BoostingDepth's `lwlr.py`). The 2×2 normal
//! equations are `[[Σwx², Σwx], [Σwx, Σw + λ]] [a, c]ᵀ = [Σwxz, Σwz]ᵀ`. The aligned depth is
//! `a(u,v)·x + c(u,v)`, stored folded onto ẑ as maps `S = a·s_g`, `T = a·t_g + c` (metres), so that
//! `z = S ⊙ ẑ + T`.
//!
//! Two solves:
//! - [`LwlrSolve::Grid`] (default, faithful to BoostingDepth): local fits only at grid nodes
//!   `u = offset + step·i < W`, `v = offset + step·j < H` (32 px, offset 16), then `S` and `T` are
//!   resized bilinearly to full size with half-pixel centres (OpenCV `INTER_LINEAR` /
//!   `align_corners = false` semantics: source coordinate `(x + ½)·n_nodes/W − ½`, clamped), so
//!   a node's value lands at pixel `step·i + (step − 1)/2`, half a pixel from where it was solved,
//!   as in the reference. Defaults: `b = 50 px · W/640`, `λ = 1`, pre-fit on.
//! - [`LwlrSolve::Exact`]: the local fit at every pixel. [`LwlrConfig::bare_exact`] is the paper's
//!   bare formula (no pre-fit, `λ = 0`).
//!
//! Speed: the Gaussian weight is separable, `w = exp(−Δu²/2b²)·exp(−Δv²/2b²)`; per-sample column
//! and row tables are computed once, and the five sums of an image row are a small GEMM
//! (`5×n` coefficients times an `n×W` weight table) in cache-sized column blocks, rows in parallel
//! (rayon). Local systems that are singular (relative determinant below 1e-12, e.g. all weight on
//! one sample) fall back to the global fit at that pixel and are counted.
//!
//! Grid vs exact, measured (test `grid_vs_exact_difference`, printed by
//! `cargo test -p moma-core --release -- --nocapture grid_vs_exact`): on a synthetic 640×480
//! tabletop (plane at ~0.8–1.2 m, objects, a planar scale field and smooth bumps in the
//! prediction) with 100 random samples and the default settings (b = 50 px, λ = 1, pre-fit), the
//! aligned depths of the two solves differ by 0.15 mm on average and 1.7 mm at most (ridge and
//! pre-fit identical in both; the difference is the 32-px grid plus bilinear resize only); their
//! MAE against the ground truth is 2.80 mm (grid) vs 2.78 mm (exact).

use ndarray::{Array2, ArrayView2, ArrayViewMut2};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::grid::{self, MapCache, WeightTables, interpolate_nodes, resize_bilinear};
use super::gssa::{self, GssaModel};
use super::{Sample, SampleSet};
use crate::error::{CoreError, Result};
use crate::image::ImageSize;

/// Fewest samples LWLR needs (the global pre-fit needs 2).
pub const MIN_SAMPLES: usize = 2;

/// BoostingDepth's default bandwidth, pixels, at its reference width [`REFERENCE_WIDTH_PX`].
pub const REFERENCE_BANDWIDTH_PX: f64 = 50.0;
/// Image width (pixels) at which [`REFERENCE_BANDWIDTH_PX`] applies.
pub const REFERENCE_WIDTH_PX: f64 = 640.0;

/// A local system is singular when `det ≤ SINGULAR_REL · (Σw + λ) · Σwx²`.
const SINGULAR_REL: f64 = 1e-12;

/// Where the local fits are solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum LwlrSolve {
    /// BoostingDepth: on grid nodes, then bilinear resize of the maps.
    #[default]
    Grid,
    /// At every pixel.
    Exact,
}

/// LWLR settings. `Default` is BoostingDepth's implementation ([`LwlrConfig::faithful`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LwlrConfig {
    /// Grid (faithful) or exact per-pixel solve.
    pub solve: LwlrSolve,
    /// Gaussian bandwidth b, pixels; `None`: 50 px scaled by image width / 640.
    pub bandwidth_px: Option<f64>,
    /// Ridge λ added to the shift entry of each local 2×2 normal matrix (BoostingDepth: 1; 0 = none).
    /// In units of weight (Σw ≤ n); it pulls the local shift towards 0 (towards the pre-fit).
    pub ridge_shift: f64,
    /// Fit a global scale-shift first and run LWLR on the globally aligned prediction.
    pub global_prefit: bool,
    /// Grid node spacing, pixels (grid solve only).
    pub grid_step_px: usize,
    /// Position of the first grid node, pixels (grid solve only).
    pub grid_offset_px: usize,
}

impl Default for LwlrConfig {
    fn default() -> Self {
        Self::faithful()
    }
}

impl LwlrConfig {
    /// BoostingDepth's `lwlr.py`: grid every 32 px from 16, λ = 1 on the shift, global pre-fit,
    /// bandwidth 50 px at 640 px width.
    pub const fn faithful() -> Self {
        Self {
            solve: LwlrSolve::Grid,
            bandwidth_px: None,
            ridge_shift: 1.0,
            global_prefit: true,
            grid_step_px: 32,
            grid_offset_px: 16,
        }
    }

    /// As [`LwlrConfig::faithful`] but solved at every pixel (isolates the effect of the grid).
    pub const fn exact() -> Self {
        Self {
            solve: LwlrSolve::Exact,
            ..Self::faithful()
        }
    }

    /// The bare published formula at every pixel: no pre-fit, no ridge.
    pub const fn bare_exact() -> Self {
        Self {
            solve: LwlrSolve::Exact,
            ridge_shift: 0.0,
            global_prefit: false,
            ..Self::faithful()
        }
    }

    /// The bandwidth used for an image of `size`, pixels.
    pub fn bandwidth_for(&self, size: ImageSize) -> f64 {
        self.bandwidth_px
            .unwrap_or(REFERENCE_BANDWIDTH_PX * size.width as f64 / REFERENCE_WIDTH_PX)
    }

    fn validate(&self, size: ImageSize) -> Result<()> {
        let b = self.bandwidth_for(size);
        if !(b.is_finite() && b > 0.0) {
            return Err(CoreError::InvalidParameter(format!(
                "LWLR bandwidth must be a positive number of pixels, got {b}"
            )));
        }
        if !(self.ridge_shift.is_finite() && self.ridge_shift >= 0.0) {
            return Err(CoreError::InvalidParameter(format!(
                "LWLR ridge must be finite and ≥ 0, got {}",
                self.ridge_shift
            )));
        }
        if self.solve == LwlrSolve::Grid && self.grid_step_px == 0 {
            return Err(CoreError::InvalidParameter(
                "LWLR grid step must be ≥ 1 px".into(),
            ));
        }
        if !size.is_within_limits() {
            return Err(CoreError::InvalidParameter(format!(
                "LWLR image size {size} is empty or too large"
            )));
        }
        Ok(())
    }
}

/// Full-size LWLR maps: `z = scale ⊙ ẑ + shift`.
#[derive(Debug, Clone, PartialEq)]
pub struct LwlrMaps {
    /// Local scale S, target units per unit ẑ (metres in depth space, 1/m in inverse space),
    /// `(height, width)`.
    pub scale: Array2<f32>,
    /// Local shift T, target units, `(height, width)`.
    pub shift: Array2<f32>,
    /// Number of local fits (pixels or grid nodes) that were singular and fell back to the global fit.
    pub singular_fits: usize,
}

/// Fitted LWLR. Serialises compactly (config, samples, pre-fit); the full-size maps are
/// computed on first use ([`LwlrModel::maps`]) and cached.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LwlrModel {
    /// Settings.
    pub config: LwlrConfig,
    /// Calibration image size (maps are for this size).
    pub image_size: ImageSize,
    /// Bandwidth b actually used, pixels.
    pub bandwidth_px: f64,
    /// Global scale-shift fit of z on ẑ (the pre-fit when enabled, the singular-system fallback always).
    pub global: GssaModel,
    /// The calibration samples.
    pub samples: Vec<Sample>,
    #[serde(skip)]
    maps: MapCache<LwlrMaps>,
}

/// Fits LWLR: validates the settings, fits the global scale-shift, and computes the maps.
///
/// # Errors
/// Too few samples (< 2); constant ẑ ([`CoreError::Degenerate`]); bad settings.
pub fn fit(samples: &SampleSet, config: &LwlrConfig) -> Result<LwlrModel> {
    config.validate(samples.image_size)?;
    let global = gssa::fit(&samples.samples)?;
    let model = LwlrModel {
        config: *config,
        image_size: samples.image_size,
        bandwidth_px: config.bandwidth_for(samples.image_size),
        global,
        samples: samples.samples.clone(),
        maps: MapCache::default(),
    };
    model.maps();
    Ok(model)
}

/// Like [`fit`] without computing the full-size maps (for leave-one-out refits that only call
/// [`LwlrModel::predict`]).
pub(crate) fn fit_unmapped(samples: &SampleSet, config: &LwlrConfig) -> Result<LwlrModel> {
    config.validate(samples.image_size)?;
    let global = gssa::fit(&samples.samples)?;
    Ok(LwlrModel {
        config: *config,
        image_size: samples.image_size,
        bandwidth_px: config.bandwidth_for(samples.image_size),
        global,
        samples: samples.samples.clone(),
        maps: MapCache::default(),
    })
}

/// Precomputed per-sample quantities of a model.
struct Prepared {
    /// Sample positions (u, v), pixels.
    uv: Vec<(f64, f64)>,
    /// Centred regressor x' and target y' per sample.
    xy: Vec<(f64, f64)>,
    x_mean: f64,
    y_mean: f64,
    /// Pre-fit (scale, shift) mapping ẑ to x.
    pre: (f64, f64),
    /// Local (a, c) used when a local system is singular.
    fallback: (f64, f64),
    ridge: f64,
    inv_2b2: f64,
}

/// Output element types of the lattice solve.
trait FromF64: Copy + Send + Sync {
    fn from_f64(x: f64) -> Self;
}
impl FromF64 for f32 {
    fn from_f64(x: f64) -> Self {
        x as f32
    }
}
impl FromF64 for f64 {
    fn from_f64(x: f64) -> Self {
        x
    }
}

impl LwlrModel {
    /// The full-size `(scale, shift)` maps for [`LwlrModel::image_size`], computed once and cached.
    pub fn maps(&self) -> &LwlrMaps {
        self.maps.get_or_init(|| self.compute_maps())
    }

    /// Number of singular local fits that fell back to the global fit (computes the maps if needed).
    pub fn singular_fits(&self) -> usize {
        self.maps().singular_fits
    }

    /// Computes the maps without caching (grid or exact solve per the config; rows in parallel).
    pub fn compute_maps(&self) -> LwlrMaps {
        let p = self.prepare();
        let (w, h) = (self.image_size.width, self.image_size.height);
        match self.config.solve {
            LwlrSolve::Exact => {
                let cols: Vec<f64> = (0..w).map(|u| u as f64).collect();
                let rows: Vec<f64> = (0..h).map(|v| v as f64).collect();
                let mut scale = vec![0.0f32; w * h];
                let mut shift = vec![0.0f32; w * h];
                let singular = solve_lattice(&p, &cols, &rows, &mut scale, &mut shift);
                LwlrMaps {
                    scale: Array2::from_shape_vec((h, w), scale).unwrap_or_default(),
                    shift: Array2::from_shape_vec((h, w), shift).unwrap_or_default(),
                    singular_fits: singular,
                }
            }
            LwlrSolve::Grid => {
                let (cols, rows) = self.grid_nodes();
                let (nx, ny) = (cols.len(), rows.len());
                let mut scale = vec![0.0f64; nx * ny];
                let mut shift = vec![0.0f64; nx * ny];
                let singular = solve_lattice(&p, &cols, &rows, &mut scale, &mut shift);
                LwlrMaps {
                    scale: resize_bilinear(&scale, nx, ny, w, h),
                    shift: resize_bilinear(&shift, nx, ny, w, h),
                    singular_fits: singular,
                }
            }
        }
    }

    /// Grid node positions (columns, rows) in pixels: `offset + step·i` below the image size
    /// (at least one node per axis, at `offset`).
    pub fn grid_nodes(&self) -> (Vec<f64>, Vec<f64>) {
        grid::grid_nodes(
            self.config.grid_step_px,
            self.config.grid_offset_px,
            self.image_size,
        )
    }

    /// Metric depth (metres) the model gives at pixel `(u, v)` for ẑ = `pred`, in f64, without
    /// the full maps: the local solve at `(u, v)` (exact) or the bilinear interpolation of the
    /// grid-node solutions (grid).
    pub fn predict(&self, u: f64, v: f64, pred: f64) -> f64 {
        let p = self.prepare();
        let (scale, shift) = match self.config.solve {
            LwlrSolve::Exact => {
                let mut out_s = [0.0f64];
                let mut out_t = [0.0f64];
                solve_lattice(&p, &[u], &[v], &mut out_s, &mut out_t);
                (out_s[0], out_t[0])
            }
            LwlrSolve::Grid => {
                let (cols, rows) = self.grid_nodes();
                let (nx, ny) = (cols.len(), rows.len());
                let mut s = vec![0.0f64; nx * ny];
                let mut t = vec![0.0f64; nx * ny];
                solve_lattice(&p, &cols, &rows, &mut s, &mut t);
                (
                    interpolate_nodes(&s, nx, ny, self.image_size, u, v),
                    interpolate_nodes(&t, nx, ny, self.image_size, u, v),
                )
            }
        };
        scale * pred + shift
    }

    /// The local scales `S(u, v)` (fitted target per unit of ẑ, the slope of
    /// [`LwlrModel::predict`]) at `points` (pixels), without the full-size maps: the grid's nodes
    /// solved once and interpolated as the maps are (grid variant), or each point solved (exact).
    pub fn scales_at(&self, points: &[(f64, f64)]) -> Vec<f64> {
        let p = self.prepare();
        match self.config.solve {
            LwlrSolve::Exact => points
                .iter()
                .map(|&(u, v)| {
                    let (mut s, mut t) = ([0.0f64], [0.0f64]);
                    solve_lattice(&p, &[u], &[v], &mut s, &mut t);
                    s[0]
                })
                .collect(),
            LwlrSolve::Grid => {
                // only the nodes the points interpolate between: each node's local fit is its
                // own, so the sub-lattice's values are the full lattice's there
                let (cols, rows) = self.grid_nodes();
                let (w, h) = (self.image_size.width, self.image_size.height);
                let sources: Vec<_> = points
                    .iter()
                    .map(|&(u, v)| {
                        (
                            grid::half_pixel_source(u, cols.len(), w),
                            grid::half_pixel_source(v, rows.len(), h),
                        )
                    })
                    .collect();
                // the nodes used, in order, and each node's position among them (usize::MAX:
                // not solved)
                let pick = |n: usize, mut kept: Vec<usize>| {
                    kept.sort_unstable();
                    kept.dedup();
                    let mut at = vec![usize::MAX; n];
                    for (k, &i) in kept.iter().enumerate() {
                        at[i] = k;
                    }
                    (at, kept)
                };
                let (col_at, col_kept) = pick(
                    cols.len(),
                    sources.iter().flat_map(|(x, _)| [x.0, x.1]).collect(),
                );
                let (row_at, row_kept) = pick(
                    rows.len(),
                    sources.iter().flat_map(|(_, y)| [y.0, y.1]).collect(),
                );
                let sub_cols: Vec<f64> = col_kept.iter().map(|&i| cols[i]).collect();
                let sub_rows: Vec<f64> = row_kept.iter().map(|&i| rows[i]).collect();
                let nx = sub_cols.len();
                let mut s = vec![0.0f64; nx * sub_rows.len()];
                let mut t = vec![0.0f64; nx * sub_rows.len()];
                solve_lattice(&p, &sub_cols, &sub_rows, &mut s, &mut t);
                let node = |y: usize, x: usize| s[row_at[y] * nx + col_at[x]];
                sources
                    .iter()
                    .map(|&((x0, x1, fx), (y0, y1, fy))| {
                        let top = node(y0, x0) * (1.0 - fx) + node(y0, x1) * fx;
                        let bot = node(y1, x0) * (1.0 - fx) + node(y1, x1) * fx;
                        top * (1.0 - fy) + bot * fy
                    })
                    .collect()
            }
        }
    }

    /// RMS residual on the calibration samples, metres (via [`LwlrModel::maps`] at the nearest pixel).
    pub(crate) fn rms_residual_m(&self) -> f64 {
        if self.samples.is_empty() {
            return 0.0;
        }
        let ss: f64 = self
            .samples
            .iter()
            .map(|s| (self.predict_at_pixel(s.u, s.v, s.pred) - s.target).powi(2))
            .sum();
        (ss / self.samples.len() as f64).sqrt()
    }

    /// The fitted value at the pixel nearest to `(u, v)` (clamped to the image) from the cached
    /// full-size maps: `S[v, u]·ẑ + T[v, u]`, exactly what
    /// [`super::AlignmentModel::apply`] computes there (in f64).
    pub fn predict_at_pixel(&self, u: f64, v: f64, pred: f64) -> f64 {
        let m = self.maps();
        let (w, h) = (self.image_size.width, self.image_size.height);
        let u = (u.round().max(0.0) as usize).min(w.saturating_sub(1));
        let v = (v.round().max(0.0) as usize).min(h.saturating_sub(1));
        f64::from(m.scale[[v, u]]) * pred + f64::from(m.shift[[v, u]])
    }

    /// Checks a model read from a file: settings valid for its image size, the stored bandwidth
    /// equal to the one the settings give, a finite global fit, at least 2 valid samples.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] naming the bad field.
    pub fn validate(&self) -> Result<()> {
        self.config.validate(self.image_size)?;
        let b = self.config.bandwidth_for(self.image_size);
        if !(self.bandwidth_px.is_finite() && self.bandwidth_px > 0.0) || self.bandwidth_px != b {
            return Err(CoreError::InvalidParameter(format!(
                "LWLR bandwidth_px is {} but must be a positive number of pixels equal to the \
                 configured {b}",
                self.bandwidth_px
            )));
        }
        if !(self.global.scale.is_finite() && self.global.shift.is_finite()) {
            return Err(CoreError::InvalidParameter(format!(
                "LWLR global fit is not finite: scale {}, shift {}",
                self.global.scale, self.global.shift
            )));
        }
        let set = SampleSet {
            // the refit does not depend on what the targets are
            space: crate::normalise::AlignSpace::Depth,
            image_size: self.image_size,
            samples: self.samples.clone(),
        };
        set.validate()?;
        set.require("lwlr", MIN_SAMPLES)
    }

    /// `out = S ⊙ ẑ + T`; shapes checked by the caller.
    pub(crate) fn apply_into(
        &self,
        normalised: ArrayView2<'_, f32>,
        out: &mut ArrayViewMut2<'_, f32>,
    ) {
        let m = self.maps();
        let w = self.image_size.width;
        let (s_all, t_all) = match (m.scale.as_slice(), m.shift.as_slice()) {
            (Some(s), Some(t)) => (s, t),
            _ => return, // maps are built in standard layout
        };
        crate::kernels::map_rows(normalised, out, |v, zin, zout| {
            let (s, t) = (&s_all[v * w..(v + 1) * w], &t_all[v * w..(v + 1) * w]);
            crate::kernels::affine_maps(zin, zout, s, t);
        });
    }

    fn prepare(&self) -> Prepared {
        let pre = if self.config.global_prefit {
            (self.global.scale, self.global.shift)
        } else {
            (1.0, 0.0)
        };
        let fallback = if self.config.global_prefit {
            (1.0, 0.0)
        } else {
            (self.global.scale, self.global.shift)
        };
        let n = self.samples.len().max(1) as f64;
        let xs: Vec<f64> = self
            .samples
            .iter()
            .map(|s| pre.0 * s.pred + pre.1)
            .collect();
        let x_mean = xs.iter().sum::<f64>() / n;
        let y_mean = self.samples.iter().map(|s| s.target).sum::<f64>() / n;
        Prepared {
            uv: self.samples.iter().map(|s| (s.u, s.v)).collect(),
            xy: xs
                .iter()
                .zip(&self.samples)
                .map(|(x, s)| (x - x_mean, s.target - y_mean))
                .collect(),
            x_mean,
            y_mean,
            pre,
            fallback,
            ridge: self.config.ridge_shift,
            inv_2b2: 1.0 / (2.0 * self.bandwidth_px * self.bandwidth_px),
        }
    }
}

/// Below this many node × sample terms [`solve_lattice`] runs on the calling thread: measured
/// (`cargo bench -p moma-core --bench core -- height_pull_lwlr`, from a thread outside the pool)
/// the pool's dispatch cost 0.8 ms of the object pull's 1.2 ms on sub-lattices of a few nodes.
const SEQUENTIAL_LATTICE_WORK: usize = 1 << 14;

/// Solves the local fits on the lattice `cols × rows` (pixels) and writes the folded
/// `(S, T)` row-major into `out_scale`, `out_shift` (`rows.len() × cols.len()`). Returns the number
/// of singular local systems.
fn solve_lattice<T: FromF64>(
    p: &Prepared,
    cols: &[f64],
    rows: &[f64],
    out_scale: &mut [T],
    out_shift: &mut [T],
) -> usize {
    let n = p.uv.len();
    let nx = cols.len();
    let tables = WeightTables::new(p.uv.iter().copied(), cols, rows, p.inv_2b2);
    let stride = tables.stride;
    let singular = std::sync::atomic::AtomicUsize::new(0);
    let init = || {
        (
            vec![[0.0f64; 5]; n],
            std::array::from_fn::<Vec<f64>, 5, _>(|_| vec![0.0f64; stride]),
        )
    };
    let solve_row = |(coef, sums): &mut (Vec<[f64; 5]>, [Vec<f64>; 5]),
                     (i, (srow, trow)): (usize, (&mut [T], &mut [T]))| {
        let fill = |k: usize, w: f64| {
            let (x, y) = p.xy[k];
            [w, w * x, w * x * x, w * y, w * x * y]
        };
        tables.row_sums(i, fill, coef, sums);
        let mut bad = 0;
        for j in 0..nx {
            let (a, c) = match local_solve(
                p,
                [sums[0][j], sums[1][j], sums[2][j], sums[3][j], sums[4][j]],
            ) {
                Some(ac) => ac,
                None => {
                    bad += 1;
                    p.fallback
                }
            };
            srow[j] = T::from_f64(a * p.pre.0);
            trow[j] = T::from_f64(a * p.pre.1 + c);
        }
        if bad > 0 {
            singular.fetch_add(bad, std::sync::atomic::Ordering::Relaxed);
        }
    };
    if rows.len() * nx * n < SEQUENTIAL_LATTICE_WORK {
        // a few nodes (a sub-lattice of `scales_at`): handing them to the thread pool costs
        // more than solving them (a calling thread outside the pool waits on a wake-up)
        let mut state = init();
        out_scale
            .chunks_mut(nx)
            .zip(out_shift.chunks_mut(nx))
            .enumerate()
            .for_each(|row| solve_row(&mut state, row));
    } else {
        out_scale
            .par_chunks_mut(nx)
            .zip(out_shift.par_chunks_mut(nx))
            .enumerate()
            .for_each_init(init, solve_row);
    }
    singular.into_inner()
}

/// Local 2×2 ridge solve from the centred weighted sums `[Σw, Σwx', Σwx'², Σwy', Σwx'y']`;
/// returns `(a, c)` in uncentred terms (`z ≈ a x + c`), `None` when singular.
#[inline]
fn local_solve(p: &Prepared, s: [f64; 5]) -> Option<(f64, f64)> {
    let [s0, s1c, s2c, s3c, s4c] = s;
    let (xm, ym, lam) = (p.x_mean, p.y_mean, p.ridge);
    // translation-invariant parts
    let d = s0 * s2c - s1c * s1c;
    let num = s0 * s4c - s1c * s3c;
    // uncentred sums
    let s1 = s1c + xm * s0;
    let s2 = s2c + 2.0 * xm * s1c + xm * xm * s0;
    let s3 = s3c + ym * s0;
    let s4 = s4c + xm * s3c + ym * s1c + xm * ym * s0;
    let det = d + lam * s2;
    let diag = s0 + lam;
    if !det.is_finite() || det <= SINGULAR_REL * diag * s2 {
        return None;
    }
    let a = (num + lam * s4) / det;
    let c = (s3 - a * s1) / diag;
    (a.is_finite() && c.is_finite()).then_some((a, c))
}
