//! `moma demo`: the whole idea in one command, on a bundled procedural scene or a real set.

use std::path::PathBuf;
use std::time::Instant;

use super::common::join_paths;
use anyhow::{Context, Result};
use clap::Args;
use moma_eval::demo::{DemoScene, build_demo, write_grasp_overlay, write_visuals};
use moma_eval::grasp_eval::{GraspEvalConfig, grasp_evaluate, grasp_table};
use moma_eval::report::{eval_table, write_eval_outputs, write_table};
use moma_eval::scene::DemoSceneConfig;

use super::common::create_dir;
use super::eval::{EvalOptions, PredArgs, load_set};

/// The whole idea in one command: build a small fixed-camera scene (a tilted table with boxes,
/// cylinders and spheres, ray-cast exact depth, 640×480, f = 600 px), simulate depth-model
/// predictions (SIMULATED, inverse depth), calibrate SSRA / GSSA / LWLR on the first frame with
/// n = 100 random ground-truth points, align the other frames (one-shot, and re-aligned on
/// static anchors: rows `realign-anchors`), print the comparison table and the grasp table
/// (top-1 grasps planned on the ground truth and on each aligned depth, ranked robust under the
/// calibration's error model, scored by PROXY on the ground truth; success and mean
/// success_prob; at most 3 seeds), and write to OUT: scene/ (the moma set), predictions/
/// (simulated .npy + predictions.json), results.{md,csv,json}, grasp_results.{md,csv,json},
/// grasps/<frame>_suction.png (top-5 suction grasps on the re-aligned SSRA depth),
/// figures/<frame>.png (Fig.-6 style), aligned/<method>/<frame>.png (uint16 mm) + .npy
/// (float32 m) + _colour.png (with aligned.json: where each came from), pointclouds/<frame>_ssra.ply.
///
/// With --set DIR it runs on a real moma set instead (simulated predictions unless --pred DIR
/// or --weights FILE are given).
///
/// An earlier demo's output in OUT is replaced; a folder that holds anything else is refused.
///
/// Examples:
///   moma demo
///   moma demo -o /tmp/moma-demo --frames 8
///   moma demo --set data/gqcnn-primesense -o demo-gqcnn
///   moma demo --set data/gqcnn-primesense --weights depth_anything_v2_vits.safetensors --model vits
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
pub struct DemoArgs {
    /// Output folder.
    #[arg(
        short,
        long,
        visible_alias = "output",
        value_name = "DIR",
        default_value = "moma-demo"
    )]
    pub out: PathBuf,
    /// Run on this moma set instead of the bundled scene.
    #[arg(long, value_name = "DIR")]
    pub set: Option<PathBuf>,
    /// Frames of the bundled scene (2 to 100: one to calibrate on, the others evaluated; the
    /// frame ids `frame_00`… sort in frame order up to 100).
    #[arg(long, default_value_t = 6, value_parser = clap::value_parser!(u16).range(2..=100))]
    pub frames: u16,
    /// Skip aligned-depth, colour-map and point-cloud exports (figures and tables only).
    #[arg(long)]
    pub no_exports: bool,
    #[command(flatten)]
    pub pred: PredArgs,
    #[command(flatten)]
    pub eval: EvalOptions,
}

/// Sampling seeds of the demo's grasp table (at most).
const DEMO_GRASP_SEEDS: usize = 3;

/// What `moma demo` writes into its output folder.
const DEMO_ENTRIES: [&str; 12] = [
    "scene",
    "predictions",
    "aligned",
    "figures",
    "grasps",
    "pointclouds",
    "results.md",
    "results.csv",
    "results.json",
    "grasp_results.md",
    "grasp_results.csv",
    "grasp_results.json",
];

/// Clears an earlier demo's output in `out` (a run of fewer frames left the others' files
/// beside the new ones, and `moma eval` on the folder then refused a prediction its index did
/// not list). A folder holding anything a demo does not write is refused, never cleared.
fn clear_earlier_demo(out: &std::path::Path, inputs: &[&std::path::Path]) -> Result<()> {
    // an earlier demo's scene and predictions may be this run's input (`--set OUT/scene`):
    // never cleared under it
    if let Ok(out_abs) = out.canonicalize() {
        for input in inputs {
            if input.canonicalize().is_ok_and(|i| i.starts_with(&out_abs)) {
                anyhow::bail!(
                    "the output folder {} holds this run's input {}: give another folder with -o",
                    out.display(),
                    input.display()
                );
            }
        }
    }
    let entries = match std::fs::read_dir(out) {
        Ok(e) => e,
        // absent, or not a folder: create_dir says so
        Err(_) => return Ok(()),
    };
    let names: Vec<std::ffi::OsString> = entries
        .map(|e| e.map(|e| e.file_name()))
        .collect::<std::io::Result<_>>()
        .with_context(|| format!("reading the output folder {}", out.display()))?;
    if let Some(other) = names
        .iter()
        .find(|n| !DEMO_ENTRIES.iter().any(|d| n.as_os_str() == *d))
    {
        anyhow::bail!(
            "the output folder {} holds {}, which `moma demo` does not write: give a new or \
             empty folder with -o (an earlier demo's folder is cleared)",
            out.display(),
            other.to_string_lossy()
        );
    }
    if !names.is_empty() {
        eprintln!("removing the earlier demo output in {}", out.display());
    }
    for name in names {
        let path = out.join(name);
        let removed = if path.is_dir() {
            std::fs::remove_dir_all(&path)
        } else {
            std::fs::remove_file(&path)
        };
        removed.with_context(|| format!("removing the earlier {}", path.display()))?;
    }
    Ok(())
}

pub fn run(args: &DemoArgs) -> Result<()> {
    let t0 = Instant::now();
    // every setting is checked before anything is written into the output folder (the bundled
    // scene's predictions are simulated, of --sim-kind): a bad value fails with nothing written
    let (set, preds, mut config) = match &args.set {
        Some(dir) => {
            let set = load_set(dir)?;
            let mut pred = args.pred.clone();
            if pred.pred.is_empty() && pred.model.weights.is_none() && pred.model.hub.is_none() {
                pred.simulate = true;
            }
            let preds = pred.predictions(&set, 0, 1)?;
            let config = args.eval.config(preds.kind()?)?;
            config.check_counts()?;
            let inputs: Vec<&std::path::Path> = std::iter::once(dir.as_path())
                .chain(args.pred.pred.iter().map(|p| p.as_path()))
                .chain(args.pred.model.weights.as_deref())
                .chain(args.pred.model.lora.as_deref())
                .collect();
            clear_earlier_demo(&args.out, &inputs)?;
            create_dir(&args.out)?;
            (set, preds, config)
        }
        None => {
            if args.pred.model.weights.is_some()
                || args.pred.model.hub.is_some()
                || !args.pred.pred.is_empty()
            {
                anyhow::bail!(
                    "the bundled scene has simulated predictions only: use --set DIR with --weights or --pred"
                );
            }
            // the bundled scene's predictions are simulated: every other source's options would
            // be ignored, as `--simulate` refuses them
            PredArgs {
                simulate: true,
                ..args.pred.clone()
            }
            .refuse_unused()?;
            let config = args.eval.config(args.pred.sim_kind)?;
            config.check_counts()?;
            let demo = DemoScene {
                scene: DemoSceneConfig {
                    frames: usize::from(args.frames),
                    ..Default::default()
                },
                simulator: args.pred.sim.config()?,
                simulator_seed: args.pred.sim_seed,
                kind: args.pred.sim_kind,
            };
            clear_earlier_demo(&args.out, &[])?;
            create_dir(&args.out)?;
            let (set, preds) =
                build_demo(&demo, Some(&args.out)).context("building the demo scene")?;
            (set, preds, config)
        }
    };
    // what moma adds to the paper: per-frame re-alignment on static anchors, where the frames
    // have RGB (the bundled scene does)
    if config.realign.is_none() && set.frames.iter().all(|f| f.rgb.is_some()) {
        config.realign = Some(moma_eval::realign::RealignEval::default());
    }
    let t_build = t0.elapsed().as_secs_f64();
    let results = moma_eval::protocol::evaluate(&set, &preds, &config)?;
    let t_eval = t0.elapsed().as_secs_f64() - t_build;
    println!("{}", eval_table(&results, false).to_text());
    let mut tables = write_eval_outputs(&args.out, "results", &results)?;
    // grasps: ground truth vs the aligned depth, by proxy, robust under the error model
    let t_grasp = Instant::now();
    // at most 3 sampling seeds for the grasps: the demo stays under a minute
    let grasp_config = GraspEvalConfig {
        eval: moma_eval::protocol::EvalConfig {
            seeds: config.seeds.min(DEMO_GRASP_SEEDS),
            ..config.clone()
        },
        ..Default::default()
    };
    match grasp_evaluate(&set, &preds, &grasp_config) {
        Ok(g) => {
            let table = grasp_table(&g.rows);
            println!("{}", table.to_text());
            tables.extend(write_table(&args.out, "grasp_results", &table, &g.rows)?);
            let overlay = write_grasp_overlay(&set, &preds, &config, &args.out)?;
            eprintln!(
                "grasps: {:.1} s; overlay of the top-5 suction grasps: {}",
                t_grasp.elapsed().as_secs_f64(),
                overlay.display()
            );
        }
        Err(e @ moma_eval::EvalError::NoGraspTrials { .. }) => {
            eprintln!("note: no grasp table: {e}");
        }
        Err(e) => return Err(e.into()),
    }
    let files = write_visuals(&set, &preds, &config, &args.out, !args.no_exports)?;
    let total = t0.elapsed().as_secs_f64();
    eprintln!(
        "{} frames: calibrated on '{}', {} evaluated; {} figures, {} depth files, {} colour maps, {} point clouds",
        set.frames.len(),
        results
            .first()
            .map(|r| r.calib_frame.as_str())
            .unwrap_or("-"),
        results.first().map(|r| r.eval_frames).unwrap_or(0),
        files.figures.len(),
        files.depth.len(),
        files.colour_maps.len(),
        files.point_clouds.len()
    );
    eprintln!("tables: {}", join_paths(&tables));
    println!(
        "timing: scene + predictions {:.2} s, evaluation ({} seeds) {:.2} s, total {:.2} s -> {}",
        t_build,
        config.seeds,
        t_eval,
        total,
        args.out.display()
    );
    Ok(())
}
