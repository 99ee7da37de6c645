//! `moma grasp-eval`: the paper's grasp success-rate table, by proxy (docs/method.md §8).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use moma_eval::grasp_eval::{
    CoverageRow, GraspEvalConfig, GraspJsonRow, GraspRow, GripperKind, coverage_table,
    grasp_evaluate, grasp_table, reliability_table_of,
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
/// raw_depth.png where the set has one) are always added. The variants are `moma eval`'s, with
/// its flags and labels (--realign anchors [--brightness], --robust, --calib-frames). Grasps are
/// ranked robust (by success probability under the frame's error model; --grasp-quality).
/// Writes OUT/grasp_results.{md,csv,json}, OUT/grasp_reliability.{md,csv,json} and
/// OUT/sigma_coverage.{md,csv,json}; --json prints one array of {"set","method","variant",
/// "norm","grasp_quality","gripper","trials","successes","success_rate","best_of_candidates",
/// "brier","brier_base_rate","reliability":[{"bin":[lo,hi],"grasps":n,"predicted":p,
/// "achieved":a}],"calibration_frame_check":{"grasps","successes","mean_success_prob"}}
/// (grasp_results.json adds "failures", "mean_success_prob", "source" and "simulated").
/// `best_of_candidates`: trials where some grasp of the planner's candidates (up to 20, the ones
/// the ranking chooses from) succeeds on the ground truth, i.e. what a perfect ranking would
/// reach: below it the ranking loses grasps, above it the candidates hold none.
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
    /// Output folder for grasp_results, grasp_reliability and sigma_coverage (.md, .csv, .json).
    #[arg(
        short,
        long,
        visible_alias = "output",
        value_name = "DIR",
        default_value = "moma-grasp-eval-out"
    )]
    pub out: PathBuf,
    /// Few-shot calibration, as `moma eval --calib-frames`: calibrate on the first K frames in
    /// sorted frame-id order, for each K given; every K plans on the frames after the largest K.
    /// Rows `one-shot` (K = 1) or `few-shot-K`.
    #[arg(
        long,
        value_delimiter = ',',
        value_name = "K",
        conflicts_with = "calib_frame"
    )]
    pub calib_frames: Vec<usize>,
    /// Grasp rankings to evaluate, comma-separated: robust (by success probability under the
    /// calibration's error model), nominal (by the planner's score). One block of rows each.
    #[arg(long, value_delimiter = ',', default_value = "robust", value_name = "QUALITIES", value_parser = parse_quality)]
    pub grasp_quality: Vec<moma_grasp::GraspQuality>,
    /// Depth maps drawn from the error model per trial.
    #[arg(long, value_name = "N", default_value_t = moma_grasp::DEFAULT_GRASP_DRAWS)]
    pub grasp_draws: usize,
    /// Robust ranking: shares of successful draws within this of the best count as tied, and the
    /// planner's score decides among them (in [0, 1]; default 0.2 for the parallel jaw, 0.5
    /// for suction).
    #[arg(long, value_name = "P")]
    pub grasp_tie_tolerance: Option<f32>,
    /// Print the JSON contract array to stdout (the table goes to stderr).
    #[arg(long)]
    pub json: bool,
}

/// `--grasp-quality` values (`moma grasp` and `moma grasp-eval`): the library's names.
pub fn parse_quality(s: &str) -> std::result::Result<moma_grasp::GraspQuality, String> {
    s.parse().map_err(|e: moma_grasp::GraspError| e.to_string())
}

pub fn run(args: &GraspEvalArgs) -> Result<()> {
    super::common::check_unique_set_names(&args.set)?;
    if args.gripper.is_empty() {
        bail!("--gripper needs at least one of parallel, suction");
    }
    if !args.calib_frames.is_empty() {
        moma_eval::protocol::check_calib_frame_counts(&args.calib_frames)
            .context("--calib-frames")?;
    }
    if args.grasp_draws == 0 {
        bail!("--grasp-draws must be at least 1");
    }
    if let Some(t) = args.grasp_tie_tolerance
        && !(0.0..=1.0).contains(&t)
    {
        bail!("--grasp-tie-tolerance {t} is outside [0, 1]");
    }
    if args.eval.norm.len() > 1 {
        bail!(
            "--norm: `moma grasp-eval` plans with one normalisation (use `moma eval` to compare several)"
        );
    }
    let t0 = Instant::now();
    let mut rows: Vec<GraspRow> = Vec::new();
    let mut coverage: Vec<CoverageRow> = Vec::new();
    // sets without any trial, noted and skipped when other sets have trials
    let mut skipped: Vec<String> = Vec::new();
    for (i, dir) in args.set.iter().enumerate() {
        let set = load_set(dir)?;
        if set.frames.iter().all(|f| f.mask.is_none()) {
            // docs/method.md §8's rule, said where its rates are read
            eprintln!(
                "note: set '{}' has no object masks: each frame is one trial, won by a grasp on \
                 anything more than 10 mm above the support plane",
                set.name
            );
        }
        let preds = args.pred.predictions(&set, i, args.set.len())?;
        let config = GraspEvalConfig {
            eval: args.eval.config(preds.kind()?)?,
            grippers: args.gripper.clone(),
            min_object_px: args.min_object_px,
            calib_frames: args.calib_frames.clone(),
            qualities: args.grasp_quality.clone(),
            draws: args.grasp_draws,
            tie_tolerance: args.grasp_tie_tolerance,
            ..Default::default()
        };
        let r = match grasp_evaluate(&set, &preds, &config) {
            Err(
                e @ (moma_eval::EvalError::NoGraspTrials { .. }
                | moma_eval::EvalError::TooFewFrames { .. }),
            ) if args.set.len() > 1 => {
                eprintln!("note: {e}; skipped");
                skipped.push(e.to_string());
                continue;
            }
            r => r?,
        };
        eprintln!(
            "{}: {} rows ({:.1} s)",
            set.name,
            r.rows.len(),
            t0.elapsed().as_secs_f64()
        );
        rows.extend(r.rows);
        coverage.extend(r.coverage);
    }
    if rows.is_empty() {
        bail!("no set has anything to grasp:\n  {}", skipped.join("\n  "));
    }
    create_dir(&args.out)?;
    let mut table = grasp_table(&rows);
    for s in &skipped {
        table.title.push_str(&format!(" — skipped: {s}"));
    }
    let mut files = write_table(&args.out, "grasp_results", &table, &rows)?;
    let reliability = reliability_table_of(&rows);
    let cov = coverage_table(&coverage);
    files.extend(write_table(
        &args.out,
        "grasp_reliability",
        &reliability,
        &rows,
    )?);
    files.extend(write_table(&args.out, "sigma_coverage", &cov, &coverage)?);
    if args.json {
        eprintln!("{}", table.to_text());
        eprintln!("{}", reliability.to_text());
        eprintln!("{}", cov.to_text());
        let json: Vec<GraspJsonRow> = rows.iter().map(GraspJsonRow::from).collect();
        println!("{}", serde_json::to_string_pretty(&json)?);
    } else {
        println!("{}", table.to_text());
        println!("{}", reliability.to_text());
        println!("{}", cov.to_text());
    }
    eprintln!(
        "wrote {} ({:.1} s)",
        join_paths(&files),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}
