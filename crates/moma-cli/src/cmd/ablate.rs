//! `moma ablate`: the paper's ablations, each a table (md/csv/json) and a PNG plot.

use std::path::PathBuf;
use std::time::Instant;

use super::common::join_paths;
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use moma_core::PredictionKind;
use moma_eval::ablate::{self, AblationOutput, SAMPLE_COUNTS};
use moma_eval::protocol::{EvalNote, PredictionSet, check_calib_frame_counts, few_shot_variant};
use moma_eval::simulate::{Simulator, simulate_frames};

// `ablate samples --counts`' help writes the default out comma-separated, as the flag takes it
const _: () = {
    let c = SAMPLE_COUNTS;
    assert!(c.len() == 7 && c[0] == 20 && c[1] == 50 && c[2] == 100 && c[3] == 200);
    assert!(c[4] == 400 && c[5] == 1000 && c[6] == 3000);
};

use super::common::create_dir;
use super::eval::{DEFAULT_SAMPLES, EvalOptions, PredArgs, load_set};

/// Ablations: number of samples (with calibration time), normalisation, prediction source,
/// transparent objects. Each writes OUT/ablation_<name>.{md,csv,json} and a PNG plot per set
/// (OUT/ablation_<name>_<set>.png), and prints the table.
///
/// Examples:
///   moma ablate samples --set data/gqcnn-primesense --simulate -o out/ablations
///   moma ablate norm --set data/gqcnn-primesense --simulate --norms minmax,median,none
///   moma ablate source --set data/gqcnn-primesense --source "sim metric:metric-depth:preds/d" \
///       --source "sim disp:relative-disparity:preds/i"
///   moma ablate source --set data/gqcnn-primesense      # simulated depth vs simulated inverse depth
///   moma ablate transparent --set data/cleargrasp-transparent --simulate
///   moma ablate norm --set data/gqcnn-primesense --simulate --calib-frames 3   # few-shot
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
pub struct AblateArgs {
    /// Which ablation.
    #[command(subcommand)]
    pub which: AblateCommand,
}

/// The ablations.
#[derive(Debug, Clone, Subcommand)]
pub enum AblateCommand {
    /// (a) n ∈ {20, 50, 100, 200, 400, 1000, 3000}: accuracy and median fit time per method.
    Samples {
        #[command(flatten)]
        common: AblateCommon,
        /// Sample counts, comma-separated [default: 20,50,100,200,400,1000,3000].
        #[arg(long, value_delimiter = ',', hide_default_value = true, default_values_t = SAMPLE_COUNTS.to_vec())]
        counts: Vec<usize>,
    },
    /// (b) normalisation × method.
    Norm {
        #[command(flatten)]
        common: AblateCommon,
        /// Normalisations, comma-separated.
        #[arg(
            long,
            value_delimiter = ',',
            default_value = "minmax,minmax-unit,median,none"
        )]
        norms: Vec<moma_core::Normalisation>,
    },
    /// (c) prediction source: several prediction folders with labels (default: simulated depth
    /// vs simulated inverse depth, in memory).
    Source {
        #[command(flatten)]
        common: AblateCommon,
        /// LABEL:KIND:DIR (KIND = metric-depth | relative-depth | relative-disparity), repeatable.
        #[arg(long, value_name = "LABEL:KIND:DIR")]
        source: Vec<String>,
    },
    /// (d) transparent objects: the methods plus the raw sensor depth (raw_depth.png) against
    /// the ground truth from opaque replicas, inside the transparent-object masks.
    Transparent {
        #[command(flatten)]
        common: AblateCommon,
    },
}

/// Options shared by every ablation.
#[derive(Debug, Clone, Args)]
pub struct AblateCommon {
    /// Moma set folder(s).
    #[arg(long, value_name = "DIR", required = true)]
    pub set: Vec<PathBuf>,
    #[command(flatten)]
    pub pred: PredArgs,
    #[command(flatten)]
    pub eval: EvalOptions,
    /// Output folder.
    #[arg(
        short,
        long,
        visible_alias = "output",
        value_name = "DIR",
        default_value = "moma-ablate-out"
    )]
    pub out: PathBuf,
    /// Few-shot calibration: every ablation calibrates on the first K frames in sorted frame-id
    /// order (one fit, --samples per frame) and scores the frames after K; the tables say so.
    /// 1 (default): the one-shot protocol (--calib-frame, every other frame scored). A set with
    /// fewer than K + 1 frames gets a row saying so (when no set has enough, the command fails).
    #[arg(long, value_name = "K", default_value_t = 1)]
    pub calib_frames: usize,
}

impl AblateCommon {
    /// `rows` of one set, or the note of a set with too few frames for --calib-frames (pushed to
    /// `notes`, no rows); any other error stops the ablation.
    fn noted<T>(
        &self,
        notes: &mut Vec<EvalNote>,
        rows: moma_eval::Result<Vec<T>>,
    ) -> Result<Vec<T>> {
        match rows {
            Ok(r) => Ok(r),
            Err(e) => match EvalNote::from_error(&e, &few_shot_variant(self.calib_frames)) {
                Some(note) => {
                    eprintln!("note: {e}; skipped");
                    notes.push(note);
                    Ok(Vec::new())
                }
                None => Err(e.into()),
            },
        }
    }
}

fn report(out: &AblationOutput, table_md: &std::path::Path, t0: Instant) -> Result<()> {
    let text = std::fs::read_to_string(table_md)
        .with_context(|| format!("reading {}", table_md.display()))?;
    println!("{text}");
    eprintln!(
        "wrote {} and plots {} ({:.1} s)",
        join_paths(&out.tables),
        join_paths(&out.plots),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

fn parse_source(s: &str, set: &moma_eval::data::LoadedSet) -> Result<PredictionSet> {
    let mut parts = s.splitn(3, ':');
    let (Some(label), Some(kind), Some(dir)) = (parts.next(), parts.next(), parts.next()) else {
        bail!("--source '{s}': expected LABEL:KIND:DIR");
    };
    let kind: PredictionKind = kind.parse().with_context(|| format!("--source '{s}'"))?;
    let mut p = PredictionSet::read(set, std::path::Path::new(dir), Some(kind))?;
    p.label = label.to_string();
    Ok(p)
}

pub fn run(args: &AblateArgs) -> Result<()> {
    let t0 = Instant::now();
    let common = match &args.which {
        AblateCommand::Samples { common, .. }
        | AblateCommand::Norm { common, .. }
        | AblateCommand::Source { common, .. }
        | AblateCommand::Transparent { common } => common,
    };
    check_calib_frame_counts(&[common.calib_frames]).context("--calib-frames")?;
    super::common::check_unique_set_names(&common.set)?;
    common.eval.one_shot_only("ablate")?;
    let k = common.calib_frames;
    let mut notes = Vec::new();
    create_dir(&common.out)?;
    let n = common.set.len();
    match &args.which {
        AblateCommand::Samples { counts, .. } => {
            // The sweep sets the sample count; a --samples would be silently replaced by it.
            if common.eval.samples != DEFAULT_SAMPLES {
                bail!(
                    "--samples {} does not apply to `moma ablate samples`: it sweeps the \
                     counts of --counts",
                    common.eval.samples
                );
            }
            super::common::check_no_repeats("--counts", counts)?;
            let mut rows = Vec::new();
            for (i, dir) in common.set.iter().enumerate() {
                let set = load_set(dir)?;
                let preds = common.pred.predictions(&set, i, n)?;
                let config = common.eval.config(preds.kind()?)?;
                let r = ablate::samples(&set, &preds, &config, counts, k);
                rows.extend(common.noted(&mut notes, r)?);
            }
            super::common::check_some_rows(&rows, &notes)?;
            let out = ablate::write_samples(&common.out, &rows, &notes)?;
            report(&out, &out.tables[0], t0)
        }
        AblateCommand::Norm { norms, .. } => {
            // The sweep sets the normalisation; a --norm would be silently replaced by it.
            if !common.eval.norm.is_empty() {
                bail!(
                    "--norm does not apply to `moma ablate norm`: give the normalisations to \
                     compare with --norms"
                );
            }
            super::common::check_no_repeats("--norms", norms)?;
            let mut rows = Vec::new();
            for (i, dir) in common.set.iter().enumerate() {
                let set = load_set(dir)?;
                let preds = common.pred.predictions(&set, i, n)?;
                let config = common.eval.config(preds.kind()?)?;
                let r = ablate::norms(&set, &preds, &config, norms, k);
                rows.extend(common.noted(&mut notes, r)?);
            }
            super::common::check_some_rows(&rows, &notes)?;
            let out = ablate::write_norms(&common.out, &rows, &notes)?;
            report(&out, &out.tables[0], t0)
        }
        AblateCommand::Source { source, .. } => {
            // its sources are --source folders (each with its kind) or, by default, the
            // simulator's two kinds: every other source's options would be ignored
            let p = &common.pred;
            if !p.pred.is_empty() || p.pred_kind.is_some() || p.simulate {
                bail!(
                    "ablate source compares --source LABEL:KIND:DIR folders (default: the \
                     simulator's depth and inverse depth): --pred, --pred-kind and --simulate do \
                     not apply"
                );
            }
            p.model
                .refuse_for("ablate source's --source folders or simulated predictions")?;
            let sim = p.simulator_options_given();
            if source.is_empty() && sim.contains(&"--sim-kind") {
                bail!(
                    "--sim-kind: ablate source simulates both kinds (metric-depth and \
                     relative-disparity) by default"
                );
            }
            if !source.is_empty() && !sim.is_empty() {
                bail!(
                    "{}: simulator options, which apply only to ablate source's default \
                     (simulated) sources, not to --source folders",
                    sim.join(", ")
                );
            }
            let mut rows = Vec::new();
            for dir in &common.set {
                let set = load_set(dir)?;
                let sources: Vec<PredictionSet> = if source.is_empty() {
                    let cfg = common.pred.sim.config()?;
                    [
                        PredictionKind::MetricDepth,
                        PredictionKind::RelativeDisparity,
                    ]
                    .into_iter()
                    .map(|kind| -> Result<PredictionSet> {
                        let sim = Simulator::new(cfg, common.pred.sim_seed, kind, set.intrinsics)?;
                        Ok(PredictionSet {
                            label: format!("SIMULATED {kind}"),
                            simulated: true,
                            maps: simulate_frames(&set, &sim, common.pred.sim_transparency.into())?,
                        })
                    })
                    .collect::<Result<_>>()?
                } else {
                    source
                        .iter()
                        .map(|s| parse_source(s, &set))
                        .collect::<Result<_>>()?
                };
                // RAW only for the metric-depth sources: the default method list of a depth
                // prediction, filtered per source by the library.
                let config = common.eval.config(PredictionKind::MetricDepth)?;
                let r = ablate::sources(&set, &sources, &config, k);
                rows.extend(common.noted(&mut notes, r)?);
            }
            super::common::check_some_rows(&rows, &notes)?;
            let out = ablate::write_sources(&common.out, &rows, &notes)?;
            report(&out, &out.tables[0], t0)
        }
        AblateCommand::Transparent { .. } => {
            let mut results = Vec::new();
            for (i, dir) in common.set.iter().enumerate() {
                let set = load_set(dir)?;
                let preds = common.pred.predictions(&set, i, n)?;
                let config = common.eval.config(preds.kind()?)?;
                let r = ablate::transparent(&set, &preds, &config, k).map(|r| vec![r]);
                results.extend(common.noted(&mut notes, r)?);
            }
            super::common::check_some_rows(&results, &notes)?;
            let out = ablate::write_transparent(&common.out, &results, &notes)?;
            report(&out, &out.tables[0], t0)
        }
    }
}
