//! Few-shot calibration on moma sets with SIMULATED predictions (docs/method.md §6, seed 0,
//! inverse depth), the same as `moma eval SETS --simulate --calib-frames 1,2,3 --methods
//! ssra,gssa,lwlr` without building the CLI:
//!
//! `cargo run --release -p moma-eval --example few_shot -- SET_DIR... [--ks 1,2,3] [--seeds 10]
//! [--norm minmax] [--fluctuation 0.03]` (`--fluctuation`: the simulator's per-frame
//! fluctuation of a_k, b_k, docs/method.md §6 component 4).
//!
//! Prints the table (notes for sets with too few frames), then per set and method whether
//! K = 3 is worse than K = 1, and the per-frame MAE of each K (which frames K helps).

use moma_core::PredictionKind;
use moma_core::align::Method;
use moma_eval::data::load_set;
use moma_eval::protocol::{
    EvalConfig, EvalNote, PredictionSet, Prepared, Variant, evaluate_few_shot, evaluate_variant,
};
use moma_eval::report::eval_table_with_notes;
use moma_eval::simulate::{SimulatorConfig, TransparencySource, simulated_predictions};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut dirs = Vec::new();
    let mut ks: Vec<usize> = vec![1, 2, 3];
    let mut seeds = 10;
    let mut norm = moma_core::normalise::Normalisation::Minmax;
    let mut sim_config = SimulatorConfig::default();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--ks" => {
                ks = args
                    .next()
                    .ok_or("--ks needs a list")?
                    .split(',')
                    .map(str::parse)
                    .collect::<Result<_, _>>()?;
            }
            "--seeds" => seeds = args.next().ok_or("--seeds needs a number")?.parse()?,
            "--norm" => norm = args.next().ok_or("--norm needs a name")?.parse()?,
            "--fluctuation" => {
                sim_config.frame_fluctuation =
                    args.next().ok_or("--fluctuation needs a number")?.parse()?;
            }
            _ => dirs.push(std::path::PathBuf::from(a)),
        }
    }
    let config = EvalConfig {
        methods: ["ssra", "gssa", "lwlr"]
            .iter()
            .map(|s| s.parse::<Method>())
            .collect::<Result<_, _>>()?,
        seeds,
        norms: vec![norm],
        ..Default::default()
    };
    let (mut all, mut notes) = (Vec::new(), Vec::new());
    for dir in &dirs {
        let set = load_set(dir)?;
        let preds = simulated_predictions(
            &set,
            sim_config,
            0,
            PredictionKind::RelativeDisparity,
            TransparencySource::Auto,
        )?;
        match evaluate_few_shot(&set, &preds, &config, &ks) {
            Ok(rows) => {
                single_frame_diagnostic(&set, &preds, &config, &ks)?;
                all.extend(rows);
            }
            Err(e) => match EvalNote::from_error(&e, "few-shot") {
                Some(n) => notes.push(n),
                None => return Err(e.into()),
            },
        }
    }
    println!(
        "{}",
        eval_table_with_notes(&all, &notes, false).to_markdown()
    );
    // Per set and method: MAE (mm) per K, and per scored frame.
    let k_max = ks.iter().copied().max().unwrap_or(1);
    for r in all.iter().filter(|r| r.variant == "one-shot") {
        let by_k: Vec<&moma_eval::protocol::EvalResult> = all
            .iter()
            .filter(|x| x.set == r.set && x.method == r.method)
            .collect();
        let line: Vec<String> = by_k
            .iter()
            .map(|x| format!("{} {:.2}", x.variant, x.per_image.mae.mean * 1e3))
            .collect();
        println!("{} {}: MAE mm {}", r.set, r.method, line.join(", "));
        for (fi, f) in r.frames.iter().enumerate() {
            let per_k: Vec<String> = by_k
                .iter()
                .map(|x| {
                    let m = &x.frames[fi].per_seed;
                    format!(
                        "{:.2}",
                        m.iter().map(|d| d.mae).sum::<f64>() / m.len() as f64 * 1e3
                    )
                })
                .collect();
            println!("    frame {}: {}", f.frame, per_k.join(" / "));
        }
    }
    println!("(K = {ks:?}, scored frames: those after the first {k_max}; SIMULATED predictions)");
    Ok(())
}

/// One-shot calibration on each of the first K_max frames alone, scored on the same frames as
/// the few-shot rows: is frame 0 a lucky (or unlucky) calibration frame? Their mean is the
/// expected one-shot MAE for a calibration frame drawn among them.
fn single_frame_diagnostic(
    set: &moma_eval::data::LoadedSet,
    preds: &PredictionSet,
    config: &EvalConfig,
    ks: &[usize],
) -> Result<(), Box<dyn std::error::Error>> {
    let k_max = ks.iter().copied().max().unwrap_or(1);
    let prep = Prepared::new(set, preds, config)?;
    let eval_idx: Vec<usize> = (k_max..set.frames.len()).collect();
    for m in &config.methods {
        let m = prep.method(m);
        let norm = prep.normalisation_for(&m, config.norms[0]);
        let maes: Vec<f64> = (0..k_max)
            .map(|i| {
                evaluate_variant(
                    &prep,
                    &m,
                    &norm,
                    config.samples,
                    Variant {
                        name: "single",
                        calib: &[i],
                        eval_idx: &eval_idx,
                        robust: None,
                    },
                )
                .map(|r| r.per_image.mae.mean * 1e3)
            })
            .collect::<Result<_, _>>()?;
        let mean = maes.iter().sum::<f64>() / maes.len() as f64;
        let list: Vec<String> = maes
            .iter()
            .enumerate()
            .map(|(i, x)| format!("{} {x:.2}", set.frames[i].id))
            .collect();
        println!(
            "{} {m}: one-shot MAE mm by calibration frame: {}; mean {mean:.2}",
            set.name,
            list.join(", ")
        );
    }
    Ok(())
}
