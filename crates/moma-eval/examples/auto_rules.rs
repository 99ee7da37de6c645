//! Data for choosing `auto`'s selection rule (docs/method.md §10) on SIMULATED predictions over
//! several simulator seeds: per simulator seed, set and sampling seed, each candidate's
//! cross-validated squared errors on the calibration samples (target units, as `auto` computes
//! them) and the masked MAE it reaches on the other frames; and, for blends instead of a choice,
//! the masked MAE of the candidates' aligned maps averaged pixel by pixel in the alignment space
//! (`blends`: equal weights; weights ∝ 1 / CV mean square; `stack`: the simplex weights, on a
//! grid of step 0.1, that minimise the CV mean square of the blended leave-one-out predictions;
//! `top2`: the two lowest CV errors, equally). One JSON object per line on stdout;
//! `benches/eval/auto_rules.py` scores selection rules and blends on it.
//!
//! `MOMA_SHARED_DIR=../shared cargo run --release -p moma-eval --example auto_rules -- [SIM_SEEDS] [SEEDS] [EDGE_MARGIN_PX]`
//! (the edge margin of the calibration samples, `moma eval --edge-margin-px`; default 0)

use moma_core::PredictionKind;
use moma_core::align::Method;
use moma_core::align::local::{auto_candidates, loo_predictions};
use moma_core::image::MetricDepth;
use moma_core::metrics::DepthMetrics;
use moma_core::normalise::AlignSpace;
use moma_core::normalise::Normalisation;
use moma_eval::protocol::{EvalConfig, Prepared};
use moma_eval::simulate::{SimulatorConfig, TransparencySource, simulated_predictions};

const SETS: [&str; 4] = [
    "gqcnn-primesense",
    "graspnet6dof-table",
    "m2t2-table",
    "cleargrasp-transparent",
];

/// Every weight vector of `k` entries in multiples of 1/`steps` that sums to 1.
fn simplex(k: usize, steps: usize) -> Vec<Vec<f64>> {
    /// Every way to write `n` as an ordered sum of `k` non-negative integers.
    fn compositions(k: usize, n: usize) -> Vec<Vec<usize>> {
        if k <= 1 {
            return vec![vec![n]];
        }
        (0..=n)
            .flat_map(|i| {
                compositions(k - 1, n - i).into_iter().map(move |mut rest| {
                    rest.insert(0, i);
                    rest
                })
            })
            .collect()
    }
    compositions(k, steps)
        .into_iter()
        .map(|c| c.into_iter().map(|i| i as f64 / steps as f64).collect())
        .collect()
}

/// Blends of the candidates: name and weights (see the module documentation).
fn blend_weights(
    loos: &[Vec<f64>],
    target: &[f64],
    grid: &[Vec<f64>],
) -> Vec<(&'static str, Vec<f64>)> {
    let k = loos.len();
    let cv_sq = |w: &[f64]| -> f64 {
        target
            .iter()
            .enumerate()
            .map(|(j, y)| ((0..k).map(|c| w[c] * loos[c][j]).sum::<f64>() - y).powi(2))
            .sum()
    };
    let mse: Vec<f64> = (0..k)
        .map(|c| {
            let mut w = vec![0.0; k];
            w[c] = 1.0;
            cv_sq(&w)
        })
        .collect();
    let inv_sum: f64 = mse.iter().map(|e| 1.0 / e).sum();
    let stack = grid
        .iter()
        .min_by(|a, b| cv_sq(a).total_cmp(&cv_sq(b)))
        .cloned()
        .unwrap_or_else(|| vec![1.0 / k as f64; k]);
    let mut order: Vec<usize> = (0..k).collect();
    order.sort_by(|a, b| mse[*a].total_cmp(&mse[*b]));
    let mut top2 = vec![0.0; k];
    for &c in order.iter().take(2) {
        top2[c] = 1.0 / k.min(2) as f64;
    }
    vec![
        ("equal", vec![1.0 / k as f64; k]),
        (
            "inverse_cv_mse",
            mse.iter().map(|e| 1.0 / e / inv_sum).collect(),
        ),
        ("stack", stack),
        ("top2", top2),
    ]
}

/// `maps` blended with `w` in `space` (disparity averaged in inverse space, through
/// [`AlignSpace`]'s own conversions); NaN where any is.
fn blend(maps: &[&MetricDepth], w: &[f64], space: AlignSpace) -> MetricDepth {
    let mut acc = ndarray::Array2::<f64>::zeros(maps[0].depth_m.dim());
    for (m, &wc) in maps.iter().zip(w) {
        acc.zip_mut_with(&m.depth_m, |a, &z| {
            *a += wc * space.target_from_depth(f64::from(z));
        });
    }
    MetricDepth::new(acc.mapv(|t| space.depth_from_target(t) as f32))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let sim_seeds: u64 = args.get(1).map_or(Ok(10), |s| s.parse())?;
    let seeds: u64 = args.get(2).map_or(Ok(10), |s| s.parse())?;
    let edge_margin_px: u32 = args.get(3).map_or(Ok(0), |s| s.parse())?;
    let shared = std::env::var("MOMA_SHARED_DIR").unwrap_or_else(|_| "../shared".into());
    let methods: Vec<Method> = auto_candidates().to_vec();
    let grid = simplex(methods.len(), 10);
    for name in SETS {
        let set =
            moma_eval::data::load_set(&std::path::Path::new(&shared).join("data").join(name))?;
        for sim_seed in 0..sim_seeds {
            let preds = simulated_predictions(
                &set,
                SimulatorConfig::default(),
                sim_seed,
                PredictionKind::RelativeDisparity,
                TransparencySource::Auto,
            )?;
            let config = EvalConfig {
                methods: methods.clone(),
                edge_margin_px,
                ..EvalConfig::default()
            };
            let prep = Prepared::new(&set, &preds, &config)?;
            let eval_idx = prep.eval_indices();
            for seed in 0..seeds {
                let mut cands = Vec::new();
                let (mut aligned_maps, mut loos) = (Vec::new(), Vec::new());
                let (mut target_y, mut space) = (Vec::new(), AlignSpace::Inverse);
                for m in &methods {
                    let m = prep.method(m);
                    let norm = prep.normalisation_for(&m, Normalisation::Minmax);
                    let map = prep.normalised(prep.calib, &norm)?;
                    let cal = prep.calibrate(&m, &norm, &map, 100, seed)?;
                    let mut ms = Vec::new();
                    let mut frames = Vec::new();
                    for &i in &eval_idx {
                        let frame = prep.normalised(i, &norm)?;
                        let (aligned, metrics) = prep.score(&cal, &frame, i)?;
                        ms.push(metrics);
                        frames.push(aligned);
                    }
                    aligned_maps.push(frames);
                    let mae = DepthMetrics::mean(&ms)?.mae;
                    // the calibration frame itself, densely: inside its masks, and every valid pixel
                    let (aligned, at_calib) = prep.score(&cal, &map, prep.calib)?;
                    let whole = DepthMetrics::compute(&aligned, &set.frames[prep.calib].gt, None)?;
                    let target = cal.samples.in_space(norm.space);
                    let loo = loo_predictions(&target, &m)?;
                    let sq: Vec<f64> = target
                        .samples
                        .iter()
                        .zip(&loo)
                        .map(|(s, y)| (s.target - y).powi(2))
                        .collect();
                    target_y = target.samples.iter().map(|s| s.target).collect();
                    space = norm.space;
                    loos.push(loo);
                    cands.push(serde_json::json!({"method": m.to_string(), "mae_m": mae, "cv_sq": sq, "calib_mask_mae_m": at_calib.mae, "calib_whole_mae_m": whole.mae}));
                }
                let mut blends = serde_json::Map::new();
                for (rule, w) in blend_weights(&loos, &target_y, &grid) {
                    let mut ms = Vec::new();
                    for (f, &i) in eval_idx.iter().enumerate() {
                        let maps: Vec<&MetricDepth> = aligned_maps.iter().map(|m| &m[f]).collect();
                        let b = blend(&maps, &w, space);
                        ms.push(DepthMetrics::compute(
                            &b,
                            &set.frames[i].gt,
                            Some(&prep.eval_masks[i]),
                        )?);
                    }
                    blends.insert(
                        rule.into(),
                        serde_json::json!({"weights": w, "mae_m": DepthMetrics::mean(&ms)?.mae}),
                    );
                }
                println!(
                    "{}",
                    serde_json::json!({"set": name, "sim_seed": sim_seed, "seed": seed, "candidates": cands, "blends": blends})
                );
            }
        }
    }
    Ok(())
}
