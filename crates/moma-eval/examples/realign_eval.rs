//! Re-alignment on static anchors on the shared sets with SIMULATED predictions (docs/method.md
//! §10): one-shot vs re-aligned MAE per set and method, brightness 1 / 0.8 / 1.2, and the
//! ablation over the anchor count and the ridge.
//!
//! `MOMA_SHARED_DIR=/work/shared cargo run --release -p moma-eval --example realign_eval [SEEDS] [KIND] [TARGET] [no-ablation] [form=F] [ridge=λ] [max-anchors=N] [acceptance-se=K] [sim-seeds=S]`
//! (default 10 seeds, simulated kind `relative-disparity` (old name `inverse-depth`);
//! `metric-depth` for metric-like predictions;
//! target `calibration-output` or `ground-truth`; the main table uses the library's
//! `RealignConfig` defaults unless `key=value` arguments override them). `sim-seeds=S` repeats
//! everything for simulator seeds 0..S (each a new draw of the per-set distortions and of the
//! per-frame fluctuation) and averages the MAEs per set and method over them: with one
//! simulator seed, the frame-to-frame change re-alignment corrects is a single random draw.

use moma_core::PredictionKind;
use moma_core::align::Method;
use moma_core::realign::CorrectionModel;
use moma_eval::protocol::{EvalConfig, EvalResult, evaluate};
use moma_eval::realign::{RealignEval, realign_table};
use moma_eval::simulate::{SimulatorConfig, TransparencySource, simulated_predictions};

const SETS: [&str; 4] = [
    "gqcnn-primesense",
    "graspnet6dof-table",
    "m2t2-table",
    "cleargrasp-transparent",
];

/// (correction, max anchors, ridge λ, acceptance margin in standard errors)
const ABLATION: [(CorrectionModel, usize, f64, f64); 19] = [
    (CorrectionModel::ScaleShift, 200, 0.0, 0.0),
    (CorrectionModel::ScaleShift, 200, 10.0, 0.0),
    (CorrectionModel::ScaleShift, 200, 100.0, 0.0),
    (CorrectionModel::ScaleShift, 200, 1000.0, 0.0),
    (CorrectionModel::ScaleShift, 2000, 10.0, 0.0),
    (CorrectionModel::ScaleShift, 2000, 100.0, 0.0),
    (CorrectionModel::ScaleShift, 2000, 1000.0, 0.0),
    (CorrectionModel::ScaleShift, 50, 100.0, 0.0),
    (CorrectionModel::ScaleShift, 200, 100.0, 1.0),
    (CorrectionModel::Planar, 200, 100.0, 0.0),
    (CorrectionModel::Planar, 2000, 100.0, 0.0),
    (CorrectionModel::Planar, 2000, 1000.0, 0.0),
    (CorrectionModel::PredictionAffine, 200, 1.0, 1.0),
    (CorrectionModel::PredictionAffine, 2000, 0.0, 1.0),
    (CorrectionModel::PredictionAffine, 2000, 1.0, 0.0),
    (CorrectionModel::PredictionAffine, 2000, 1.0, 1.0),
    (CorrectionModel::PredictionAffine, 2000, 1.0, 2.0),
    (CorrectionModel::PredictionAffine, 2000, 10.0, 1.0),
    (CorrectionModel::PredictionAffine, 2000, 100.0, 1.0),
];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let seeds: usize = std::env::args().nth(1).map_or(Ok(10), |s| s.parse())?;
    let kind: PredictionKind = std::env::args()
        .nth(2)
        .map_or(Ok(PredictionKind::RelativeDisparity), |s| s.parse())?;
    let target: moma_core::realign::AnchorTarget = std::env::args()
        .nth(3)
        .map_or(Ok(Default::default()), |s| s.parse())?;
    let mut ablate = true;
    let mut sim_seeds = 1u64;
    let mut base = RealignEval::default();
    for a in std::env::args().skip(4) {
        match a.split_once('=') {
            None if a == "no-ablation" => ablate = false,
            Some(("form", v)) => base.config.model = v.parse()?,
            Some(("ridge", v)) => base.config.ridge = v.parse()?,
            Some(("max-anchors", v)) => base.config.max_anchors = v.parse()?,
            Some(("acceptance-se", v)) => base.config.acceptance_se = v.parse()?,
            Some(("sim-seeds", v)) => sim_seeds = v.parse()?,
            _ => return Err(format!("unknown argument '{a}'").into()),
        }
    }
    let shared = std::env::var("MOMA_SHARED_DIR").unwrap_or_else(|_| "/work/shared".into());
    let methods: Vec<Method> = ["ssra", "gssa", "lwlr"]
        .iter()
        .map(|m| m.parse())
        .collect::<Result<_, _>>()?;
    let mut sets = Vec::new();
    let mut loaded = Vec::new();
    for name in SETS {
        let set =
            moma_eval::data::load_set(&std::path::Path::new(&shared).join("data").join(name))?;
        for sim_seed in 0..sim_seeds {
            let preds = simulated_predictions(
                &set,
                SimulatorConfig::default(),
                sim_seed,
                kind,
                TransparencySource::Auto,
            )?;
            loaded.push((sets.len(), preds));
        }
        sets.push(set);
    }
    let run = |mut realign: RealignEval| -> Result<Vec<EvalResult>, Box<dyn std::error::Error>> {
        realign.config.target = target;
        let mut all = Vec::new();
        for (set, preds) in &loaded {
            let set = &sets[*set];
            let config = EvalConfig {
                methods: methods.clone(),
                seeds,
                realign: Some(realign.clone()),
                ..Default::default()
            };
            all.extend(evaluate(set, preds, &config)?);
        }
        Ok(average_over_sim_seeds(all))
    };
    // main table: brightness 1, 0.8, 1.2
    println!(
        "main table: correction {}, max anchors {}, ridge {}, acceptance {} standard error(s)",
        base.config.model, base.config.max_anchors, base.config.ridge, base.config.acceptance_se
    );
    let all = run(RealignEval {
        brightness: vec![1.0, 0.8, 1.2],
        ..base.clone()
    })?;
    println!("{}", realign_table(&all).to_markdown());
    // the check: per method and variant, the change averaged over sets
    println!(
        "\n| method | variant | mean MAE change over sets % | sets made worse | worst frame rise mm | frames worse | worse > 2 mm | frames worse > 2 mm (mean over seeds) | worst rise of a frame's mean mm |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for m in &methods {
        for v in [
            "realign-anchors",
            "realign-anchors-b0.80",
            "realign-anchors-b1.20",
        ] {
            let rows: Vec<&EvalResult> = all
                .iter()
                .filter(|r| r.method == m.to_string() && r.variant == v)
                .collect();
            let changes: Vec<f64> = rows
                .iter()
                .filter_map(|r| {
                    r.realign
                        .map(|s| (r.per_image.mae.mean - s.one_shot_mae_m) / s.one_shot_mae_m)
                })
                .collect();
            let worse_sets = changes.iter().filter(|&&c| c > 0.0).count();
            let max_rise = rows
                .iter()
                .filter_map(|r| r.realign.map(|s| s.max_worse_mm))
                .fold(0.0, f64::max);
            let (w, n) = rows
                .iter()
                .filter_map(|r| r.realign)
                .fold((0, 0), |(w, n), s| (w + s.worse, n + s.results));
            let (wb, fb, ff) =
                rows.iter()
                    .filter_map(|r| r.realign)
                    .fold((0, 0, 0.0f64), |(wb, fb, ff), s| {
                        (
                            wb + s.worse_beyond_bound,
                            fb + s.frames_beyond_bound,
                            ff.max(s.max_frame_worse_mm),
                        )
                    });
            println!(
                "| {} | {v} | {:+.1} | {worse_sets}/{} | {max_rise:.2} | {w}/{n} | {wb} | {fb} | {ff:.2} |",
                m.to_string().to_uppercase(),
                100.0 * changes.iter().sum::<f64>() / changes.len() as f64,
                changes.len()
            );
        }
    }
    if !ablate {
        return Ok(());
    }
    // ablation: anchors used and ridge, brightness 1, mean change over sets and methods
    println!(
        "\n| correction | max anchors | ridge λ | acceptance SE | mean MAE change % | frames worse | max worse mm |"
    );
    println!("|---|---|---|---|---|---|---|");
    for (model, max_anchors, ridge, se) in ABLATION {
        {
            let mut realign = RealignEval::default();
            realign.config.model = model;
            realign.config.max_anchors = max_anchors;
            realign.config.ridge = ridge;
            realign.config.acceptance_se = se;
            let rows = run(realign)?;
            let stats: Vec<(f64, moma_eval::realign::RealignStats)> = rows
                .iter()
                .filter_map(|r| r.realign.map(|s| (r.per_image.mae.mean, s)))
                .collect();
            let change = stats
                .iter()
                .map(|(re, s)| (re - s.one_shot_mae_m) / s.one_shot_mae_m)
                .sum::<f64>()
                / stats.len() as f64;
            let (w, n) = stats
                .iter()
                .fold((0, 0), |(w, n), (_, s)| (w + s.worse, n + s.results));
            let mx = stats
                .iter()
                .map(|(_, s)| s.max_worse_mm)
                .fold(0.0, f64::max);
            println!(
                "| {model} | {max_anchors} | {ridge} | {se} | {:+.1} | {w}/{n} | {mx:.2} |",
                100.0 * change
            );
        }
    }
    Ok(())
}

/// Rows of the same set, method and variant from several simulator seeds merged into one: the
/// MAE and the one-shot MAE averaged, the frame counts summed, the largest rise kept. The other
/// fields (spreads, δ, REL, RMSE, per-frame detail) keep the first seed's values: the tables here
/// read only the MAE and the re-alignment counts.
fn average_over_sim_seeds(rows: Vec<EvalResult>) -> Vec<EvalResult> {
    let mut merged: Vec<(EvalResult, usize)> = Vec::new();
    for r in rows {
        let same = merged
            .iter_mut()
            .find(|(m, _)| m.set == r.set && m.method == r.method && m.variant == r.variant);
        match same {
            None => merged.push((r, 1)),
            Some((m, k)) => {
                *k += 1;
                let w = 1.0 / *k as f64;
                m.per_image.mae.mean += w * (r.per_image.mae.mean - m.per_image.mae.mean);
                if let (Some(a), Some(b)) = (m.realign.as_mut(), r.realign) {
                    a.one_shot_mae_m += w * (b.one_shot_mae_m - a.one_shot_mae_m);
                    a.accepted += b.accepted;
                    a.worse += b.worse;
                    a.results += b.results;
                    a.max_worse_mm = a.max_worse_mm.max(b.max_worse_mm);
                    a.worse_beyond_bound += b.worse_beyond_bound;
                    a.frames_beyond_bound += b.frames_beyond_bound;
                    a.max_frame_worse_mm = a.max_frame_worse_mm.max(b.max_frame_worse_mm);
                    a.mean_anchors += w * (b.mean_anchors - a.mean_anchors);
                    a.worse_fraction = a.worse as f64 / a.results as f64;
                }
            }
        }
    }
    merged.into_iter().map(|(m, _)| m).collect()
}
