//! Evaluation of per-frame re-alignment on static anchors (docs/method.md §10;
//! [`moma_core::realign`]).
//!
//! Per seed, the calibration of [`crate::protocol`] gets the anchor store of the calibration
//! frame (its `rgb.png` and ground truth); every evaluated frame is aligned one-shot and then
//! re-aligned on the anchors found in its own `rgb.png`, and both results are scored in the same
//! region. Rows get `variant` `realign-anchors` (`realign-anchors-b0.80` for a brightness factor
//! other than 1) and [`RealignStats`]: how many frame × seed results were made worse, by how
//! much at most, how many corrections were accepted.
//!
//! **Brightness** (`--brightness 0.8,1.2`): the evaluated frames' RGB is scaled by β (rounded,
//! clipped to 255) before the anchor test; the calibration frame is unchanged. A depth model
//! also reacts to brightness; the evaluation models this (SIMULATED, documented here) as an
//! extra per-frame fluctuation of the simulator's component-4 form applied to the evaluated
//! frames' predictions: in inverse-depth form q (q = the prediction for `inverse-depth`, 1/p for
//! `depth`), q ← (1 + κ ln β)·q + κ ln β·min q, κ = [`RealignEval::brightness_response`]
//! (default 0.05, i.e. about −1.1 % / +0.9 % at β = 0.8 / 1.2); values ≤ 0 (no depth, the
//! model's ReLU region) stay as they are. For inverse-depth predictions under min-max
//! normalisation the affine change would be removed by the normalisation, but the zeros pinned at
//! 0 keep the minimum fixed, so it does change the one-shot result (the one-shot baseline of a
//! β ≠ 1 row differs from the β = 1 row; [`RealignStats::one_shot_mae_m`] records it).

use moma_core::Prediction;
use moma_core::align::Method;
use moma_core::metrics::DepthMetrics;
use moma_core::normalise::NormalisationConfig;
use moma_core::realign::{GreyHalf, RealignConfig};
use ndarray::{Array3, ArrayView3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{EvalError, Result};
use crate::protocol::{EvalResult, Prepared};
use crate::report::Table;
use moma_core::{AlignOptions, PredictionInput};

/// What the evaluation of re-alignment runs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RealignEval {
    /// The re-alignment settings (its seed is offset by the sampling seed).
    pub config: RealignConfig,
    /// Brightness factors of the evaluated frames' RGB, one block of rows each (default `[1]`).
    pub brightness: Vec<f64>,
    /// κ of the simulated brightness response of the prediction (module documentation).
    pub brightness_response: f64,
}

impl Default for RealignEval {
    fn default() -> Self {
        Self {
            config: RealignConfig::default(),
            brightness: vec![1.0],
            brightness_response: 0.05,
        }
    }
}

/// Per-row statistics of re-alignment against the one-shot result of the same calibration.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RealignStats {
    /// Brightness factor β of the evaluated frames.
    pub brightness: f64,
    /// Frame × seed results.
    pub results: usize,
    /// Results where the correction was accepted.
    pub accepted: usize,
    /// Results whose MAE rose (by more than 1 µm).
    pub worse: usize,
    /// `worse / results`.
    pub worse_fraction: f64,
    /// Results whose MAE rose by more than [`WORSE_BOUND_MM`] (the per-frame bound).
    #[serde(default)]
    pub worse_beyond_bound: usize,
    /// Largest MAE rise over all results, millimetres (0 when none rose).
    pub max_worse_mm: f64,
    /// Frames whose MAE, averaged over the seeds, rose by more than [`WORSE_BOUND_MM`].
    #[serde(default)]
    pub frames_beyond_bound: usize,
    /// Largest rise of a frame's MAE averaged over the seeds, millimetres (0 when none rose).
    #[serde(default)]
    pub max_frame_worse_mm: f64,
    /// Mean anchors found per frame.
    pub mean_anchors: f64,
    /// Per-image-mean MAE of the one-shot results these were compared with (metres, mean over
    /// seeds): with β ≠ 1 the evaluated predictions carry the brightness response.
    pub one_shot_mae_m: f64,
}

/// The per-frame rise of the MAE that re-alignment should never exceed, millimetres (docs/evaluation.md):
/// [`RealignStats::worse_beyond_bound`] counts the results beyond it.
pub const WORSE_BOUND_MM: f64 = 2.0;

/// Checks a brightness factor β against the simulated response of strength κ (module
/// documentation): β finite and > 0, κ finite and ≥ 0, and the response's scale 1 + κ·ln β at
/// least ½ (below β = e^(−1/κ), about 2e-9 at κ = 0.05, it turns the prediction upside down).
///
/// # Errors
/// [`EvalError::InvalidParameter`] naming β (or κ) and the bound.
pub fn check_brightness(beta: f64, kappa: f64) -> Result<()> {
    if !(beta.is_finite() && beta > 0.0) {
        return Err(EvalError::InvalidParameter(format!(
            "brightness factor {beta} must be finite and > 0"
        )));
    }
    if !(kappa.is_finite() && kappa >= 0.0) {
        return Err(EvalError::InvalidParameter(format!(
            "brightness response κ = {kappa} must be finite and ≥ 0"
        )));
    }
    if 1.0 + kappa * beta.ln() < 0.5 {
        return Err(EvalError::InvalidParameter(format!(
            "brightness factor {beta} is too dark for the simulated brightness response \
             (κ = {kappa}): it needs 1 + κ·ln β ≥ ½, i.e. β ≥ {:.3e}",
            (-0.5 / kappa).exp()
        )));
    }
    Ok(())
}

/// The variant name of a brightness factor.
pub fn variant_name(brightness: f64) -> String {
    if brightness == 1.0 {
        "realign-anchors".into()
    } else {
        format!("realign-anchors-b{brightness:.2}")
    }
}

/// RGB scaled by `beta`, rounded and clipped.
pub fn scale_brightness(rgb: ArrayView3<'_, u8>, beta: f64) -> Array3<u8> {
    let b = beta as f32;
    rgb.mapv(|x| (x as f32 * b).round().clamp(0.0, 255.0) as u8)
}

/// The simulated brightness response of a prediction (module documentation).
pub fn brightness_response(pred: &Prediction, beta: f64, kappa: f64) -> Prediction {
    if beta == 1.0 || kappa == 0.0 {
        return pred.clone();
    }
    let e = kappa * beta.ln();
    let disparity = pred.kind.is_disparity();
    let to_q = |p: f32| if disparity { p as f64 } else { 1.0 / p as f64 };
    let min_q = pred
        .values
        .iter()
        .map(|&p| to_q(p))
        .filter(|q| q.is_finite() && *q > 0.0)
        .fold(f64::INFINITY, f64::min);
    let min_q = if min_q.is_finite() { min_q } else { 0.0 };
    let values = pred.values.mapv(|p| {
        let q = to_q(p);
        if !(q.is_finite() && q > 0.0) {
            return p; // no depth (the model's ReLU region) stays as it is
        }
        let q = (1.0 + e) * q + e * min_q;
        if disparity {
            q as f32
        } else {
            (1.0 / q) as f32
        }
    });
    Prediction::new(values, pred.kind)
}

/// What re-aligning the frames of one set needs for one normalisation and brightness: the
/// normalised maps (the evaluated frames with the brightness response), the evaluated frames'
/// grey (from the scaled RGB) and the seed-independent anchor store of the calibration frame. Shared by the
/// depth evaluation ([`evaluate_realign`]) and the grasp evaluation.
pub struct RealignSetup {
    /// Normalised maps of every frame.
    pub maps: std::sync::Arc<Vec<moma_core::normalise::NormalisedMap>>,
    greys: Vec<Option<GreyHalf>>,
    store: moma_core::realign::AnchorStore,
    realign: RealignEval,
}

impl RealignSetup {
    /// Prepares re-alignment of `prep`'s frames with normalisation `norm` at brightness `beta`.
    ///
    /// # Errors
    /// A frame without RGB; no usable anchor store; normalisation errors.
    pub fn new(
        prep: &Prepared<'_>,
        norm: &NormalisationConfig,
        realign: &RealignEval,
        beta: f64,
    ) -> Result<Self> {
        let set = prep.set;
        let ctx = |i: usize| format!("set '{}', frame '{}'", set.name, set.frames[i].id);
        let plain = prep.normalised_all(norm)?;
        let maps = if beta == 1.0 {
            plain
        } else {
            prep.cached_maps(norm, beta, |i| {
                if i == prep.calib {
                    return Ok(plain[i].clone());
                }
                let p = brightness_response(&prep.preds.maps[i], beta, realign.brightness_response);
                moma_core::normalise::normalise(
                    &p,
                    norm,
                    prep.workspace.as_deref().map(moma_core::Workspace::mask),
                )
                .map_err(|e| EvalError::core(ctx(i), e))
            })?
        };
        let grey = |i: usize, rgb: ArrayView3<'_, u8>| {
            moma_io::grey_half(rgb).map_err(|e| EvalError::core(ctx(i), e))
        };
        // each frame's grey once (the anchor rule compares greys), not once per seed
        let greys: Vec<Option<GreyHalf>> = (0..set.frames.len())
            .map(|i| -> Result<_> {
                if i == prep.calib {
                    return Ok(None);
                }
                let rgb = scale_brightness(rgb_view(prep, i)?, beta);
                Ok(Some(grey(i, rgb.view())?))
            })
            .collect::<Result<_>>()?;
        let calib_grey = grey(prep.calib, rgb_view(prep, prep.calib)?)?;
        let calib_gt = &set.frames[prep.calib].gt;
        let store = moma_core::realign::AnchorStore::new(&calib_grey, calib_gt)
            .map_err(|e| EvalError::core(format!("{}: anchor store", ctx(prep.calib)), e))?;
        Ok(Self {
            maps,
            greys,
            store,
            realign: realign.clone(),
        })
    }

    /// The calibration of `method` for sampling seed `seed`, with the anchor store.
    ///
    /// # Errors
    /// As [`Prepared::calibrate`].
    pub fn calibrate(
        &self,
        prep: &Prepared<'_>,
        method: &Method,
        norm: &NormalisationConfig,
        n: usize,
        seed: u64,
    ) -> Result<moma_core::Calibration> {
        let ctx = format!(
            "set '{}', frame '{}': anchor store",
            prep.set.name, prep.set.frames[prep.calib].id
        );
        prep.calibrate(method, norm, &self.maps[prep.calib], n, seed)?
            .with_anchor_store(
                &self.store,
                PredictionInput::normalised(&self.maps[prep.calib], prep.kind()),
            )
            .map_err(|e| EvalError::core(ctx, e))
    }

    /// Frame `i` re-aligned on its anchors (the re-alignment seeded by the sampling seed
    /// `seed`): the re-aligned depth and the report. The one-shot result, where a caller wants
    /// it, is [`Prepared::score`]'s (the grasp evaluation and the demo do not).
    ///
    /// # Errors
    /// A frame without RGB; alignment errors, naming the frame.
    pub fn realign_frame(
        &self,
        prep: &Prepared<'_>,
        cal: &moma_core::Calibration,
        i: usize,
        seed: u64,
    ) -> Result<(moma_core::MetricDepth, moma_core::realign::RealignReport)> {
        let set = prep.set;
        let config = RealignConfig {
            seed: self.realign.config.seed.wrapping_add(seed),
            ..self.realign.config
        };
        let grey = self.greys[i]
            .as_ref()
            .ok_or_else(|| EvalError::frame(&set.name, &set.frames[i].id, "no RGB"))?;
        let aligned = cal
            .aligned(
                PredictionInput::normalised(&self.maps[i], prep.kind()),
                &AlignOptions::realigned(grey, &config),
            )
            .map_err(|e| {
                EvalError::core(
                    format!("set '{}', frame '{}'", set.name, set.frames[i].id),
                    e,
                )
            })?;
        let report = aligned.realign.ok_or_else(|| {
            EvalError::frame(&set.name, &set.frames[i].id, "re-alignment gave no report")
        })?;
        Ok((aligned.depth, report))
    }
}

fn rgb_view<'a>(prep: &'a Prepared<'_>, i: usize) -> Result<ArrayView3<'a, u8>> {
    let f = &prep.set.frames[i];
    let img = f.rgb.as_ref().ok_or_else(|| {
        EvalError::frame(
            &prep.set.name,
            &f.id,
            "re-alignment needs the frame's rgb.png, which was not loaded",
        )
    })?;
    ArrayView3::from_shape(
        (img.height() as usize, img.width() as usize, 3),
        img.as_raw(),
    )
    .map_err(|e| EvalError::frame(&prep.set.name, &f.id, format!("rgb.png: {e}")))
}

/// Evaluates re-alignment for one (method, normalisation) at brightness `beta`: every seed's
/// calibration with the calibration frame's anchor store, every other frame one-shot and
/// re-aligned.
///
/// # Errors
/// A frame without RGB, the errors of the protocol's steps, naming the frame.
pub fn evaluate_realign(
    prep: &Prepared<'_>,
    method: &Method,
    norm: &NormalisationConfig,
    n: usize,
    realign: &RealignEval,
    beta: f64,
) -> Result<EvalResult> {
    check_brightness(beta, realign.brightness_response)?;
    realign
        .config
        .validate()
        .map_err(|e| EvalError::core("re-alignment settings", e))?;
    let set = prep.set;
    let method = prep.method(method);
    let eval_idx = prep.eval_indices();
    let ctx = |i: usize| format!("set '{}', frame '{}'", set.name, set.frames[i].id);
    let setup = RealignSetup::new(prep, norm, realign, beta)?;
    let seeds: Vec<u64> = (0..prep.config.seeds as u64)
        .map(|s| prep.config.seed_base + s)
        .collect();
    type PerFrame = (
        DepthMetrics,
        DepthMetrics,
        moma_core::realign::RealignReport,
    );
    let per_seed: Vec<(moma_core::align::FitReport, Vec<PerFrame>)> = seeds
        .par_iter()
        .map(|&seed| -> Result<_> {
            let cal = setup.calibrate(prep, &method, norm, n, seed)?;
            let frames = eval_idx
                .iter()
                .map(|&i| -> Result<PerFrame> {
                    let (_, one) = prep.score(&cal, &setup.maps[i], i)?;
                    let (aligned, report) = setup.realign_frame(prep, &cal, i, seed)?;
                    let re = DepthMetrics::compute(
                        &aligned,
                        &set.frames[i].gt,
                        Some(&prep.eval_masks[i]),
                    )
                    .map_err(|e| EvalError::core(ctx(i), e))?;
                    Ok((one, re, report))
                })
                .collect::<Result<Vec<_>>>()?;
            Ok((cal.report, frames))
        })
        .collect::<Result<_>>()?;
    let agg = |pick: fn(&PerFrame) -> DepthMetrics,
               f: fn(&[DepthMetrics]) -> moma_core::Result<DepthMetrics>|
     -> Result<Vec<DepthMetrics>> {
        per_seed
            .iter()
            .map(|(_, fr)| {
                let ms: Vec<DepthMetrics> = fr.iter().map(pick).collect();
                f(&ms).map_err(|e| {
                    EvalError::core(format!("set '{}', aggregating metrics", set.name), e)
                })
            })
            .collect()
    };
    let one_mean = agg(|p| p.0, DepthMetrics::mean)?;
    let rises = Rises::of(
        &per_seed
            .iter()
            .map(|(_, fr)| fr.iter().map(|(one, re, _)| (one.mae, re.mae)).collect())
            .collect::<Vec<_>>(),
    );
    let reports = per_seed.iter().flat_map(|(_, fr)| fr.iter().map(|p| &p.2));
    let (accepted, anchors) = reports.fold((0usize, 0usize), |(a, n), r| {
        (a + usize::from(r.accepted), n + r.anchors)
    });
    let results = rises.results;
    let realigned: Vec<(moma_core::align::FitReport, Vec<DepthMetrics>)> = per_seed
        .iter()
        .map(|(r, fr)| (r.clone(), fr.iter().map(|p| p.1).collect()))
        .collect();
    let name = variant_name(beta);
    let mut row = crate::protocol::summarise(
        prep,
        &method,
        norm,
        n,
        crate::protocol::Variant {
            name: &name,
            calib: &[prep.calib],
            eval_idx: &eval_idx,
            robust: None,
        },
        &realigned,
    )?;
    row.realign = Some(RealignStats {
        brightness: beta,
        results,
        accepted,
        worse: rises.worse,
        worse_fraction: rises.worse as f64 / results.max(1) as f64,
        worse_beyond_bound: rises.beyond_bound,
        max_worse_mm: rises.max_m * 1e3,
        frames_beyond_bound: rises.frame_means_beyond_bound,
        max_frame_worse_mm: rises.max_frame_mean_m * 1e3,
        mean_anchors: anchors as f64 / results.max(1) as f64,
        one_shot_mae_m: one_mean.iter().map(|m| m.mae).sum::<f64>() / one_mean.len() as f64,
    });
    Ok(row)
}

/// How re-alignment raised the MAE, from `(one-shot, re-aligned)` MAEs in metres indexed
/// `[seed][frame]`: per result (frame × seed), and per frame averaged over the seeds (which draw
/// only the calibration samples).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Rises {
    /// Frame × seed results.
    results: usize,
    /// Results whose MAE rose by more than 1 µm.
    worse: usize,
    /// Results whose MAE rose by more than [`WORSE_BOUND_MM`].
    beyond_bound: usize,
    /// Largest rise of a result, metres (0 when none rose).
    max_m: f64,
    /// Frames whose rise averaged over the seeds exceeds [`WORSE_BOUND_MM`].
    frame_means_beyond_bound: usize,
    /// Largest rise of a frame averaged over the seeds, metres (0 when none rose).
    max_frame_mean_m: f64,
}

impl Rises {
    fn of(maes: &[Vec<(f64, f64)>]) -> Self {
        let bound_m = WORSE_BOUND_MM * 1e-3;
        let mut r = Self {
            results: 0,
            worse: 0,
            beyond_bound: 0,
            max_m: 0.0,
            frame_means_beyond_bound: 0,
            max_frame_mean_m: 0.0,
        };
        for &(one, re) in maes.iter().flatten() {
            let d = re - one;
            r.results += 1;
            if d > 1e-6 {
                r.worse += 1;
                r.beyond_bound += usize::from(d > bound_m);
                r.max_m = r.max_m.max(d);
            }
        }
        let frames = maes.first().map_or(0, Vec::len);
        for f in 0..frames {
            let d = maes.iter().map(|s| s[f].1 - s[f].0).sum::<f64>() / maes.len() as f64;
            r.frame_means_beyond_bound += usize::from(d > bound_m);
            r.max_frame_mean_m = r.max_frame_mean_m.max(d);
        }
        r
    }
}

/// The re-alignment table: per row with [`RealignStats`], the one-shot and re-aligned MAE (mm,
/// per-image mean, mean over seeds), their change, and the worse-frame statistics.
pub fn realign_table(results: &[EvalResult]) -> Table {
    let headers = [
        "set",
        "method",
        "variant",
        "one-shot MAE mm",
        "realigned MAE mm",
        "change %",
        "accepted",
        "frames worse",
        &format!("worse > {WORSE_BOUND_MM} mm"),
        "max worse mm",
        &format!("frame means > {WORSE_BOUND_MM} mm"),
        "anchors/frame",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let rows = results
        .iter()
        .filter_map(|r| r.realign.map(|s| (r, s)))
        .map(|(r, s)| {
            let (a, b) = (s.one_shot_mae_m * 1e3, r.per_image.mae.mean * 1e3);
            vec![
                r.set.clone(),
                r.method.to_uppercase(),
                r.variant.clone(),
                format!("{a:.2}"),
                format!("{b:.2}"),
                format!("{:+.1}", 100.0 * (b - a) / a),
                format!("{}/{}", s.accepted, s.results),
                format!(
                    "{}/{} ({:.1} %)",
                    s.worse,
                    s.results,
                    100.0 * s.worse_fraction
                ),
                s.worse_beyond_bound.to_string(),
                format!("{:.2}", s.max_worse_mm),
                format!(
                    "{} (max {:.2})",
                    s.frames_beyond_bound, s.max_frame_worse_mm
                ),
                format!("{:.0}", s.mean_anchors),
            ]
        })
        .collect();
    let sim = results.iter().any(|r| r.simulated);
    Table {
        title: format!(
            "{}per-frame re-alignment on static anchors vs one-shot (per-image mean MAE, mean over seeds)",
            if sim {
                "SIMULATED predictions — "
            } else {
                ""
            }
        ),
        headers,
        rows,
    }
}

#[cfg(test)]
mod rises_tests {
    use super::Rises;

    #[test]
    fn rises_count_results_and_frame_means_separately() {
        // two seeds × three frames, (one-shot, re-aligned) MAE in metres
        let maes = vec![
            vec![(0.010, 0.0135), (0.020, 0.015), (0.030, 0.030)],
            vec![(0.012, 0.0120), (0.020, 0.0235), (0.030, 0.0305)],
        ];
        let r = Rises::of(&maes);
        assert_eq!(r.results, 6);
        // rises: +3.5, −5, 0 | 0, +3.5, +0.5 mm
        assert_eq!(r.worse, 3);
        assert_eq!(r.beyond_bound, 2);
        assert!((r.max_m - 0.0035).abs() < 1e-12);
        // frame means: +1.75, −0.75, +0.25 mm: none beyond 2 mm
        assert_eq!(r.frame_means_beyond_bound, 0);
        assert!((r.max_frame_mean_m - 0.00175).abs() < 1e-12);
        // one seed alone: its frame means are its results
        let one = Rises::of(&maes[..1]);
        assert_eq!((one.beyond_bound, one.frame_means_beyond_bound), (1, 1));
        assert_eq!(Rises::of(&[]).results, 0);
    }
}
