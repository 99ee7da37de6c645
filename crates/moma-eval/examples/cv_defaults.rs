//! Data for choosing the cross-validation defaults of `auto` and the local corrections
//! (docs/evaluation.md, "Real predictions"): for each configuration of a JSON list (`[{"label": …, "local": {LocalConfig
//! fields}}]`), `auto`, `ssra-local` and `gssa-local` with those settings (and gssa, ssra, lwlr
//! once, as anchors) are evaluated
//! - on the REAL predictions of `zed-da3-office`, per-frame protocol (each frame calibrated on its
//!   own samples), AbsRel of each frame on the whole reference and on the reference ≤ 5 m;
//! - on the shared fixed-camera sets with SIMULATED inverse-depth predictions (simulator seed 0),
//!   the fixed-camera protocol, MAE and AbsRel per set.
//!
//! One JSON object per line on stdout; `benches/eval/cv_defaults.py` makes the tables.
//!
//! `MOMA_SHARED_DIR=../shared cargo run --release -p moma-eval --example cv_defaults -- CONFIGS.json [SEEDS] [NORM]`

use std::path::Path;

use moma_core::PredictionKind;
use moma_core::align::Method;
use moma_core::align::local::LocalConfig;
use moma_core::normalise::Normalisation;
use moma_eval::protocol::{EvalConfig, EvalResult, Protocol, evaluate};
use moma_eval::simulate::{SimulatorConfig, TransparencySource, simulated_predictions};
use serde::Deserialize;

const SIM_SETS: [&str; 4] = [
    "gqcnn-primesense",
    "graspnet6dof-table",
    "m2t2-table",
    "cleargrasp-transparent",
];

#[derive(Deserialize)]
struct Config {
    label: String,
    #[serde(default)]
    local: LocalConfig,
}

/// The methods of one configuration, and their row labels.
fn methods(configs: &[Config]) -> (Vec<Method>, Vec<String>) {
    let mut m = vec![
        Method::Gssa,
        Method::Ssra(Default::default()),
        Method::Lwlr(Default::default()),
    ];
    let mut labels = vec!["-".to_string(); 3];
    for c in configs {
        m.push(Method::Auto(c.local.clone()));
        m.push(Method::SsraLocal(c.local.clone()));
        m.push(Method::GssaLocal(c.local.clone()));
        labels.extend(std::iter::repeat_n(c.label.clone(), 3));
    }
    (m, labels)
}

fn emit(rows: &[EvalResult], labels: &[String], cap: &str) {
    for (r, label) in rows.iter().zip(labels) {
        for f in &r.frames {
            let n = f.per_seed.len() as f64;
            let rel = f.per_seed.iter().map(|m| m.rel).sum::<f64>() / n;
            let mae = f.per_seed.iter().map(|m| m.mae).sum::<f64>() / n;
            println!(
                "{}",
                serde_json::json!({
                    "set": r.set, "protocol": r.protocol, "cap": cap, "label": label,
                    "method": r.method, "frame": f.frame, "rel": rel, "mae": mae,
                    "fit_ms": r.fit_time_median_s * 1e3,
                })
            );
        }
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let configs: Vec<Config> = serde_json::from_str(&std::fs::read_to_string(
        args.get(1)
            .ok_or("usage: cv_defaults CONFIGS.json [SEEDS] [NORM]")?,
    )?)?;
    let seeds: usize = args.get(2).map_or(Ok(10), |s| s.parse())?;
    let norm: Normalisation = args.get(3).map_or(Ok(Normalisation::None), |s| s.parse())?;
    let shared = std::env::var("MOMA_SHARED_DIR").unwrap_or_else(|_| "../shared".into());
    let data = Path::new(&shared).join("data");
    let (methods, labels) = methods(&configs);
    let only = std::env::var("CV_ONLY").unwrap_or_default();

    if only.is_empty() || only == "real" {
        let set = moma_eval::data::load_set(&data.join("zed-da3-office"))?;
        let preds = moma_eval::protocol::PredictionSet::read(
            &set,
            &data.join("zed-da3-office/predictions"),
            None,
        )?;
        for (cap, score_cap) in [("all", None), ("5m", Some(5.0))] {
            let config = EvalConfig {
                methods: methods.clone(),
                norms: vec![norm],
                seeds,
                protocol: Protocol::PerFrame,
                score_max_depth_m: score_cap,
                ..EvalConfig::default()
            };
            emit(&evaluate(&set, &preds, &config)?, &labels, cap);
        }
    }
    if only.is_empty() || only == "sim" {
        for name in SIM_SETS {
            let set = moma_eval::data::load_set(&data.join(name))?;
            let preds = simulated_predictions(
                &set,
                SimulatorConfig::default(),
                0,
                PredictionKind::RelativeDisparity,
                TransparencySource::Auto,
            )?;
            let config = EvalConfig {
                methods: methods.clone(),
                seeds,
                ..EvalConfig::default()
            };
            emit(&evaluate(&set, &preds, &config)?, &labels, "all");
        }
    }
    Ok(())
}
