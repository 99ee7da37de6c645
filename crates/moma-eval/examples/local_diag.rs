//! Diagnostics of the local correction and `auto` (docs/method.md §10) on simulated predictions:
//! per set and seed, each candidate's leave-one-out RMS on the calibration samples against the
//! MAE it reaches inside the masks of the other frames (what the evaluation scores), and what
//! `ssra-local`, `gssa-local` and `auto` chose.
//!
//! `cargo run --release -p moma-eval --example local_diag -- DATA_DIR PRED_DIR [SEEDS]`
//! with `PRED_DIR/<set>` written by `moma simulate` (results are SIMULATED).

use std::path::PathBuf;

use moma_core::align::local::{auto_candidates, loo_predictions, one_standard_error_choice};
use moma_core::align::{AlignmentModel, Method};
use moma_core::metrics::DepthMetrics;
use moma_core::normalise::Normalisation;
use moma_eval::data::load_set;
use moma_eval::protocol::{EvalConfig, PredictionSet, Prepared};

const SETS: [&str; 4] = [
    "gqcnn-primesense",
    "graspnet6dof-table",
    "m2t2-table",
    "cleargrasp-transparent",
];

fn label_idx(l: &str) -> usize {
    match l {
        "t" => 0,
        "m2" => 1,
        _ => 2,
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let data = PathBuf::from(args.get(1).map_or("/work/shared/data", String::as_str));
    let preds_dir = PathBuf::from(args.get(2).map_or("/tmp/local2/preds", String::as_str));
    let seeds: u64 = args.get(3).map_or(Ok(10), |s| s.parse())?;
    let verbose = std::env::var_os("DIAG_VERBOSE").is_some();
    let names = ["gssa", "ssra", "lwlr", "gssa-local", "ssra-local", "auto"];
    let methods: Vec<Method> = names.iter().map(|n| n.parse()).collect::<Result<_, _>>()?;
    println!("SIMULATED predictions; MAE mm inside the masks of the non-calibration frames");
    for set_name in SETS {
        let set = load_set(&data.join(set_name))?;
        let preds = PredictionSet::read(&set, &preds_dir.join(set_name), None)?;
        let config = EvalConfig {
            methods: methods.clone(),
            ..EvalConfig::default()
        };
        let prep = Prepared::new(&set, &preds, &config)?;
        let eval_idx = prep.eval_indices();
        let mut mae_sum = vec![0.0; names.len()];
        let mut whole_sum = vec![0.0; names.len()];
        let mut picks: Vec<String> = Vec::new();
        let mut alt_sum = [0.0; 3];
        let mut bias_acc = vec![(0.0, 0.0, 0.0); names.len()];
        println!("\n== {set_name} ({} eval frames)", eval_idx.len());
        for seed in 0..seeds {
            let mut line = format!("seed {seed:2}:");
            let mut last_mae = vec![0.0; names.len()];
            for (mi, m) in methods.iter().enumerate() {
                let m = prep.method(m);
                let norm = prep.normalisation_for(&m, Normalisation::Minmax);
                let maps: Vec<_> = (0..set.frames.len())
                    .map(|i| prep.normalised(i, &norm))
                    .collect::<Result<_, _>>()?;
                let cal = prep.calibrate(&m, &norm, &maps[prep.calib], 100, seed)?;
                let mut ms = Vec::new();
                let mut whole = Vec::new();
                for &i in &eval_idx {
                    let (aligned, metrics) = prep.score(&cal, &maps[i], i)?;
                    ms.push(metrics);
                    whole.push(DepthMetrics::compute(&aligned, &set.frames[i].gt, None)?);
                    if std::env::var_os("DIAG_BIAS").is_some() {
                        let mask = &prep.eval_masks[i];
                        let (mut sb, mut nb, mut so, mut no) = (0.0, 0usize, 0.0, 0usize);
                        for ((p, g), inside) in aligned
                            .depth_m
                            .iter()
                            .zip(set.frames[i].gt.depth_m.iter())
                            .zip(mask.data().iter())
                        {
                            if !(p.is_finite() && *g > 0.0 && g.is_finite()) {
                                continue;
                            }
                            if *inside {
                                sb += f64::from(p - g);
                                nb += 1;
                            } else {
                                so += f64::from(p - g);
                                no += 1;
                            }
                        }
                        bias_acc[mi].0 += sb / nb.max(1) as f64 * 1e3;
                        bias_acc[mi].1 += so / no.max(1) as f64 * 1e3;
                        bias_acc[mi].2 += 1.0;
                    }
                }
                let mae = DepthMetrics::mean(&ms)?.mae * 1e3;
                let wmae = DepthMetrics::mean(&whole)?.mae * 1e3;
                mae_sum[mi] += mae;
                last_mae[mi] = mae;
                whole_sum[mi] += wmae;
                line += &format!(" {}={mae:.2}/{wmae:.2}", names[mi]);
                match &cal.model {
                    AlignmentModel::Local(l) if verbose => {
                        line += &format!(
                            "[gl {:.4} ch {:.4} b{:.0} l{} fb{}]",
                            l.global_loo_rms_target,
                            l.chosen.loo_rms_target,
                            l.chosen.bandwidth_px,
                            l.chosen.ridge,
                            u8::from(l.fallback)
                        );
                    }
                    AlignmentModel::Auto(a) => {
                        picks.push(a.chosen.name().to_string());
                        line += &format!("[{}", a.chosen.name());
                        if verbose {
                            for c in &a.candidates {
                                line += &format!(
                                    " {}:{:.4}",
                                    c.method,
                                    c.loo_rms_target.unwrap_or(f64::NAN)
                                );
                            }
                        }
                        line += "]";
                    }
                    _ => {}
                }
            }
            // auto's rule on losses in metres instead of target units (diagnostic)
            if std::env::var_os("DIAG_METRES").is_some() {
                let m = prep.method(&methods[0]);
                let norm = prep.normalisation_for(&m, Normalisation::Minmax);
                let map = prep.normalised(prep.calib, &norm)?;
                let cal = prep.calibrate(&m, &norm, &map, 100, seed)?;
                let depth = &cal.samples;
                let target = depth.in_space(norm.space);
                let mut sq_t = Vec::new();
                let mut sq_m = Vec::new();
                let mut abs_m = Vec::new();
                for method in auto_candidates() {
                    let loo = loo_predictions(&target, &method)?;
                    let mut a = Vec::new();
                    let mut b = Vec::new();
                    let mut c = Vec::new();
                    for ((p, t), y) in depth.samples.iter().zip(&target.samples).zip(&loo) {
                        a.push((t.target - y).powi(2));
                        let z = norm.space.depth_from_target(*y);
                        let e = if z.is_finite() {
                            z - p.target
                        } else {
                            p.target
                        };
                        b.push(e * e);
                        c.push(e.abs());
                    }
                    sq_t.push(a);
                    sq_m.push(b);
                    abs_m.push(c);
                }
                for (label, l) in [("t", &sq_t), ("m2", &sq_m), ("m1", &abs_m)] {
                    let refs: Vec<&[f64]> = l.iter().map(Vec::as_slice).collect();
                    let i = if std::env::var_os("DIAG_MIN").is_some() {
                        let means: Vec<f64> = refs.iter().map(|r| r.iter().sum::<f64>()).collect();
                        (0..means.len())
                            .min_by(|&a, &b| means[a].total_cmp(&means[b]))
                            .unwrap_or(0)
                    } else {
                        one_standard_error_choice(&refs).unwrap_or(0)
                    };
                    let name = auto_candidates()[i].name();
                    let mi = names.iter().position(|n| *n == name).unwrap_or(0);
                    let mae = last_mae[mi];
                    alt_sum[label_idx(label)] += mae;
                    line += &format!(" auto_{label}={name}:{mae:.2}");
                }
            }
            println!("{line}");
        }
        let k = seeds as f64;
        let mut summary = String::from("mean  :");
        for (mi, n) in names.iter().enumerate() {
            summary += &format!(" {n}={:.2}/{:.2}", mae_sum[mi] / k, whole_sum[mi] / k);
        }
        println!("{summary}");
        if std::env::var_os("DIAG_BIAS").is_some() {
            let mut b = String::from("bias mm (mask/outside):");
            for (mi, n) in names.iter().enumerate() {
                let (a, o, c) = bias_acc[mi];
                b += &format!(" {n}={:+.2}/{:+.2}", a / c, o / c);
            }
            println!("{b}");
        }
        println!(
            "auto rule on target² / metres² / |metres|: {:.2} / {:.2} / {:.2}",
            alt_sum[0] / k,
            alt_sum[1] / k,
            alt_sum[2] / k
        );
        picks.sort();
        picks.dedup_by(|a, b| a == b);
        println!("auto picked: {}", picks.join(","));
    }
    Ok(())
}
