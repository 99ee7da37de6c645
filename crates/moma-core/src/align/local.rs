//! Local correction on top of a global fit (`ssra-local`, `gssa-local`; METHOD.md §10) and
//! `auto`, the method chosen by leave-one-out cross-validation.
//!
//! The global model (SSRA or GSSA) gives `F(u, v, ẑ)` in the target space (metres in depth space,
//! 1/m in inverse space: the method works on whatever target the samples carry). At each node of a
//! coarse grid (LWLR's: every 32 px from 16 px) a scale/shift correction of `F` is fitted by
//! weighted least squares with Gaussian weights `w_k = exp(−d_k²/(2b²))` (`d_k` the pixel distance
//! node–sample, `b` the bandwidth in pixels) and a ridge pulling it towards the identity:
//!
//! `min_{δs,δt} Σ_k w_k (y_k − F_k − δs (F_k − c) − δt)² + λ (q δs² + δt²)`,
//!
//! with `c` the mean of `F_k` over the samples and `q` the mean of `(F_k − c)²` (so that both ridge
//! terms are in target units² per unit weight; `λ` is in units of weight, Σw ≤ n). The corrected
//! value is `s F + t` with `s = 1 + δs`, `t = δt − δs c`; `(s, t)` are stored at the grid nodes and
//! resized bilinearly to full size with LWLR's half-pixel-centre rule.
//!
//! `b` and `λ` are chosen by leave-one-out cross-validation over
//! [`LocalConfig::bandwidth_fractions`] (× image diagonal) × [`LocalConfig::ridges`]:
//! - the global part's LOO prediction is exact and closed-form (hat matrix of the linear least
//!   squares: `y_k − F₍₋ₖ₎(k) = r_k / (1 − h_kk)`);
//! - the local part drops sample `k`'s weight from the node sums of the (up to four) nodes around
//!   it, re-solves those 2×2 systems and interpolates, then corrects `F₍₋ₖ₎(k)`. The other samples
//!   keep their full-fit `F` (an approximation: the global model has 2–4 parameters fitted on all
//!   n samples). As `λ → ∞` the local LOO error tends to the global one exactly.
//!
//! Guard: when the best candidate's LOO RMS is not below the global fit's, the model falls back to
//! the global fit (`fallback: true`, no correction maps).
//!
//! `auto` computes the LOO RMS of gssa, ssra, lwlr, gssa-local and ssra-local on the calibration
//! samples (gssa, ssra: hat matrix; lwlr: exact refits without each sample; local variants: as
//! above) and keeps the method with the lowest (first in that order on ties).

use std::sync::{Arc, OnceLock};

use ndarray::{Array2, ArrayView2, ArrayViewMut2};
use serde::{Deserialize, Serialize};

use super::gssa::{self, GssaModel};
use super::lwlr::{self, half_pixel_source, resize_bilinear};
use super::ssra::{self, SsraConfig, SsraModel, solve_spd4};
use super::{AlignmentModel, Sample, SampleSet};
use crate::error::{CoreError, Result};
use crate::image::ImageSize;

/// Fewest samples `gssa-local` needs (GSSA's 2, plus 2 so that leave-one-out is defined).
pub const GSSA_LOCAL_MIN_SAMPLES: usize = gssa::MIN_SAMPLES + 2;
/// Fewest samples `ssra-local` needs (SSRA's 4, plus 2 so that leave-one-out is defined).
pub const SSRA_LOCAL_MIN_SAMPLES: usize = ssra::MIN_SAMPLES + 2;
/// Fewest samples `auto` needs (GSSA with leave-one-out).
pub const AUTO_MIN_SAMPLES: usize = gssa::MIN_SAMPLES + 1;

/// A leverage `h_kk` closer than this to 1 makes leave-one-out undefined.
const LEVERAGE_MAX: f64 = 1.0 - 1e-9;

/// Which global model the correction sits on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LocalBase {
    /// Global scale and shift.
    Gssa,
    /// Scale-shift-rotation.
    Ssra,
}

/// Settings of the local correction. `Default`: b ∈ {0.05, 0.1, 0.2, 0.4} × image diagonal,
/// λ ∈ {0.1, 1, 10, 100}, grid every 32 px from 16 px.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LocalConfig {
    /// Candidate bandwidths as fractions of the image diagonal (each > 0).
    pub bandwidth_fractions: Vec<f64>,
    /// Candidate ridges λ, units of weight (each > 0).
    pub ridges: Vec<f64>,
    /// Grid node spacing, pixels (≥ 1).
    pub grid_step_px: usize,
    /// Position of the first grid node, pixels.
    pub grid_offset_px: usize,
}

impl Default for LocalConfig {
    fn default() -> Self {
        Self {
            bandwidth_fractions: vec![0.05, 0.1, 0.2, 0.4],
            ridges: vec![0.1, 1.0, 10.0, 100.0],
            grid_step_px: 32,
            grid_offset_px: 16,
        }
    }
}

impl LocalConfig {
    fn validate(&self) -> Result<()> {
        if self.bandwidth_fractions.is_empty() || self.ridges.is_empty() {
            return Err(CoreError::InvalidParameter(
                "local correction needs at least one candidate bandwidth and one ridge".into(),
            ));
        }
        for &f in &self.bandwidth_fractions {
            if !(f.is_finite() && f > 0.0) {
                return Err(CoreError::InvalidParameter(format!(
                    "local correction bandwidth fraction must be finite and > 0, got {f}"
                )));
            }
        }
        for &l in &self.ridges {
            if !(l.is_finite() && l > 0.0) {
                return Err(CoreError::InvalidParameter(format!(
                    "local correction ridge must be finite and > 0, got {l}"
                )));
            }
        }
        if self.grid_step_px == 0 {
            return Err(CoreError::InvalidParameter(
                "local correction grid step must be ≥ 1 px".into(),
            ));
        }
        Ok(())
    }

    /// Grid node positions (columns, rows), pixels: `offset + step·i` below the image size (at
    /// least one node per axis).
    pub fn grid_nodes(&self, size: ImageSize) -> (Vec<f64>, Vec<f64>) {
        let step = self.grid_step_px.max(1);
        let off = self.grid_offset_px;
        let axis = |len: usize| -> Vec<f64> {
            let v: Vec<f64> = (off..len).step_by(step).map(|x| x as f64).collect();
            if v.is_empty() { vec![off as f64] } else { v }
        };
        (axis(size.width), axis(size.height))
    }
}

/// The global model under the correction.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "method", rename_all = "lowercase")]
pub enum GlobalFit {
    /// Global scale and shift.
    Gssa(GssaModel),
    /// Scale-shift-rotation.
    Ssra(SsraModel),
}

impl GlobalFit {
    /// The global model's value `F(u, v, ẑ)` (target units).
    #[inline]
    pub fn predict(&self, u: f64, v: f64, pred: f64) -> f64 {
        match self {
            Self::Gssa(m) => m.predict(pred),
            Self::Ssra(m) => m.predict(u, v, pred),
        }
    }

    /// `(g, T)` with `F = g(u, v)·ẑ + T`.
    #[inline]
    fn slope_offset(&self, u: f64, v: f64) -> (f64, f64) {
        match self {
            Self::Gssa(m) => (m.scale, m.shift_m),
            Self::Ssra(m) => (
                m.alpha_m_per_px * u + m.beta_m_per_px * v + m.gamma_m,
                m.t3_m,
            ),
        }
    }

    fn as_model(&self) -> AlignmentModel {
        match self {
            Self::Gssa(m) => AlignmentModel::Gssa(*m),
            Self::Ssra(m) => AlignmentModel::Ssra(*m),
        }
    }
}

/// One (bandwidth, ridge) candidate and its leave-one-out RMS.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocalCandidate {
    /// Bandwidth b, pixels.
    pub bandwidth_px: f64,
    /// Ridge λ, units of weight.
    pub ridge: f64,
    /// Leave-one-out RMS error on the calibration samples, target units (metres in depth space).
    pub loo_rms: f64,
}

/// Full-size folded maps: `z = scale ⊙ ẑ + shift`.
#[derive(Debug, Clone, PartialEq)]
struct LocalMaps {
    scale: Array2<f32>,
    shift: Array2<f32>,
}

/// Fitted local correction on a global model. Serialises the global fit, the candidates, the
/// chosen pair and the correction `(s, t)` at the grid nodes; full-size maps are computed on first
/// use and cached.
#[derive(Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocalModel {
    /// Settings.
    pub config: LocalConfig,
    /// Calibration image size.
    pub image_size: ImageSize,
    /// The global fit.
    pub global: GlobalFit,
    /// Leave-one-out RMS of the global fit alone, target units.
    pub global_loo_rms: f64,
    /// Every candidate in order (bandwidth-major), with its LOO RMS.
    pub candidates: Vec<LocalCandidate>,
    /// The best candidate (lowest LOO RMS, first on ties).
    pub chosen: LocalCandidate,
    /// `true` when the best candidate did not beat the global fit: the model is the global fit.
    pub fallback: bool,
    /// Grid nodes per row.
    pub nodes_x: usize,
    /// Grid nodes per column.
    pub nodes_y: usize,
    /// Correction scale s at the nodes, row-major `nodes_y × nodes_x` (empty on fallback).
    pub node_scale: Vec<f64>,
    /// Correction shift t at the nodes, target units, row-major (empty on fallback).
    pub node_shift: Vec<f64>,
    #[serde(skip)]
    maps: OnceLock<Arc<LocalMaps>>,
}

impl std::fmt::Debug for LocalModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LocalModel")
            .field("image_size", &self.image_size)
            .field("global", &self.global)
            .field("global_loo_rms", &self.global_loo_rms)
            .field("chosen", &self.chosen)
            .field("fallback", &self.fallback)
            .field("nodes", &(self.nodes_x, self.nodes_y))
            .finish()
    }
}

/// Equality of the fitted quantities (the cached maps follow from them).
impl PartialEq for LocalModel {
    fn eq(&self, o: &Self) -> bool {
        self.config == o.config
            && self.image_size == o.image_size
            && self.global == o.global
            && self.global_loo_rms == o.global_loo_rms
            && self.candidates == o.candidates
            && self.chosen == o.chosen
            && self.fallback == o.fallback
            && self.nodes_x == o.nodes_x
            && self.nodes_y == o.nodes_y
            && self.node_scale == o.node_scale
            && self.node_shift == o.node_shift
    }
}

/// Leave-one-out predictions `F₍₋ₖ₎(k)` of GSSA from the hat matrix.
fn gssa_loo(samples: &[Sample], m: &GssaModel) -> Result<Vec<f64>> {
    let n = samples.len() as f64;
    let mx = samples.iter().map(|s| s.pred).sum::<f64>() / n;
    let sxx: f64 = samples.iter().map(|s| (s.pred - mx).powi(2)).sum();
    samples
        .iter()
        .enumerate()
        .map(|(k, s)| {
            let h = 1.0 / n + (s.pred - mx).powi(2) / sxx;
            loo_value(k, s, m.predict(s.pred), h)
        })
        .collect()
}

/// Leave-one-out predictions of SSRA from the hat matrix of its (centred) features.
fn ssra_loo(samples: &[Sample], m: &SsraModel) -> Result<Vec<f64>> {
    let n = samples.len() as f64;
    let mu = samples.iter().map(|s| s.u).sum::<f64>() / n;
    let mv = samples.iter().map(|s| s.v).sum::<f64>() / n;
    let feat = |s: &Sample| [s.pred * (s.u - mu), s.pred * (s.v - mv), s.pred, 1.0];
    let mut a = [[0.0f64; 4]; 4];
    for s in samples {
        let x = feat(s);
        for i in 0..4 {
            for j in 0..4 {
                a[i][j] += x[i] * x[j];
            }
        }
    }
    samples
        .iter()
        .enumerate()
        .map(|(k, s)| {
            let x = feat(s);
            let y = solve_spd4(&a, &x).ok_or_else(|| {
                CoreError::Degenerate(
                    "SSRA normal matrix is singular; leave-one-out undefined".into(),
                )
            })?;
            let h: f64 = x.iter().zip(&y).map(|(p, q)| p * q).sum();
            loo_value(k, s, m.predict(s.u, s.v, s.pred), h)
        })
        .collect()
}

/// `F₍₋ₖ₎(k) = y − r/(1 − h)`.
fn loo_value(k: usize, s: &Sample, fitted: f64, h: f64) -> Result<f64> {
    if !(h.is_finite() && h < LEVERAGE_MAX) {
        return Err(CoreError::Degenerate(format!(
            "sample {k} alone determines the global fit (leverage {h:.6}); leave-one-out is undefined"
        )));
    }
    Ok(s.depth_m - (s.depth_m - fitted) / (1.0 - h))
}

fn rms(values: impl Iterator<Item = f64>) -> f64 {
    let (mut ss, mut n) = (0.0, 0usize);
    for v in values {
        ss += v * v;
        n += 1;
    }
    if n == 0 { 0.0 } else { (ss / n as f64).sqrt() }
}

/// Per-sample quantities of the correction.
struct Prep<'a> {
    samples: &'a [Sample],
    /// `F_k − c`.
    x: Vec<f64>,
    /// `y_k − F_k`.
    e: Vec<f64>,
    q: f64,
    cols: Vec<f64>,
    rows: Vec<f64>,
}

impl Prep<'_> {
    /// Node sums `[Σw, Σwx, Σwx², Σwe, Σwxe]` (row-major nodes) and the weight tables.
    fn node_sums(&self, b: f64) -> (Vec<[f64; 5]>, Vec<f64>, Vec<f64>) {
        let inv = 1.0 / (2.0 * b * b);
        let (nx, ny) = (self.cols.len(), self.rows.len());
        let mut wu = vec![0.0; self.samples.len() * nx];
        let mut wv = vec![0.0; self.samples.len() * ny];
        for (k, s) in self.samples.iter().enumerate() {
            for (j, &u) in self.cols.iter().enumerate() {
                wu[k * nx + j] = (-(u - s.u).powi(2) * inv).exp();
            }
            for (i, &v) in self.rows.iter().enumerate() {
                wv[k * ny + i] = (-(v - s.v).powi(2) * inv).exp();
            }
        }
        let mut sums = vec![[0.0f64; 5]; nx * ny];
        for k in 0..self.samples.len() {
            let (x, e) = (self.x[k], self.e[k]);
            let c = [1.0, x, x * x, e, x * e];
            for i in 0..ny {
                let a = wv[k * ny + i];
                if a < 1e-300 {
                    continue;
                }
                let row = &mut sums[i * nx..(i + 1) * nx];
                for (j, acc) in row.iter_mut().enumerate() {
                    let w = a * wu[k * nx + j];
                    for (t, ct) in acc.iter_mut().zip(&c) {
                        *t += w * ct;
                    }
                }
            }
        }
        (sums, wu, wv)
    }

    /// Solves one node's ridge system; returns `(δs, δt)`.
    #[inline]
    fn solve(&self, s: &[f64; 5], ridge: f64) -> (f64, f64) {
        let [w, wx, wxx, we, wxe] = *s;
        let (a, bb, d) = (wxx + ridge * self.q, wx, w + ridge);
        let det = a * d - bb * bb;
        if !(det.is_finite() && det > 0.0) {
            return (0.0, 0.0);
        }
        ((d * wxe - bb * we) / det, (a * we - bb * wxe) / det)
    }
}

/// Fits the global model and the cross-validated local correction.
///
/// # Errors
/// Too few samples (gssa-local < 4, ssra-local < 6); the global fit's errors
/// ([`CoreError::Degenerate`] ...); a sample with leverage 1; bad settings.
pub fn fit(samples: &SampleSet, base: LocalBase, config: &LocalConfig) -> Result<LocalModel> {
    config.validate()?;
    let size = samples.image_size;
    if size.pixels() == 0 {
        return Err(CoreError::InvalidParameter(format!(
            "local correction image size {size} is empty"
        )));
    }
    let s = &samples.samples;
    let (global, f_loo) = match base {
        LocalBase::Gssa => {
            let m = gssa::fit(s)?;
            (GlobalFit::Gssa(m), gssa_loo(s, &m)?)
        }
        LocalBase::Ssra => {
            let m = ssra::fit(samples, &SsraConfig::default())?;
            (GlobalFit::Ssra(m), ssra_loo(s, &m)?)
        }
    };
    let global_loo_rms = rms(s.iter().zip(&f_loo).map(|(p, f)| p.depth_m - f));
    let n = s.len() as f64;
    let f: Vec<f64> = s.iter().map(|p| global.predict(p.u, p.v, p.pred)).collect();
    let c = f.iter().sum::<f64>() / n;
    let x: Vec<f64> = f.iter().map(|v| v - c).collect();
    let q = (x.iter().map(|v| v * v).sum::<f64>() / n).max(f64::MIN_POSITIVE);
    let (cols, rows) = config.grid_nodes(size);
    let prep = Prep {
        samples: s,
        e: s.iter().zip(&f).map(|(p, fk)| p.depth_m - fk).collect(),
        x,
        q,
        cols,
        rows,
    };
    let (nx, ny) = (prep.cols.len(), prep.rows.len());
    let (w, h) = (size.width, size.height);
    let diag = ((w * w + h * h) as f64).sqrt();
    // bilinear neighbours of each sample's pixel
    let neighbours: Vec<[(usize, usize, f64); 2]> = s
        .iter()
        .map(|p| {
            let (u, v) = nearest_pixel(p.u, p.v, size);
            [half_pixel_source(u, nx, w), half_pixel_source(v, ny, h)]
        })
        .collect();

    let mut candidates = Vec::new();
    let mut best: Option<(usize, Vec<[f64; 5]>)> = None;
    for &frac in &config.bandwidth_fractions {
        let b = frac * diag;
        let (sums, wu, wv) = prep.node_sums(b);
        for &ridge in &config.ridges {
            let resid = s.iter().enumerate().map(|(k, p)| {
                let [(x0, x1, fx), (y0, y1, fy)] = neighbours[k];
                let (xk, ek) = (prep.x[k], prep.e[k]);
                let own = [1.0, xk, xk * xk, ek, xk * ek];
                let at = |i: usize, j: usize| {
                    let wk = wu[k * nx + j] * wv[k * ny + i];
                    let mut sm = sums[i * nx + j];
                    for (t, o) in sm.iter_mut().zip(&own) {
                        *t -= wk * o;
                    }
                    prep.solve(&sm, ridge)
                };
                let (a00, a01, a10, a11) = (at(y0, x0), at(y0, x1), at(y1, x0), at(y1, x1));
                let bil = |p00: f64, p01: f64, p10: f64, p11: f64| {
                    (p00 * (1.0 - fx) + p01 * fx) * (1.0 - fy) + (p10 * (1.0 - fx) + p11 * fx) * fy
                };
                let ds = bil(a00.0, a01.0, a10.0, a11.0);
                let dt = bil(a00.1, a01.1, a10.1, a11.1);
                let fl = f_loo[k];
                p.depth_m - (fl + ds * (fl - c) + dt)
            });
            let loo_rms = rms(resid);
            candidates.push(LocalCandidate {
                bandwidth_px: b,
                ridge,
                loo_rms,
            });
            let idx = candidates.len() - 1;
            let better = match &best {
                None => true,
                Some((bi, _)) => loo_rms < candidates[*bi].loo_rms,
            };
            if better {
                best = Some((idx, sums.clone()));
            }
        }
    }
    let (bi, best_sums) = best
        .ok_or_else(|| CoreError::InvalidParameter("local correction has no candidate".into()))?;
    let chosen = candidates[bi];
    if !chosen.loo_rms.is_finite() {
        return Err(CoreError::Degenerate(format!(
            "local correction leave-one-out error is {} on these {} samples",
            chosen.loo_rms,
            s.len()
        )));
    }
    let fallback = chosen.loo_rms >= global_loo_rms;
    let (mut node_scale, mut node_shift) = (Vec::new(), Vec::new());
    if !fallback {
        for sm in &best_sums {
            let (ds, dt) = prep.solve(sm, chosen.ridge);
            node_scale.push(1.0 + ds);
            node_shift.push(dt - ds * c);
        }
    }
    Ok(LocalModel {
        config: config.clone(),
        image_size: size,
        global,
        global_loo_rms,
        candidates,
        chosen,
        fallback,
        nodes_x: nx,
        nodes_y: ny,
        node_scale,
        node_shift,
        maps: OnceLock::new(),
    })
}

fn nearest_pixel(u: f64, v: f64, size: ImageSize) -> (f64, f64) {
    let cl = |x: f64, len: usize| (x.round().max(0.0)).min(len.saturating_sub(1) as f64);
    (cl(u, size.width), cl(v, size.height))
}

impl LocalModel {
    /// `ssra-local` or `gssa-local`.
    pub fn name(&self) -> &'static str {
        match self.global {
            GlobalFit::Gssa(_) => "gssa-local",
            GlobalFit::Ssra(_) => "ssra-local",
        }
    }

    /// The leave-one-out RMS of the model as used: the global one on fallback, else the chosen
    /// candidate's.
    pub fn loo_rms(&self) -> f64 {
        if self.fallback {
            self.global_loo_rms
        } else {
            self.chosen.loo_rms
        }
    }

    /// The fitted value at the pixel nearest to `(u, v)` (clamped) for ẑ = `pred`, in f64:
    /// `s·F + t` with `(s, t)` interpolated from the nodes as the full-size maps are (equal to
    /// [`LocalModel`]'s apply up to f32 rounding); the global value on fallback.
    pub fn predict_at(&self, u: f64, v: f64, pred: f64) -> f64 {
        let (u, v) = nearest_pixel(u, v, self.image_size);
        let fv = self.global.predict(u, v, pred);
        if self.fallback {
            return fv;
        }
        let (nx, ny) = (self.nodes_x, self.nodes_y);
        let (x0, x1, fx) = half_pixel_source(u, nx, self.image_size.width);
        let (y0, y1, fy) = half_pixel_source(v, ny, self.image_size.height);
        let bil = |m: &[f64]| {
            let top = m[y0 * nx + x0] * (1.0 - fx) + m[y0 * nx + x1] * fx;
            let bot = m[y1 * nx + x0] * (1.0 - fx) + m[y1 * nx + x1] * fx;
            top * (1.0 - fy) + bot * fy
        };
        bil(&self.node_scale) * fv + bil(&self.node_shift)
    }

    fn maps(&self) -> &LocalMaps {
        self.maps.get_or_init(|| {
            let (w, h) = (self.image_size.width, self.image_size.height);
            let s = resize_bilinear(&self.node_scale, self.nodes_x, self.nodes_y, w, h);
            let t = resize_bilinear(&self.node_shift, self.nodes_x, self.nodes_y, w, h);
            let mut scale = Array2::<f32>::zeros((h, w));
            let mut shift = Array2::<f32>::zeros((h, w));
            for ((v, u), o) in scale.indexed_iter_mut() {
                let (g, t0) = self.global.slope_offset(u as f64, v as f64);
                let sv = f64::from(s[[v, u]]);
                *o = (sv * g) as f32;
                shift[[v, u]] = (sv * t0 + f64::from(t[[v, u]])) as f32;
            }
            Arc::new(LocalMaps { scale, shift })
        })
    }

    /// `out = S ⊙ ẑ + T` (or the global fit on fallback); shapes checked by the caller.
    pub(crate) fn apply_into(
        &self,
        normalised: ArrayView2<'_, f32>,
        out: &mut ArrayViewMut2<'_, f32>,
    ) {
        if self.fallback {
            match &self.global {
                GlobalFit::Gssa(m) => {
                    let (s, t) = (m.scale as f32, m.shift_m as f32);
                    crate::kernels::map_rows(normalised, out, |_, zin, zout| {
                        crate::kernels::affine(zin, zout, s, t)
                    });
                }
                GlobalFit::Ssra(m) => m.apply_into(normalised, out),
            }
            return;
        }
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

    /// Checks a model read from a file: settings, finite global fit and LOO errors, bandwidth
    /// and ridge > 0, node counts matching the grid, node maps finite (empty on fallback).
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] naming the bad field.
    pub fn validate(&self) -> Result<()> {
        let bad = |msg: String| {
            Err(CoreError::InvalidParameter(format!(
                "{}: {msg}",
                self.name()
            )))
        };
        self.config.validate()?;
        if self.image_size.pixels() == 0 {
            return bad(format!("image size {} is empty", self.image_size));
        }
        if let GlobalFit::Ssra(m) = &self.global
            && m.image_size != self.image_size
        {
            return bad("global SSRA fit is for another image size".into());
        }
        self.global.as_model().validate()?;
        if !self.global_loo_rms.is_finite() {
            return bad(format!("global_loo_rms is {}", self.global_loo_rms));
        }
        for c in self.candidates.iter().chain([&self.chosen]) {
            if !(c.bandwidth_px.is_finite() && c.bandwidth_px > 0.0) {
                return bad(format!(
                    "bandwidth_px {} must be finite and > 0",
                    c.bandwidth_px
                ));
            }
            if !(c.ridge.is_finite() && c.ridge > 0.0) {
                return bad(format!("ridge {} must be finite and > 0", c.ridge));
            }
            if !c.loo_rms.is_finite() {
                return bad(format!("loo_rms {} is not finite", c.loo_rms));
            }
        }
        let (cols, rows) = self.config.grid_nodes(self.image_size);
        if (cols.len(), rows.len()) != (self.nodes_x, self.nodes_y) {
            return bad(format!(
                "{}×{} nodes stored but the grid has {}×{}",
                self.nodes_x,
                self.nodes_y,
                cols.len(),
                rows.len()
            ));
        }
        let want = if self.fallback {
            0
        } else {
            self.nodes_x * self.nodes_y
        };
        if self.node_scale.len() != want || self.node_shift.len() != want {
            return bad(format!(
                "node maps have {} and {} values, expected {want}",
                self.node_scale.len(),
                self.node_shift.len()
            ));
        }
        if let Some(x) = self
            .node_scale
            .iter()
            .chain(&self.node_shift)
            .find(|x| !x.is_finite())
        {
            return bad(format!("node map value {x} is not finite"));
        }
        Ok(())
    }
}

/// One method `auto` considered.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AutoCandidate {
    /// Method name.
    pub method: String,
    /// Leave-one-out RMS on the calibration samples (target units); `None` when the method could
    /// not be fitted on these samples.
    pub loo_rms: Option<f64>,
}

/// `auto`'s result: the chosen fitted model and every candidate's LOO RMS.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AutoModel {
    /// The chosen method fitted on all samples.
    pub chosen: Box<AlignmentModel>,
    /// Every candidate in the order tried (gssa, ssra, lwlr, gssa-local, ssra-local).
    pub candidates: Vec<AutoCandidate>,
}

impl AutoModel {
    /// Checks the chosen model (not itself `auto`) and the candidates' LOO values.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] naming the bad value.
    pub fn validate(&self) -> Result<()> {
        if matches!(*self.chosen, AlignmentModel::Auto(_) | AlignmentModel::Raw) {
            return Err(CoreError::InvalidParameter(format!(
                "auto: chosen model cannot be '{}'",
                self.chosen.name()
            )));
        }
        self.chosen.validate()?;
        for c in &self.candidates {
            if let Some(x) = c.loo_rms
                && !(x.is_finite() && x >= 0.0)
            {
                return Err(CoreError::InvalidParameter(format!(
                    "auto: candidate {} has leave-one-out RMS {x}",
                    c.method
                )));
            }
        }
        if !self
            .candidates
            .iter()
            .any(|c| c.method == self.chosen.name())
        {
            return Err(CoreError::InvalidParameter(format!(
                "auto: chosen method '{}' is not among the candidates",
                self.chosen.name()
            )));
        }
        Ok(())
    }
}

/// LOO RMS of LWLR by exact refits without each sample.
fn lwlr_loo(samples: &SampleSet, cfg: &lwlr::LwlrConfig) -> Result<f64> {
    let s = &samples.samples;
    let mut resid = Vec::with_capacity(s.len());
    let mut rest = SampleSet {
        image_size: samples.image_size,
        samples: Vec::with_capacity(s.len()),
    };
    for (k, p) in s.iter().enumerate() {
        rest.samples.clear();
        rest.samples.extend(
            s.iter()
                .enumerate()
                .filter(|(i, _)| *i != k)
                .map(|(_, q)| *q),
        );
        let m = lwlr::fit_unmapped(&rest, cfg)?;
        resid.push(p.depth_m - m.predict(p.u, p.v, p.pred));
    }
    Ok(rms(resid.into_iter()))
}

/// Fits `auto`: every candidate method, its LOO RMS, the lowest kept.
///
/// # Errors
/// [`CoreError::TooFewSamples`] below 3 samples; [`CoreError::Degenerate`] when no candidate
/// could be fitted (the first candidate's error is returned).
pub fn fit_auto(samples: &SampleSet) -> Result<AutoModel> {
    let s = &samples.samples;
    let mut candidates = Vec::new();
    let mut best: Option<(f64, AlignmentModel)> = None;
    let mut first_err = None;
    let mut consider = |name: &'static str, r: Result<(f64, AlignmentModel)>| match r {
        Ok((loo, model)) => {
            candidates.push(AutoCandidate {
                method: name.to_string(),
                loo_rms: Some(loo),
            });
            if best.as_ref().is_none_or(|(b, _)| loo < *b) {
                best = Some((loo, model));
            }
        }
        Err(e) => {
            candidates.push(AutoCandidate {
                method: name.to_string(),
                loo_rms: None,
            });
            first_err.get_or_insert(e);
        }
    };
    consider(
        "gssa",
        gssa::fit(s).and_then(|m| {
            let f = gssa_loo(s, &m)?;
            Ok((
                rms(s.iter().zip(&f).map(|(p, v)| p.depth_m - v)),
                AlignmentModel::Gssa(m),
            ))
        }),
    );
    consider(
        "ssra",
        if s.len() < ssra::MIN_SAMPLES + 1 {
            Err(too_few("ssra", s.len(), ssra::MIN_SAMPLES + 1))
        } else {
            ssra::fit(samples, &SsraConfig::default()).and_then(|m| {
                let f = ssra_loo(s, &m)?;
                Ok((
                    rms(s.iter().zip(&f).map(|(p, v)| p.depth_m - v)),
                    AlignmentModel::Ssra(m),
                ))
            })
        },
    );
    let lcfg = lwlr::LwlrConfig::faithful();
    consider(
        "lwlr",
        lwlr_loo(samples, &lcfg)
            .and_then(|loo| Ok((loo, AlignmentModel::Lwlr(lwlr::fit(samples, &lcfg)?)))),
    );
    for (name, base, need) in [
        ("gssa-local", LocalBase::Gssa, GSSA_LOCAL_MIN_SAMPLES),
        ("ssra-local", LocalBase::Ssra, SSRA_LOCAL_MIN_SAMPLES),
    ] {
        let r = if s.len() < need {
            Err(too_few(name, s.len(), need))
        } else {
            fit(samples, base, &LocalConfig::default())
                .map(|m| (m.loo_rms(), AlignmentModel::Local(Box::new(m))))
        };
        consider(name, r);
    }
    match best {
        Some((_, model)) => Ok(AutoModel {
            chosen: Box::new(model),
            candidates,
        }),
        None => Err(first_err.unwrap_or_else(|| {
            CoreError::Degenerate("auto: no candidate method could be fitted".into())
        })),
    }
}

fn too_few(method: &'static str, got: usize, need: usize) -> CoreError {
    CoreError::TooFewSamples { method, got, need }
}
