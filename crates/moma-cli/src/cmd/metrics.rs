//! `moma metrics`: score a metric depth map against ground truth.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use moma_core::metrics::DepthMetrics;

use super::common::print_json;

/// Depth metrics of a metric depth map against ground truth (docs/method.md §3).
///
/// Over pixels inside the mask where the ground truth is valid (> 0, finite) and the prediction
/// is finite: δ_t = fraction with max(p/g, g/p) < t (t = 1.05, 1.10, 1.25), REL = mean |p−g|/g,
/// RMSE = sqrt(mean (p−g)²) and MAE = mean |p−g| in metres.
///
/// Examples:
///   moma metrics --pred aligned/0001.depth.png --gt set/frames/0001/depth.png \
///       --mask set/frames/0001/mask.png
///   moma metrics --pred aligned/0001.depth.npy --gt set/frames/0001/depth.png --json
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
pub struct MetricsArgs {
    /// Metric depth to score: uint16 PNG (mm), .npy (m) or .pfm (m).
    #[arg(long, value_name = "FILE")]
    pub pred: PathBuf,
    /// Ground-truth depth, same formats.
    #[arg(long, value_name = "FILE")]
    pub gt: PathBuf,
    /// Evaluation mask (8-bit PNG, nonzero = inside); whole image when absent.
    #[arg(long, value_name = "PNG")]
    pub mask: Option<PathBuf>,
    /// Print one JSON object: d105, d110, d125, rel, rmse (m), mae (m), n (pixels), simulated
    /// (true when --pred is a raw prediction that its predictions.json lists as SIMULATED, or a
    /// depth that `moma align`, `grasp -o` or `demo` wrote from SIMULATED predictions, as the
    /// aligned.json of its folder records; a copy elsewhere is not listed).
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: &MetricsArgs) -> Result<()> {
    let pred = super::common::read_metric_depth(
        &args.pred,
        "--pred",
        "align it first (`moma align --calib calib.json --pred FILE -o aligned/`) and score the \
         aligned .depth.npy or .depth.png",
    )?;
    // The I/O error names the ground-truth file; the context adds which map it is for.
    let gt = moma_io::read_depth_sized(&args.gt, pred.size())
        .with_context(|| format!("reading the ground truth for {}", args.pred.display()))?;
    let mask = args
        .mask
        .as_ref()
        .map(|p| moma_io::read_mask_sized(p, pred.size()))
        .transpose()?;
    let m = DepthMetrics::compute(&pred, &gt, mask.as_ref()).with_context(|| {
        format!(
            "scoring {} against {}",
            args.pred.display(),
            args.gt.display()
        )
    })?;
    // the per-pixel sums are f32 (single precision is exact enough for depths of metres and
    // fast): only depths beyond ~1e18 m overflow them, which no depth map holds
    if ![m.rel, m.rmse, m.mae].iter().all(|x| x.is_finite()) {
        anyhow::bail!(
            "scoring {} against {}: the errors overflow (REL {}, RMSE {} m, MAE {} m): depths \
             of that size are not metres",
            args.pred.display(),
            args.gt.display(),
            m.rel,
            m.rmse,
            m.mae
        );
    }
    // a raw prediction listed as simulated, or a depth aligned from simulated predictions, is
    // labelled so in the numbers too, as every evaluation's results are
    let simulated = match super::common::depth_origin(&args.pred)? {
        super::common::DepthOrigin::Simulated(index) => Some(index),
        _ => None,
    };
    if let Some(index) = &simulated {
        eprintln!(
            "note: {} is SIMULATED (not from a depth model's output; {}): these are not a depth \
             model's errors",
            args.pred.display(),
            index.display()
        );
    }
    let simulated = simulated.is_some();
    if args.json {
        let mut value = serde_json::to_value(m)?;
        if let Some(fields) = value.as_object_mut() {
            fields.insert("simulated".into(), simulated.into());
        }
        print_json(&value)?;
    } else {
        println!("pixels  d1.05   d1.10   d1.25   REL     RMSE(m)  MAE(m)");
        println!(
            "{:<7} {:.4}  {:.4}  {:.4}  {:.4}  {:.4}   {:.4}",
            m.n, m.d105, m.d110, m.d125, m.rel, m.rmse, m.mae
        );
    }
    Ok(())
}
