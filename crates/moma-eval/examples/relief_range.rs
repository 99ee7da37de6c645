//! The error model's relief range on real predictions (docs/grasping.md, "Tall objects: the
//! relief range"): for a calibration file, a prediction and its reference depth, the MAE of the
//! aligned depth, of the expected truth with the relief clamped at 0.1 m (every build before
//! calibration-file version 6), and of the expected truth over the fitted range
//! (`relief_max_m`), on the reference's pixels up to MAX_DEPTH_M (default 5 m).
//!
//! `cargo run --release -p moma-eval --example relief_range -- CALIB.json PRED.npy DEPTH.png [MAX_DEPTH_M]`

use moma_core::error_model::MAX_RELIEF_M;
use moma_core::metrics::DepthMetrics;
use moma_core::pipeline::AlignOptions;
use moma_core::{Mask, MetricDepth};
use ndarray::Array2;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 4 {
        return Err("usage: relief_range CALIB.json PRED.npy DEPTH.png [MAX_DEPTH_M]".into());
    }
    let file = moma_io::read_calibration(&args[1])?;
    let pred = moma_io::read_prediction(&args[2], file.prediction_kind)?;
    let gt = moma_io::read_depth(&args[3])?;
    let max_depth_m: f32 = args.get(4).map_or(Ok(5.0), |s| s.parse())?;
    let cal = &file.calibration;
    let aligned = cal.aligned(&pred, &AlignOptions::default())?;
    let model = cal
        .error_model
        .clone()
        .ok_or("the calibration has no error model")?;
    let clamped = moma_core::DepthErrorModel {
        relief_max_m: MAX_RELIEF_M,
        ..model.clone()
    };
    // the reference's pixels up to max_depth_m (DepthMetrics also skips pixels without depth)
    let near = Mask::new(gt.depth_m.mapv(|t| t <= max_depth_m));
    let mae_mm = |d: Array2<f32>| -> Result<f64, moma_core::CoreError> {
        Ok(1e3 * DepthMetrics::compute(&MetricDepth::new(d), &gt, Some(&near))?.mae)
    };
    let view = aligned.depth.depth_m.view();
    println!(
        "relief_bias {:.3} relief_max_m {:.1}: MAE mm aligned {:.1}, expected truth clamped at \
         0.1 m {:.1}, over the range {:.1}",
        model.relief_bias,
        model.relief_max_m,
        mae_mm(aligned.depth.depth_m.clone())?,
        mae_mm(clamped.expected_truth_map(view, false))?,
        mae_mm(model.expected_truth_map(view, false))?,
    );
    Ok(())
}
