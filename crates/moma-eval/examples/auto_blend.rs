//! Negative experiment for `auto` (issue 12, item 1) on SIMULATED predictions: instead of
//! selecting one of [`AUTO_CANDIDATES`], blend their aligned maps, pixel by pixel, with weights
//! from the candidates' cross-validated errors on the 100 calibration samples (the same
//! spatially buffered leave-one-out `auto` uses). Rules: equal weights; weights ∝ 1 / CV mean
//! square; stacking (the simplex weights, on a grid of step 0.1, that minimise the CV mean square
//! of the blended leave-one-out predictions); the mean of the two lowest CV errors. Each blend is
//! averaged in disparity (`_disp`) and in depth (`_depth`). One JSON object per (set, simulator
//! seed, sampling seed) on stdout: the masked MAE (metres) of every candidate, of `auto`, and of
//! every blend; `benches/eval/auto_blend.py` summarises it.
//!
//! `MOMA_SHARED_DIR=../shared cargo run --release -p moma-eval --example auto_blend -- [SIM_SEEDS] [SEEDS] [EDGE_MARGIN_PX]`
use moma_core::PredictionKind;
use moma_core::align::Method;
use moma_core::align::local::{AUTO_CANDIDATES, loo_predictions};
use moma_core::image::MetricDepth;
use moma_core::metrics::DepthMetrics;
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
    fn rec(k: usize, left: usize, cur: &mut Vec<usize>, out: &mut Vec<Vec<usize>>) {
        if k == 1 {
            cur.push(left);
            out.push(cur.clone());
            cur.pop();
            return;
        }
        for i in 0..=left {
            cur.push(i);
            rec(k - 1, left - i, cur, out);
            cur.pop();
        }
    }
    let mut out = Vec::new();
    rec(k, steps, &mut Vec::new(), &mut out);
    out.into_iter()
        .map(|v| v.into_iter().map(|i| i as f64 / steps as f64).collect())
        .collect()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let sim_seeds: u64 = args.get(1).map_or(Ok(10), |s| s.parse())?;
    let seeds: u64 = args.get(2).map_or(Ok(10), |s| s.parse())?;
    let edge_margin_px: u32 = args.get(3).map_or(Ok(0), |s| s.parse())?;
    let shared = std::env::var("MOMA_SHARED_DIR").unwrap_or_else(|_| "../shared".into());
    let mut names: Vec<String> = AUTO_CANDIDATES.iter().map(|s| s.to_string()).collect();
    names.push("auto".into());
    let methods: Vec<Method> = names.iter().map(|n| n.parse()).collect::<Result<_, _>>()?;
    let grid = simplex(5, 10);
    for name in SETS {
        let set =
            moma_eval::data::load_set(&std::path::Path::new(&shared).join("data").join(name))?;
        for sim_seed in 0..sim_seeds {
            let preds = simulated_predictions(
                &set,
                SimulatorConfig::default(),
                sim_seed,
                PredictionKind::InverseDepth,
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
                // per method: per eval frame aligned map; cv preds
                let mut maps: Vec<Vec<MetricDepth>> = Vec::new();
                let mut maes = Vec::new();
                let mut loos: Vec<Vec<f64>> = Vec::new();
                let mut target_y = Vec::new();
                for m in &methods {
                    let m = prep.method(m);
                    let norm = prep.normalisation_for(&m, Normalisation::Minmax);
                    let map = prep.normalised(prep.calib, &norm)?;
                    let cal = prep.calibrate(&m, &norm, &map, 100, seed)?;
                    let mut ms = Vec::new();
                    let mut fm = Vec::new();
                    for &i in &eval_idx {
                        let frame = prep.normalised(i, &norm)?;
                        let (a, s) = prep.score(&cal, &frame, i)?;
                        ms.push(s);
                        fm.push(a);
                    }
                    maes.push(DepthMetrics::mean(&ms)?.mae);
                    if m.to_string() != "auto" {
                        let target = cal.samples.in_space(norm.space);
                        loos.push(loo_predictions(&target, &m.to_string())?);
                        target_y = target.samples.iter().map(|s| s.depth_m).collect();
                        maps.push(fm);
                    }
                }
                let k = loos.len();
                let cv_mse: Vec<f64> = loos
                    .iter()
                    .map(|l| {
                        l.iter()
                            .zip(&target_y)
                            .map(|(a, b)| (a - b).powi(2))
                            .sum::<f64>()
                            / l.len() as f64
                    })
                    .collect();
                // stacking weights on the simplex grid
                let mut best = (f64::INFINITY, vec![0.0; k]);
                for w in &grid {
                    let e: f64 = (0..target_y.len())
                        .map(|j| {
                            let p: f64 = (0..k).map(|c| w[c] * loos[c][j]).sum();
                            (p - target_y[j]).powi(2)
                        })
                        .sum();
                    if e < best.0 {
                        best = (e, w.clone());
                    }
                }
                let inv: Vec<f64> = cv_mse.iter().map(|e| 1.0 / e).collect();
                let s: f64 = inv.iter().sum();
                let w_inv: Vec<f64> = inv.iter().map(|x| x / s).collect();
                let w_eq = vec![1.0 / k as f64; k];
                let mut order: Vec<usize> = (0..k).collect();
                order.sort_by(|a, b| cv_mse[*a].total_cmp(&cv_mse[*b]));
                let mut w_top2 = vec![0.0; k];
                w_top2[order[0]] = 0.5;
                w_top2[order[1]] = 0.5;
                let rules: Vec<(&str, &Vec<f64>)> = vec![
                    ("equal", &w_eq),
                    ("inv_mse", &w_inv),
                    ("stack", &best.1),
                    ("top2", &w_top2),
                ];
                let mut out = serde_json::Map::new();
                for (rn, w) in rules {
                    for disp in [true, false] {
                        let mut ms = Vec::new();
                        for (fi, &i) in eval_idx.iter().enumerate() {
                            let shape = maps[0][fi].depth_m.dim();
                            let mut acc = ndarray::Array2::<f32>::zeros(shape);
                            for c in 0..k {
                                let wc = w[c] as f32;
                                if wc == 0.0 {
                                    continue;
                                }
                                acc.zip_mut_with(&maps[c][fi].depth_m, |a, &z| {
                                    *a += wc * if disp { 1.0 / z } else { z };
                                });
                            }
                            if disp {
                                acc.mapv_inplace(|d| {
                                    if d > 0.0 && d.is_finite() {
                                        1.0 / d
                                    } else {
                                        f32::NAN
                                    }
                                });
                            }
                            let md = MetricDepth::new(acc);
                            ms.push(DepthMetrics::compute(
                                &md,
                                &set.frames[i].gt,
                                Some(&prep.eval_masks[i]),
                            )?);
                        }
                        out.insert(
                            format!("{rn}_{}", if disp { "disp" } else { "depth" }),
                            DepthMetrics::mean(&ms)?.mae.into(),
                        );
                    }
                }
                println!(
                    "{}",
                    serde_json::json!({"set": name, "sim_seed": sim_seed, "seed": seed, "names": names, "maes": maes, "blends": out, "stack_w": best.1})
                );
            }
        }
    }
    Ok(())
}
