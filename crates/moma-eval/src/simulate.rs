//! The MDEM simulator of docs/method.md §6: turns ground-truth depth into a plausible, **simulated**
//! monocular-depth-model prediction, seeded and documented component by component.
//!
//! Components, applied in this order to the hole-filled ground truth (nearest valid pixel):
//! 1. **Viewpoint / intrinsics mismatch** (per set): the model "sees" the scene from a camera
//!    rotated by (θ, φ) about the x and y axes and believes perturbed intrinsics K̃
//!    (focal ×(1 ± `focal_error`), principal point ± `principal_point_error` × image size).
//!    A prediction ẑ at pixel (u, v) back-projects to ẑ·K̃⁻¹[u, v, 1] in the model's frame; rotated
//!    into the real camera its depth must be the true z, so ẑ = z / (r₃ · K̃⁻¹[u, v, 1]) with r₃
//!    the third row of R. Then z = ẑ(αu + βv + γ): a planar scale field, exactly SSRA's model.
//! 2. **Smooth non-planar distortion** (per set): z ← z·(1 + a·g(u, v)), g a sum of
//!    `bump_count` Gaussian bumps (σ 15–35 % of the width, random centres and signs) scaled so
//!    max |g| = 1; a = `bump_amplitude`.
//! 3. **Relief compression**: z ← B + (1 − c)(z − B), B a Gaussian blur of z
//!    (σ = `relief_sigma_px` × width/640), c = `relief_compression`.
//! 4. **Per-frame fluctuation** (seeded by the frame id), in inverse depth:
//!    1/z ← a_k/z + b_k, a_k = 1 + U(±f), b_k = U(±f)·min(1/z), f = `frame_fluctuation`.
//! 5. **Edge smoothing** (Gaussian, σ = `edge_sigma_px` × width/640) and spatially correlated
//!    multiplicative noise z ← z(1 + s·n), n white noise blurred with σ = `noise_corr_sigma_px`
//!    × width/640 and rescaled to unit standard deviation, s = `noise_std`.
//! 6. **Transparent objects** (only where a transparency mask is given): inside the mask
//!    z ← z + p(B − z), B the surface behind the object (nearest pixel outside the mask, smoothed),
//!    p = `transparency_pull` (the model "sees through" glass).
//!
//! Output kinds: `metric-depth` = g·z with a per-set global scale error
//! g = 1 + U(±`depth_scale_error`) (a metric head, nominally metres); `relative-disparity` =
//! max(0, K/z + b) with a per-set arbitrary scale K = exp(U(±`inverse_log_scale`)) and shift
//! b = β·mean(K/z), β = U(`disparity_shift_min`, `disparity_shift_max`) per set (a relative model's
//! disparity is affine-invariant: scale *and* shift unknown); `relative-depth` = K·z (a relative
//! depth model: the same arbitrary scale K, no unit).
//!
//! Every component is disabled by setting its strength to 0; with all strengths 0 the output is
//! the hole-filled ground truth (times g, or K/·). Randomness: per-set parts come from `seed`,
//! per-frame parts from a stable FNV-1a hash of (`seed`, frame id). Everything written by
//! [`simulate_set`] is labelled simulated (`predictions.json` beside the predictions).

use std::path::Path;

use moma_core::{Intrinsics, Mask, MetricDepth, Prediction, PredictionKind, is_valid_depth};
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::data::{LoadedSet, write_text};
use crate::error::{EvalError, Result};
use crate::imgproc::{fill_nearest, gaussian_blur};

/// Strengths of the simulator components (docs/method.md §6). Every field at 0 disables its part.
/// Pixel sizes are given for a 640-pixel-wide image and scaled with the image width.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimulatorConfig {
    /// 1. Largest rotation of the model's virtual camera about x and y, degrees (default 3).
    pub view_angle_deg: f64,
    /// 1. Largest relative focal-length error (default 0.10 = ±10 %).
    pub focal_error: f64,
    /// 1. Largest principal-point error as a fraction of the image size (default 0.05).
    pub principal_point_error: f64,
    /// 2. Amplitude a of the smooth bumps, relative (default 0.02).
    pub bump_amplitude: f64,
    /// 2. Number of Gaussian bumps (default 4).
    pub bump_count: usize,
    /// 3. Relief compression c: small structures shrunk by (1 − c) (default 0.2, i.e. ×0.8).
    pub relief_compression: f64,
    /// 3. Blur σ defining "small structures", pixels at 640 px width (default 30).
    pub relief_sigma_px: f64,
    /// 4. Per-frame fluctuation f of a_k, b_k in inverse depth (default 0.03).
    pub frame_fluctuation: f64,
    /// 5. Edge-smoothing Gaussian σ, pixels at 640 px width (default 1.5).
    pub edge_sigma_px: f64,
    /// 5. Relative standard deviation of the multiplicative noise (default 0.005).
    pub noise_std: f64,
    /// 5. Correlation length (blur σ) of the noise, pixels at 640 px width (default 4).
    pub noise_corr_sigma_px: f64,
    /// 6. Pull p of the depth inside the transparency mask towards the surface behind (default 0.5).
    pub transparency_pull: f64,
    /// Output `metric-depth`: largest global scale error (default 0.25 = ±25 %).
    pub depth_scale_error: f64,
    /// Outputs `relative-disparity` and `relative-depth`: K = exp(U(±this)) (default 1.0, K in
    /// [0.37, 2.7]).
    pub inverse_log_scale: f64,
    /// Output `relative-disparity`: the disparity shift b = β·mean(K/z) of a relative model,
    /// β drawn per set uniformly from [`Self::disparity_shift_min`, `Self::disparity_shift_max`]
    /// (defaults −0.55 and +0.3; −0.55 measured on a real relative output, docs/method.md §6);
    /// disparities ≤ 0 become 0, as the model's final ReLU does.
    pub disparity_shift_min: f64,
    /// Upper end of β (default 0.3).
    pub disparity_shift_max: f64,
}

impl Default for SimulatorConfig {
    fn default() -> Self {
        Self {
            view_angle_deg: 3.0,
            focal_error: 0.10,
            principal_point_error: 0.05,
            bump_amplitude: 0.02,
            bump_count: 4,
            relief_compression: 0.2,
            relief_sigma_px: 30.0,
            frame_fluctuation: 0.03,
            edge_sigma_px: 1.5,
            noise_std: 0.005,
            noise_corr_sigma_px: 4.0,
            transparency_pull: 0.5,
            depth_scale_error: 0.25,
            inverse_log_scale: 1.0,
            disparity_shift_min: -0.55,
            disparity_shift_max: 0.3,
        }
    }
}

impl SimulatorConfig {
    /// All components off (output = hole-filled ground truth, up to the kind conversion).
    pub fn identity() -> Self {
        Self {
            view_angle_deg: 0.0,
            focal_error: 0.0,
            principal_point_error: 0.0,
            bump_amplitude: 0.0,
            bump_count: 0,
            relief_compression: 0.0,
            relief_sigma_px: 30.0,
            frame_fluctuation: 0.0,
            edge_sigma_px: 0.0,
            noise_std: 0.0,
            noise_corr_sigma_px: 4.0,
            transparency_pull: 0.0,
            depth_scale_error: 0.0,
            inverse_log_scale: 0.0,
            disparity_shift_min: 0.0,
            disparity_shift_max: 0.0,
        }
    }

    /// Checks every strength is finite and non-negative.
    ///
    /// # Errors
    /// [`EvalError::InvalidParameter`] naming the field.
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("view_angle_deg", self.view_angle_deg),
            ("focal_error", self.focal_error),
            ("principal_point_error", self.principal_point_error),
            ("bump_amplitude", self.bump_amplitude),
            ("relief_compression", self.relief_compression),
            ("relief_sigma_px", self.relief_sigma_px),
            ("frame_fluctuation", self.frame_fluctuation),
            ("edge_sigma_px", self.edge_sigma_px),
            ("noise_std", self.noise_std),
            ("noise_corr_sigma_px", self.noise_corr_sigma_px),
            ("transparency_pull", self.transparency_pull),
            ("depth_scale_error", self.depth_scale_error),
            ("inverse_log_scale", self.inverse_log_scale),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(EvalError::InvalidParameter(format!(
                    "simulator {name} = {v} must be finite and >= 0"
                )));
            }
        }
        // Upper bounds: beyond them a component no longer describes a depth model (a focal
        // length through zero, a principal point off the image, a blur wider than the image),
        // and a typo in a --sim-config file would hang on a huge blur or write maps of inf or 0.
        for (name, v, max, why) in [
            ("view_angle_deg", self.view_angle_deg, 45.0, "degrees"),
            (
                "focal_error",
                self.focal_error,
                0.9,
                "a relative error: the focal length stays > 0",
            ),
            (
                "principal_point_error",
                self.principal_point_error,
                1.0,
                "a fraction of the image",
            ),
            ("bump_amplitude", self.bump_amplitude, 1.0, "relative"),
            ("bump_count", self.bump_count as f64, 1000.0, "bumps"),
            (
                "relief_sigma_px",
                self.relief_sigma_px,
                640.0,
                "px at 640 px width",
            ),
            (
                "edge_sigma_px",
                self.edge_sigma_px,
                640.0,
                "px at 640 px width",
            ),
            (
                "noise_corr_sigma_px",
                self.noise_corr_sigma_px,
                640.0,
                "px at 640 px width",
            ),
            ("noise_std", self.noise_std, 1.0, "relative"),
            (
                "inverse_log_scale",
                self.inverse_log_scale,
                10.0,
                "K up to e^10",
            ),
        ] {
            if v > max {
                return Err(EvalError::InvalidParameter(format!(
                    "simulator {name} = {v} is above its largest sensible value {max} ({why})"
                )));
            }
        }
        if self.relief_compression > 1.0 || self.transparency_pull > 1.0 {
            return Err(EvalError::InvalidParameter(
                "simulator relief_compression and transparency_pull must be <= 1".into(),
            ));
        }
        if !(self.disparity_shift_min.is_finite()
            && self.disparity_shift_max.is_finite()
            && self.disparity_shift_min <= self.disparity_shift_max
            && self.disparity_shift_min > -1.0)
        {
            return Err(EvalError::InvalidParameter(format!(
                "simulator disparity shift range [{}, {}] must be finite, ordered and above -1",
                self.disparity_shift_min, self.disparity_shift_max
            )));
        }
        if self.frame_fluctuation >= 1.0 || self.depth_scale_error >= 1.0 {
            return Err(EvalError::InvalidParameter(
                "simulator frame_fluctuation and depth_scale_error must be < 1".into(),
            ));
        }
        Ok(())
    }
}

/// One Gaussian bump of component 2 (pixels).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Bump {
    /// Centre column, pixels.
    pub u: f64,
    /// Centre row, pixels.
    pub v: f64,
    /// Standard deviation, pixels.
    pub sigma_px: f64,
    /// Signed weight.
    pub weight: f64,
}

/// The per-set random draws of the simulator (recorded in `predictions.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SetDraws {
    /// 1. Rotation about x, radians.
    pub theta_rad: f64,
    /// 1. Rotation about y, radians.
    pub phi_rad: f64,
    /// 1. The model's believed intrinsics K̃.
    pub model_intrinsics: Intrinsics,
    /// 1. The resulting planar field z = ẑ(αu + βv + γ): [α, β, γ].
    pub planar_field: [f64; 3],
    /// 2. Bumps.
    pub bumps: Vec<Bump>,
    /// 2. Normalisation making max |g| = 1.
    pub bump_norm: f64,
    /// Output `metric-depth`: global scale g.
    pub depth_scale: f64,
    /// Outputs `relative-disparity` and `relative-depth`: scale K.
    pub inverse_scale: f64,
    /// Output `relative-disparity`: shift fraction β (b = β·mean(K/z) per frame).
    pub disparity_shift: f64,
}

/// A seeded simulator for one fixed camera (one set).
#[derive(Debug, Clone)]
pub struct Simulator {
    /// Component strengths.
    pub config: SimulatorConfig,
    /// Set seed.
    pub seed: u64,
    /// Kind of the predictions produced.
    pub kind: PredictionKind,
    /// The true camera.
    pub intrinsics: Intrinsics,
    /// Per-set random draws.
    pub draws: SetDraws,
}

/// Stable 64-bit FNV-1a hash of a seed and a label (frame id); independent of Rust versions.
pub fn seed_for(seed: u64, label: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in seed.to_le_bytes().iter().chain(label.as_bytes()) {
        h ^= *b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

fn uniform_pm(rng: &mut ChaCha8Rng, a: f64) -> f64 {
    if a == 0.0 {
        // keep the stream aligned whether or not a component is enabled
        let _: f64 = rng.random();
        0.0
    } else {
        a * (2.0 * rng.random::<f64>() - 1.0)
    }
}

impl Simulator {
    /// Draws the per-set parameters from `seed`.
    ///
    /// # Errors
    /// Invalid config or intrinsics.
    pub fn new(
        config: SimulatorConfig,
        seed: u64,
        kind: PredictionKind,
        intrinsics: Intrinsics,
    ) -> Result<Self> {
        config.validate()?;
        intrinsics
            .validate()
            .map_err(|e| EvalError::core("simulator intrinsics", e))?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed_for(seed, "moma-sim/set"));
        let (w, h) = (intrinsics.width as f64, intrinsics.height as f64);
        let theta = uniform_pm(&mut rng, config.view_angle_deg).to_radians();
        let phi = uniform_pm(&mut rng, config.view_angle_deg).to_radians();
        let f_scale = 1.0 + uniform_pm(&mut rng, config.focal_error);
        let dcx = uniform_pm(&mut rng, config.principal_point_error) * w;
        let dcy = uniform_pm(&mut rng, config.principal_point_error) * h;
        let mk = Intrinsics {
            fx: intrinsics.fx * f_scale,
            fy: intrinsics.fy * f_scale,
            cx: intrinsics.cx + dcx,
            cy: intrinsics.cy + dcy,
            ..intrinsics
        };
        // R = Rx(θ)·Ry(φ); third row r3 = (−sin φ cos θ... ) computed explicitly.
        let (st, ct) = theta.sin_cos();
        let (sp, cp) = phi.sin_cos();
        // Rx = [[1,0,0],[0,ct,-st],[0,st,ct]], Ry = [[cp,0,sp],[0,1,0],[-sp,0,cp]]
        // third row of Rx·Ry = [st·0 + ct·(−sp), st, ct·cp] ... = [−ct·sp, st, ct·cp]
        let r3 = [-ct * sp, st, ct * cp];
        // r3 · K̃⁻¹[u,v,1] = r3x (u − c̃x)/f̃x + r3y (v − c̃y)/f̃y + r3z = αu + βv + γ
        let alpha = r3[0] / mk.fx;
        let beta = r3[1] / mk.fy;
        let gamma = r3[2] - alpha * mk.cx - beta * mk.cy;
        let mut bumps = Vec::with_capacity(config.bump_count);
        for _ in 0..config.bump_count {
            bumps.push(Bump {
                u: rng.random::<f64>() * w,
                v: rng.random::<f64>() * h,
                sigma_px: (0.15 + 0.2 * rng.random::<f64>()) * w,
                weight: (0.5 + 0.5 * rng.random::<f64>())
                    * if rng.random::<bool>() { 1.0 } else { -1.0 },
            });
        }
        let mut bump_norm = 0.0f64;
        if !bumps.is_empty() {
            for v in 0..intrinsics.height {
                for u in 0..intrinsics.width {
                    bump_norm = bump_norm.max(bump_value(&bumps, u as f64, v as f64).abs());
                }
            }
        }
        let depth_scale = 1.0 + uniform_pm(&mut rng, config.depth_scale_error);
        let inverse_scale = uniform_pm(&mut rng, config.inverse_log_scale).exp();
        // drawn last, so that the draws above are those of earlier versions
        let u: f64 = rng.random();
        let disparity_shift = config.disparity_shift_min
            + u * (config.disparity_shift_max - config.disparity_shift_min);
        Ok(Self {
            config,
            seed,
            kind,
            intrinsics,
            draws: SetDraws {
                theta_rad: theta,
                phi_rad: phi,
                model_intrinsics: mk,
                planar_field: [alpha, beta, gamma],
                bumps,
                bump_norm: if bump_norm > 0.0 { bump_norm } else { 1.0 },
                depth_scale,
                inverse_scale,
                disparity_shift,
            },
        })
    }

    fn px_scale(&self) -> f64 {
        self.intrinsics.width as f64 / 640.0
    }

    /// Simulates the prediction for one frame.
    ///
    /// `gt` in metres (invalid = 0/NaN), `transparency` the glass region (component 6), `frame_id`
    /// seeds the per-frame parts.
    ///
    /// # Errors
    /// Size mismatch with the camera, no valid ground-truth pixel, a transparency mask covering
    /// the whole image.
    pub fn predict(
        &self,
        gt: &MetricDepth,
        transparency: Option<&Mask>,
        frame_id: &str,
    ) -> Result<Prediction> {
        let size = self.intrinsics.size();
        size.expect_eq("ground truth", gt.size())
            .map_err(|e| EvalError::core(format!("simulating frame '{frame_id}'"), e))?;
        if let Some(m) = transparency {
            size.expect_eq("transparency mask", m.size())
                .map_err(|e| EvalError::core(format!("simulating frame '{frame_id}'"), e))?;
        }
        let no_valid = || {
            EvalError::InvalidParameter(format!(
                "simulating frame '{frame_id}': ground truth has no valid pixel"
            ))
        };
        let valid = gt.depth_m.mapv(is_valid_depth);
        let mut z = fill_nearest(&gt.depth_m, &valid).ok_or_else(no_valid)?;
        let c = &self.config;
        let s = self.px_scale();

        // 1. viewpoint / intrinsics mismatch: ẑ = z / (αu + βv + γ)
        let [a, b, g] = self.draws.planar_field;
        if c.view_angle_deg > 0.0 || c.focal_error > 0.0 || c.principal_point_error > 0.0 {
            z.indexed_iter_mut().for_each(|((v, u), x)| {
                *x = (*x as f64 / (a * u as f64 + b * v as f64 + g)) as f32;
            });
        }
        // 2. smooth non-planar distortion
        if c.bump_amplitude > 0.0 && !self.draws.bumps.is_empty() {
            let k = c.bump_amplitude / self.draws.bump_norm;
            z.indexed_iter_mut().for_each(|((v, u), x)| {
                let gv = bump_value(&self.draws.bumps, u as f64, v as f64);
                *x = (*x as f64 * (1.0 + k * gv)) as f32;
            });
        }
        // 3. relief compression
        if c.relief_compression > 0.0 {
            let blur = gaussian_blur(&z, c.relief_sigma_px * s);
            let keep = (1.0 - c.relief_compression) as f32;
            ndarray::Zip::from(&mut z)
                .and(&blur)
                .for_each(|x, &bl| *x = bl + keep * (*x - bl));
        }
        // 4. per-frame fluctuation in inverse depth
        let mut rng = ChaCha8Rng::seed_from_u64(seed_for(self.seed, frame_id));
        let ak = 1.0 + uniform_pm(&mut rng, c.frame_fluctuation);
        let bk_rel = uniform_pm(&mut rng, c.frame_fluctuation);
        if c.frame_fluctuation > 0.0 {
            let min_inv = z
                .iter()
                .filter(|x| x.is_finite() && **x > 0.0)
                .map(|&x| 1.0 / x as f64)
                .fold(f64::INFINITY, f64::min);
            let bk = bk_rel * min_inv;
            z.mapv_inplace(|x| (1.0 / (ak / x as f64 + bk)) as f32);
        }
        // 5. edge smoothing and correlated multiplicative noise
        if c.edge_sigma_px > 0.0 {
            z = gaussian_blur(&z, c.edge_sigma_px * s);
        }
        if c.noise_std > 0.0 {
            let white = Array2::from_shape_simple_fn(z.dim(), || {
                let x: f64 = StandardNormal.sample(&mut rng);
                x as f32
            });
            let n = gaussian_blur(&white, c.noise_corr_sigma_px * s);
            let len = n.len() as f64;
            let mean = n.iter().map(|&x| x as f64).sum::<f64>() / len;
            let sd = (n.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / len).sqrt();
            let k = if sd > 0.0 { c.noise_std / sd } else { 0.0 };
            ndarray::Zip::from(&mut z)
                .and(&n)
                .for_each(|x, &nv| *x = (*x as f64 * (1.0 + k * (nv as f64 - mean))) as f32);
        }
        // 6. transparent objects
        if let Some(mask) = transparency
            && c.transparency_pull > 0.0
            && mask.count() > 0
        {
            let outside = mask.data().mapv(|b| !b);
            let behind = fill_nearest(&z, &outside).ok_or_else(|| {
                EvalError::InvalidParameter(format!(
                    "simulating frame '{frame_id}': the transparency mask covers the whole image"
                ))
            })?;
            let behind = gaussian_blur(&behind, 5.0 * s);
            let p = c.transparency_pull as f32;
            ndarray::Zip::from(&mut z)
                .and(&behind)
                .and(mask.data())
                .for_each(|x, &bg, &m| {
                    if m {
                        *x += p * (bg - *x);
                    }
                });
        }
        let values = match self.kind {
            PredictionKind::MetricDepth => {
                let g = self.draws.depth_scale as f32;
                z.mapv(|x| g * x)
            }
            PredictionKind::RelativeDepth => {
                let k = self.draws.inverse_scale as f32;
                z.mapv(|x| k * x)
            }
            PredictionKind::RelativeDisparity => {
                let k = self.draws.inverse_scale;
                let (sum, n) = z
                    .iter()
                    .filter(|x| x.is_finite() && **x > 0.0)
                    .fold((0.0f64, 0usize), |(s, n), &x| (s + k / x as f64, n + 1));
                let b = if n > 0 {
                    self.draws.disparity_shift * sum / n as f64
                } else {
                    0.0
                };
                z.mapv(|x| ((k / x as f64) + b).max(0.0) as f32)
            }
        };
        Ok(Prediction::new(values, self.kind))
    }
}

fn bump_value(bumps: &[Bump], u: f64, v: f64) -> f64 {
    bumps
        .iter()
        .map(|b| {
            let d2 = (u - b.u).powi(2) + (v - b.v).powi(2);
            b.weight * (-d2 / (2.0 * b.sigma_px * b.sigma_px)).exp()
        })
        .sum()
}

/// Where component 6 takes its transparency mask from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum TransparencySource {
    /// The frame's `mask.png` when the set is a transparent set (its frames have `raw_depth.png`).
    #[default]
    Auto,
    /// Always the frame's `mask.png`.
    Mask,
    /// Never (component 6 off).
    None,
}

/// What `predictions.json` records beside simulated predictions: moma-io's common index head
/// (`format`, `prediction_kind`, `simulated: true`, `source`) and the simulator's settings.
#[derive(Debug, Clone, Serialize)]
pub struct SimulatedMeta {
    /// The index head every prediction folder has; `simulated` is always `true`.
    #[serde(flatten)]
    pub head: moma_io::PredictionIndexHead,
    /// Source set.
    pub set: String,
    /// Set seed.
    pub seed: u64,
    /// Whether component 6 used the frames' masks.
    pub transparency_from_mask: bool,
    /// Component strengths.
    pub config: SimulatorConfig,
    /// Per-set random draws.
    pub draws: SetDraws,
    /// Frames written.
    pub frames: Vec<String>,
}

/// Simulates every frame of `set` in memory; returns `(frame id, prediction)` in frame order.
///
/// # Errors
/// As [`Simulator::predict`], naming the frame.
pub fn simulate_frames(
    set: &LoadedSet,
    sim: &Simulator,
    transparency: TransparencySource,
) -> Result<Vec<Prediction>> {
    let use_mask = uses_mask(set, transparency);
    set.frames
        .iter()
        .map(|f| {
            let t = if use_mask { f.mask.as_ref() } else { None };
            sim.predict(&f.gt, t, &f.id)
                .map_err(|e| EvalError::frame(&set.name, &f.id, e.to_string()))
        })
        .collect()
}

/// Every frame of `set` simulated as `kind` with `config` and `seed`, labelled as
/// `moma eval --simulate` labels it: `SIMULATED <kind> (seed <seed>)`.
///
/// # Errors
/// As [`Simulator::new`] and [`simulate_frames`].
pub fn simulated_predictions(
    set: &LoadedSet,
    config: SimulatorConfig,
    seed: u64,
    kind: PredictionKind,
    transparency: TransparencySource,
) -> Result<crate::protocol::PredictionSet> {
    let sim = Simulator::new(config, seed, kind, set.intrinsics)?;
    Ok(crate::protocol::PredictionSet {
        label: format!("SIMULATED {kind} (seed {seed})"),
        simulated: true,
        maps: simulate_frames(set, &sim, transparency)?,
    })
}

fn uses_mask(set: &LoadedSet, transparency: TransparencySource) -> bool {
    match transparency {
        TransparencySource::Auto => set.frames.iter().any(|f| f.raw_depth.is_some()),
        TransparencySource::Mask => true,
        TransparencySource::None => false,
    }
}

/// Simulates every frame of `set` and writes `<out>/<frame-id>.npy` (float32 H×W) plus
/// `<out>/predictions.json` (kind, the "simulated" label, config, seed, draws).
///
/// # Errors
/// Simulation or I/O errors, naming the frame.
pub fn simulate_set(
    set: &LoadedSet,
    sim: &Simulator,
    transparency: TransparencySource,
    out: &Path,
) -> Result<(SimulatedMeta, Vec<Prediction>)> {
    std::fs::create_dir_all(out).map_err(|e| EvalError::io(out, e))?;
    let preds = simulate_frames(set, sim, transparency)?;
    for (f, p) in set.frames.iter().zip(&preds) {
        moma_io::write_npy_f32(out.join(format!("{}.npy", f.id)), p.values.view())
            .map_err(|source| EvalError::frame_io(&set.name, &f.id, source))?;
    }
    let meta = SimulatedMeta {
        head: moma_io::PredictionIndexHead::new(
            sim.kind,
            true,
            "SIMULATED MDEM prediction (moma-eval simulator, docs/method.md §6) — not a trained model",
        ),
        set: set.name.clone(),
        seed: sim.seed,
        transparency_from_mask: uses_mask(set, transparency),
        config: sim.config,
        draws: sim.draws.clone(),
        frames: set.frames.iter().map(|f| f.id.clone()).collect(),
    };
    let index = out.join(moma_io::PREDICTIONS_INDEX_FILE);
    let text = serde_json::to_string_pretty(&meta).map_err(|e| EvalError::Format {
        path: index.clone(),
        message: e.to_string(),
    })?;
    write_text(&index, &text)?;
    Ok((meta, preds))
}
