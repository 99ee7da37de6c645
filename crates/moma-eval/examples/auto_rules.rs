//! Data for choosing `auto`'s selection rule (issue 12, item 1) on SIMULATED predictions over
//! several simulator seeds: per simulator seed, set and sampling seed, each candidate's
//! cross-validated squared errors on the calibration samples (target units, as `auto` computes
//! them) and the masked MAE it reaches on the other frames. One JSON object per line on stdout;
//! `benches/eval/auto_rules.py` scores selection rules on it.
//!
//! `MOMA_SHARED_DIR=../shared cargo run --release -p moma-eval --example auto_rules -- [SIM_SEEDS] [SEEDS] [EDGE_MARGIN_PX]`
//! (the edge margin of the calibration samples, `moma eval --edge-margin-px`; default 0)

use moma_core::PredictionKind;
use moma_core::align::Method;
use moma_core::align::local::{AUTO_CANDIDATES, loo_predictions};
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

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let sim_seeds: u64 = args.get(1).map_or(Ok(10), |s| s.parse())?;
    let seeds: u64 = args.get(2).map_or(Ok(10), |s| s.parse())?;
    let edge_margin_px: u32 = args.get(3).map_or(Ok(0), |s| s.parse())?;
    let shared = std::env::var("MOMA_SHARED_DIR").unwrap_or_else(|_| "../shared".into());
    let methods: Vec<Method> = AUTO_CANDIDATES
        .iter()
        .map(|n| n.parse())
        .collect::<Result<_, _>>()?;
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
                let mut cands = Vec::new();
                for m in &methods {
                    let m = prep.method(m);
                    let norm = prep.normalisation_for(&m, Normalisation::Minmax);
                    let map = prep.normalised(prep.calib, &norm)?;
                    let cal = prep.calibrate(&m, &norm, &map, 100, seed)?;
                    let mut ms = Vec::new();
                    for &i in &eval_idx {
                        let frame = prep.normalised(i, &norm)?;
                        ms.push(prep.score(&cal, &frame, i)?.1);
                    }
                    let mae = DepthMetrics::mean(&ms)?.mae;
                    // the calibration frame itself, densely: inside its masks, and every valid pixel
                    let (aligned, at_calib) = prep.score(&cal, &map, prep.calib)?;
                    let whole = DepthMetrics::compute(&aligned, &set.frames[prep.calib].gt, None)?;
                    let target = cal.samples.in_space(norm.space);
                    let loo = loo_predictions(&target, &m.to_string())?;
                    let sq: Vec<f64> = target
                        .samples
                        .iter()
                        .zip(&loo)
                        .map(|(s, y)| (s.depth_m - y).powi(2))
                        .collect();
                    cands.push(serde_json::json!({"method": m.to_string(), "mae_m": mae, "cv_sq": sq, "calib_mask_mae_m": at_calib.mae, "calib_whole_mae_m": whole.mae}));
                }
                println!(
                    "{}",
                    serde_json::json!({"set": name, "sim_seed": sim_seed, "seed": seed, "candidates": cands})
                );
            }
        }
    }
    Ok(())
}
