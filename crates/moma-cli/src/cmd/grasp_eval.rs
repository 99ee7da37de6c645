//! `moma grasp-eval`: the paper's grasp success-rate table, by proxy (METHOD.md §8).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Result, bail};
use clap::Args;
use moma_eval::grasp_eval::{
    GraspEvalConfig, GraspJsonRow, GraspRow, GripperKind, grasp_evaluate, grasp_table,
};
use moma_eval::report::write_table;

use super::common::{create_dir, join_paths};
use super::eval::{EvalOptions, PredArgs, load_set};

/// Grasp success rates by proxy: calibrate as `moma eval` does, plan the top-1 grasp per trial on
/// the aligned depth, execute it on the ground-truth depth of the same frame.
///
/// A trial is one object region: an 8-connected component of the frame's mask with at least
/// --min-object-px pixels, or the whole frame without a mask; no grasp found is a failed trial.
/// Rows `gt` (planned on the ground truth: the planner's ceiling) and `sensor` (planned on
/// raw_depth.png where the set has one) are always added. Writes OUT/grasp_results.{md,csv,json};
/// --json prints one array of {"set","method","gripper","trials","successes","success_rate"}.
/// PROXY scores, not robot trials; SIMULATED predictions are labelled so.
///
/// Example:
///   moma simulate --set ../shared/data/gqcnn-primesense -o pred/
///   moma grasp-eval --set ../shared/data/gqcnn-primesense --pred pred/ --seeds 3
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
pub struct GraspEvalArgs {
    /// Moma set folder(s).
    #[arg(long, value_name = "DIR", required = true)]
    pub set: Vec<PathBuf>,
    #[command(flatten)]
    pub pred: PredArgs,
    #[command(flatten)]
    pub eval: EvalOptions,
    /// Grippers, comma-separated: parallel, suction.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "parallel,suction",
        value_name = "GRIPPERS"
    )]
    pub gripper: Vec<GripperKind>,
    /// Smallest mask component that counts as an object (one trial), pixels.
    #[arg(long, default_value_t = moma_grasp::MIN_TRIAL_COMPONENT_PX, value_name = "PX")]
    pub min_object_px: usize,
    /// Output folder for grasp_results.{md,csv,json}.
    #[arg(
        short,
        long,
        visible_alias = "output",
        value_name = "DIR",
        default_value = "moma-grasp-eval-out"
    )]
    pub out: PathBuf,
    /// Print the JSON contract array to stdout (the table goes to stderr).
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: &GraspEvalArgs) -> Result<()> {
    if args.gripper.is_empty() {
        bail!("--gripper needs at least one of parallel, suction");
    }
    // refused before any set is loaded or any depth model runs
    args.eval.one_shot_only("grasp-eval")?;
    if args.eval.norm.len() > 1 {
        bail!(
            "--norm: `moma grasp-eval` plans with one normalisation (use `moma eval` to compare several)"
        );
    }
    let t0 = Instant::now();
    let mut rows: Vec<GraspRow> = Vec::new();
    // sets without any trial, noted and skipped when other sets have trials
    let mut skipped: Vec<String> = Vec::new();
    for (i, dir) in args.set.iter().enumerate() {
        let set = load_set(dir)?;
        let preds = args.pred.predictions(&set, i, args.set.len())?;
        let config = GraspEvalConfig {
            eval: args.eval.config(preds.kind()?)?,
            grippers: args.gripper.clone(),
            min_object_px: args.min_object_px,
            ..Default::default()
        };
        let r = match grasp_evaluate(&set, &preds, &config) {
            Err(e @ moma_eval::EvalError::NoGraspTrials { .. }) if args.set.len() > 1 => {
                eprintln!("note: {e}; skipped");
                skipped.push(e.to_string());
                continue;
            }
            r => r?,
        };
        eprintln!(
            "{}: {} rows ({:.1} s)",
            set.name,
            r.len(),
            t0.elapsed().as_secs_f64()
        );
        rows.extend(r);
    }
    if rows.is_empty() {
        bail!("no set has anything to grasp:\n  {}", skipped.join("\n  "));
    }
    create_dir(&args.out)?;
    let mut table = grasp_table(&rows);
    for s in &skipped {
        table.title.push_str(&format!(" — skipped: {s}"));
    }
    let files = write_table(&args.out, "grasp_results", &table, &rows)?;
    if args.json {
        eprintln!("{}", table.to_text());
        let json: Vec<GraspJsonRow> = rows.iter().map(GraspJsonRow::from).collect();
        println!("{}", serde_json::to_string_pretty(&json)?);
    } else {
        println!("{}", table.to_text());
    }
    eprintln!(
        "wrote {} ({:.1} s)",
        join_paths(&files),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}
