//! Diagnosis of re-alignment on one set with SIMULATED predictions (docs/method.md §10): per
//! evaluated frame and seed, the one-shot and `prediction-affine` re-aligned MAE and signed mean
//! error (metres) on the evaluated objects and on the static background (valid ground truth
//! outside the objects), the anchors on the objects, and the accepted map.
//!
//! `MOMA_SHARED_DIR=/work/shared cargo run --release -p moma-eval --example realign_diag [SET] [METHOD] [SEEDS]`

use moma_core::align::Method;
use moma_core::normalise::NormalisationConfig;
use moma_core::realign::{CorrectionModel, GreyHalf, RealignConfig};
use moma_core::{AlignOptions, PredictionInput, PredictionKind};
use moma_eval::protocol::{EvalConfig, Prepared};
use moma_eval::simulate::{SimulatorConfig, TransparencySource, simulated_predictions};
use ndarray::ArrayView3;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let name = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "cleargrasp-transparent".into());
    let method: Method = std::env::args()
        .nth(2)
        .map_or(Ok(Method::Gssa), |s| s.parse())?;
    let seeds: u64 = std::env::args().nth(3).map_or(Ok(3), |s| s.parse())?;
    let shared = std::env::var("MOMA_SHARED_DIR").unwrap_or_else(|_| "/work/shared".into());
    let set = moma_eval::data::load_set(&std::path::Path::new(&shared).join("data").join(&name))?;
    let kind = PredictionKind::RelativeDisparity;
    let preds = simulated_predictions(
        &set,
        SimulatorConfig::default(),
        0,
        kind,
        TransparencySource::Auto,
    )?;
    let config = EvalConfig::default();
    let prep = Prepared::new(&set, &preds, &config)?;
    let norm: NormalisationConfig =
        prep.normalisation_for(&method, moma_core::normalise::Normalisation::Minmax);
    let method = prep.method(&method);
    let grey = |i: usize| -> Result<GreyHalf, Box<dyn std::error::Error>> {
        let f = &set.frames[i];
        let img = f
            .rgb
            .as_ref()
            .ok_or_else(|| format!("frame '{}' has no rgb.png", f.id))?;
        Ok(moma_io::grey_half(ArrayView3::from_shape(
            (img.height() as usize, img.width() as usize, 3),
            img.as_raw(),
        )?)?)
    };
    let cmap = prep.normalised(prep.calib, &norm)?;
    println!(
        "set {name}, calibration frame {}, method {method}",
        set.frames[prep.calib].id
    );
    println!(
        "| frame | seed | objects MAE mm one-shot → realigned | objects signed mm | background MAE mm | background signed mm | anchors (on objects) | accepted | a, b |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for seed in 0..seeds {
        let cal = prep
            .calibrate(&method, &norm, &cmap, 100, seed)?
            .with_anchors(
                &grey(prep.calib)?,
                &set.frames[prep.calib].gt,
                PredictionInput::normalised(&cmap, prep.kind()),
            )?;
        for i in prep.eval_indices() {
            let map = prep.normalised(i, &norm)?;
            let input = PredictionInput::normalised(&map, prep.kind());
            let one = cal.aligned(input, &AlignOptions::default())?.depth;
            let rc = RealignConfig {
                model: CorrectionModel::PredictionAffine,
                seed,
                ..Default::default()
            };
            let frame_grey = grey(i)?;
            let realigned = cal.aligned(input, &AlignOptions::realigned(&frame_grey, &rc))?;
            let re = realigned.depth;
            let rep = realigned.realign.ok_or("re-alignment gave no report")?;
            let anchors =
                moma_core::realign::find_anchors(cal.anchor_store()?, &frame_grey, &rc.thresholds)?;
            let objm = &prep.eval_masks[i];
            let on_obj = anchors
                .pixels
                .iter()
                .filter(|&&(u, v, _, _)| objm.data()[[v as usize, u as usize]])
                .count();
            let gt = &set.frames[i].gt.depth_m;
            let stats = |d: &ndarray::Array2<f32>, obj: bool| {
                let (mut s, mut sa, mut n) = (0.0, 0.0, 0usize);
                for ((v, u), &g) in gt.indexed_iter() {
                    let inside = objm.data()[[v, u]];
                    if inside != obj || !(g.is_finite() && g > 0.0) {
                        continue;
                    }
                    let z = d[[v, u]];
                    if !z.is_finite() {
                        continue;
                    }
                    let e = (z - g) as f64;
                    s += e;
                    sa += e.abs();
                    n += 1;
                }
                (1e3 * sa / n as f64, 1e3 * s / n as f64)
            };
            let (o1, os1) = stats(&one.depth_m, true);
            let (o2, os2) = stats(&re.depth_m, true);
            let (b1, bs1) = stats(&one.depth_m, false);
            let (b2, bs2) = stats(&re.depth_m, false);
            println!(
                "| {} | {seed} | {o1:.2} → {o2:.2} | {os1:+.2} → {os2:+.2} | {b1:.2} → {b2:.2} | {bs1:+.2} → {bs2:+.2} | {} ({on_obj}) | {} | {:?} |",
                set.frames[i].id,
                anchors.pixels.len(),
                rep.accepted,
                rep.prediction_affine
            );
        }
    }
    Ok(())
}
