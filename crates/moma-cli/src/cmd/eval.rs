//! `moma eval`: the paper's evaluation protocol (docs/method.md §4) on moma sets.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use moma_core::PredictionKind;
use moma_core::align::Method;
use moma_core::align::robust::{Robust, RobustKind};
use moma_core::normalise::{AlignSpace, Normalisation};
use moma_core::sampling::SamplingStrategy;
use moma_eval::data::LoadedSet;
use moma_eval::protocol::{
    EvalConfig, EvalNote, PredictionSet, check_calib_frame_counts, evaluate, evaluate_few_shot,
};
use moma_eval::report::{contract_json, eval_table_with_notes, write_eval_outputs_with_notes};
use moma_eval::simulate::simulated_predictions;

use super::common::{ModelArgs, create_dir, join_paths};
use super::simulate::{SimOptions, TransparencyArg, per_set_dir};

/// Evaluate alignment methods on moma sets: calibrate on one frame, score every other frame.
///
/// Protocol (docs/method.md §4): the calibration frame (default: first frame id in sorted order)
/// gives n random valid ground-truth samples; every method is fitted on them and applied to
/// every other frame, which is scored inside its mask (whole image when there is no mask):
/// δ1.05, δ1.10, δ1.25, REL, RMSE, MAE. Per-image metrics are averaged over frames; the table
/// shows mean ± std (population) over sampling seeds; the pixel-pooled variant is written too.
/// Writes OUT/results.{md,csv,json}; --json prints one JSON array (one object per set, method,
/// variant and normalisation: set, method, protocol, variant, norm, samples, seeds, calib_frame and
/// d105, d110, d125, rel, rmse, mae as {"mean", "std"}, RMSE/MAE in metres) to stdout and the
/// table to stderr. `variant` is `one-shot` unless --calib-frames asks for few-shot calibration.
///
/// --protocol per-frame (sparse-to-dense, for single frames or a moving camera): every frame is
/// calibrated on its own n samples and its own ground truth scored; auto, ssra-local and
/// gssa-local then cross-validate by plain leave-one-out in relative error (as `moma calibrate
/// --protocol per-frame`).
///
/// Predictions: --pred DIR (<frame-id>.npy, float32 H×W, of kind --pred-kind; with several sets
/// either one --pred per set or one root holding a folder per set name), --simulate (simulated
/// in memory, labelled SIMULATED), or --weights (run Depth Anything V2 on rgb.png).
///
/// Examples:
///   moma eval --set data/gqcnn-primesense --pred preds/gqcnn
///   moma eval --set data/gqcnn-primesense --simulate --seeds 10 --json > results.json
///   moma eval --set data/a --set data/b --pred preds/ --methods ssra,gssa --norm minmax,median
///   # figures in out/m2t2/m2t2-table/figures/:
///   moma eval --set data/m2t2-table --simulate --max-gt-depth 2.0 --figures -o out/m2t2
///   moma eval --set data/gqcnn-primesense --weights da2_vits.safetensors --model vits
///   moma eval --set data/gqcnn-primesense --simulate --calib-frames 1,2,3  # few-shot
///   moma eval --set data/zed-da3-office --pred data/zed-da3-office/predictions \
///       --protocol per-frame --methods gssa,ssra,lwlr,auto --norm none --score-max-gt-depth 5
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
pub struct EvalArgs {
    /// Moma set folder(s); one block of rows per set.
    #[arg(long, value_name = "DIR", required = true)]
    pub set: Vec<PathBuf>,
    #[command(flatten)]
    pub pred: PredArgs,
    #[command(flatten)]
    pub eval: EvalOptions,
    /// Output folder for results.{md,csv,json} (and figures/).
    #[arg(
        short,
        long,
        visible_alias = "output",
        value_name = "DIR",
        default_value = "moma-eval-out"
    )]
    pub out: PathBuf,
    /// Also write a Fig.-6-style figure per frame (first seed) to OUT/<set>/figures/.
    #[arg(long)]
    pub figures: bool,
    /// Print the JSON contract array to stdout (tables go to stderr).
    #[arg(long)]
    pub json: bool,
    /// Few-shot calibration: calibrate on the first K frames in sorted frame-id order (one fit,
    /// --samples per frame), for each K given (e.g. 1,2,3). Every K scores the same frames: those
    /// after the largest K. Rows are labelled `one-shot` (K = 1) or `few-shot-K`; a set with too
    /// few frames gets a row saying so (when no set has enough, the command fails).
    #[arg(
        long,
        value_delimiter = ',',
        value_name = "K",
        conflicts_with = "calib_frame"
    )]
    pub calib_frames: Vec<usize>,
}

/// Where predictions come from (shared by eval, ablate and demo).
#[derive(Debug, Clone, Args)]
pub struct PredArgs {
    /// Prediction folder(s): <frame-id>.npy, float32 H×W. One per --set, or one root with a
    /// sub-folder per set name.
    #[arg(long, value_name = "DIR")]
    pub pred: Vec<PathBuf>,
    /// Kind of the predictions in --pred: metric-depth | relative-depth | relative-disparity
    /// (docs/formats.md "Prediction kinds"). Never guessed: taken from the folder's
    /// predictions.json when present (they must agree), else required.
    #[arg(long, value_name = "KIND")]
    pub pred_kind: Option<PredictionKind>,
    /// Simulate predictions in memory (docs/method.md §6) instead of reading --pred.
    #[arg(long, conflicts_with = "pred")]
    pub simulate: bool,
    /// Kind of simulated predictions: relative-disparity (like relative Depth Anything),
    /// metric-depth (a metric head) or relative-depth.
    #[arg(long, default_value = "relative-disparity", value_name = "KIND")]
    pub sim_kind: PredictionKind,
    /// Simulator seed.
    #[arg(long, default_value_t = 0)]
    pub sim_seed: u64,
    /// Transparency source of the simulator.
    #[arg(long, value_enum, default_value_t = TransparencyArg::Auto)]
    pub sim_transparency: TransparencyArg,
    #[command(flatten)]
    pub sim: SimOptions,
    #[command(flatten)]
    pub model: ModelArgs,
}

/// `--samples`' default: the paper's ~100 sparse ground-truth points.
pub const DEFAULT_SAMPLES: usize = 100;

/// Protocol options (shared by eval and ablate).
#[derive(Debug, Clone, Args)]
pub struct EvalOptions {
    /// Methods, comma-separated: ssra, gssa, lwlr (BoostingDepth's grid variant), lwlr-exact,
    /// lwlr-bare, ssra-local, gssa-local, auto, raw. Default: ssra,gssa,lwlr, and raw for
    /// metric-depth predictions.
    #[arg(long, value_delimiter = ',', value_name = "METHODS")]
    pub methods: Vec<Method>,
    /// Normalisation(s), comma-separated (`moma eval`; `grasp-eval` plans with one): minmax
    /// (paper), minmax-unit, median, none. Default: minmax-unit (the authors' code), as `moma
    /// calibrate` takes it (docs/evaluation.md, "The default normalisation").
    #[arg(long, value_delimiter = ',', value_name = "NORMS")]
    pub norm: Vec<Normalisation>,
    /// Alignment space: inverse or depth (default: the predictions' own).
    #[arg(long, value_name = "SPACE")]
    pub space: Option<AlignSpace>,
    /// Number of calibration samples n.
    #[arg(long, default_value_t = DEFAULT_SAMPLES)]
    pub samples: usize,
    /// Number of sampling seeds (seed i = seed-base + i).
    #[arg(long, default_value_t = 10)]
    pub seeds: usize,
    /// First sampling seed.
    #[arg(long, default_value_t = 0)]
    pub seed_base: u64,
    /// Calibration frame id (default: the first id in sorted order).
    #[arg(long, value_name = "ID")]
    pub calib_frame: Option<String>,
    /// Calibration-pixel sampling: random or grid.
    #[arg(long, default_value = "random", value_name = "SAMPLING")]
    pub sampling: SamplingStrategy,
    /// Draw calibration samples more than this many pixels away from depth discontinuities of
    /// the ground truth (as `moma calibrate --edge-margin-px`); 0: anywhere valid (MOMA).
    #[arg(long, default_value_t = 0, value_name = "PX")]
    pub edge_margin_px: u32,
    /// Only sample and score ground truth at or beyond this depth, metres.
    #[arg(long, value_name = "METRES")]
    pub min_gt_depth: Option<f64>,
    /// Only sample and score ground truth up to this depth, metres (e.g. 1.0 as the authors' code).
    #[arg(long, value_name = "METRES")]
    pub max_gt_depth: Option<f64>,
    /// Only score ground truth up to this depth, metres; calibration samples are still drawn
    /// from all valid ground truth (with --max-gt-depth, the smaller cap scores).
    #[arg(long, value_name = "METRES")]
    pub score_max_gt_depth: Option<f64>,
    /// Fixed workspace mask PNG (nonzero = inside, the set's image size): normalisation
    /// statistics of every frame's prediction are computed over this region only (as
    /// `moma calibrate --workspace`); sampling and scoring are unchanged.
    #[arg(long, value_name = "MASK.png")]
    pub workspace: Option<PathBuf>,
    /// Also evaluate per-frame re-alignment on static anchors: rows with variant
    /// `realign-anchors` (the calibration frame's rgb.png and ground truth as anchor store, each
    /// evaluated frame's rgb.png for its anchors) and a table of frames made worse.
    #[arg(long, value_enum, value_name = "MODE")]
    pub realign: Option<super::align::RealignArg>,
    /// Brightness factors of the evaluated frames' RGB for --realign (one block of rows each;
    /// variant `realign-anchors-b0.80` for 0.8). SIMULATED: the predictions get a small
    /// brightness response too (moma_eval::realign documents it).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "1",
        value_name = "FACTORS",
        requires = "realign"
    )]
    pub brightness: Vec<f64>,
    #[command(flatten)]
    pub realign_flags: super::align::RealignFlags,
    /// Robust variants to evaluate besides the one-shot least-squares fit, comma-separated:
    /// huber, tukey, ransac (rows with variant robust-<kind>, for gssa, ssra, gssa-local and
    /// ssra-local only; RANSAC is seeded with each sampling seed).
    #[arg(long, value_delimiter = ',', value_name = "KINDS")]
    pub robust: Vec<RobustKind>,
    /// Residual scale of the robust fits: `auto` (the default: from the data; Huber 1.345·σ̂,
    /// Tukey 4.685·σ̂, RANSAC 2.5·σ̂) or a fixed number of metres (depth, whatever the space).
    #[arg(long, value_name = "M|auto", requires = "robust")]
    pub robust_threshold_m: Option<super::calibrate::ThresholdArg>,
    /// SIMULATED sensor errors: replace this fraction (0–1) of the calibration frame's valid
    /// ground-truth pixels by wrong depths, truth ± U(0.1, 0.5) m, seeded per sampling seed.
    /// Every variant calibrates on the same corrupted frame; scoring uses the true ground truth.
    #[arg(long, value_name = "FRACTION")]
    pub gt_outliers: Option<f64>,
    /// The protocol (fixed-camera: calibrate on one frame, score every other frame, docs/method.md
    /// §4; per-frame: sparse-to-dense, every frame calibrated on its own --samples and scored on
    /// its own dense ground truth, for single frames or frames that do not share a camera pose;
    /// rows carry `protocol`, per-frame rows have calib_frame `each`), and the cross-validation
    /// of auto, ssra-local and gssa-local, as `moma calibrate`'s.
    #[command(flatten)]
    pub cv: super::calibrate::CvArgs,
}

impl EvalOptions {
    /// Refuses the variant options (`--realign`, `--robust`) for `command`, which runs one-shot
    /// calibrations only and would otherwise skip them silently or mix their rows in; before
    /// anything is loaded.
    pub fn one_shot_only(&self, command: &str) -> Result<()> {
        if self.realign.is_some() {
            bail!("--realign is not supported by `moma {command}` (use `moma eval` for it)");
        }
        if !self.robust.is_empty() {
            bail!("--robust is not supported by `moma {command}` (use `moma eval` for it)");
        }
        Ok(())
    }

    /// The library configuration for predictions of `kind` (it decides the default methods).
    pub fn config(&self, kind: PredictionKind) -> Result<EvalConfig> {
        // none given: the library takes the predictions' kind's default
        let norms = self.norm.clone();
        let methods = if self.methods.is_empty() {
            moma_eval::protocol::default_methods(kind)
        } else {
            self.methods.clone()
        };
        let methods = methods
            .into_iter()
            .map(|m| self.cv.method(m, None, None))
            .collect::<Result<Vec<_>>>()?;
        let depth_range_m = match (self.min_gt_depth, self.max_gt_depth) {
            (None, None) => None,
            (lo, hi) => {
                for (flag, v) in [("--min-gt-depth", lo), ("--max-gt-depth", hi)] {
                    if let Some(v) = v
                        && (v < 0.0 || v.is_nan())
                    {
                        bail!("{flag} {v} must be a depth in metres, >= 0");
                    }
                }
                let (lo, hi) = (lo.unwrap_or(0.0), hi.unwrap_or(f64::INFINITY));
                if hi.partial_cmp(&lo) != Some(std::cmp::Ordering::Greater) {
                    bail!("--max-gt-depth {hi} must be larger than --min-gt-depth {lo}");
                }
                Some((lo, hi))
            }
        };
        let workspace = self
            .workspace
            .as_ref()
            .map(|p| moma_io::read_mask(p).context("reading the --workspace mask"))
            .transpose()?;
        let realign = match self.realign {
            Some(_) => {
                let r = moma_eval::realign::RealignEval {
                    config: self.realign_flags.config()?,
                    brightness: self.brightness.clone(),
                    ..Default::default()
                };
                // Refused here, before any calibration runs.
                for &b in &r.brightness {
                    moma_eval::realign::check_brightness(b, r.brightness_response)
                        .context("--brightness")?;
                }
                Some(r)
            }
            None => None,
        };
        super::common::check_no_repeats("--robust", &self.robust)?;
        super::common::check_no_repeats("--brightness", &self.brightness)?;
        let robust: Vec<Robust> = self
            .robust
            .iter()
            .map(|&k| super::calibrate::ThresholdArg::robust(self.robust_threshold_m, k))
            .collect();
        for r in &robust {
            r.validate().context("--robust-threshold-m")?;
        }
        if !robust.is_empty() && !methods.iter().any(|m| robust[0].check_method(m).is_ok()) {
            bail!(
                "--robust applies to gssa, ssra, gssa-local and ssra-local; none of the methods \
                 asked for supports it"
            );
        }
        if let Some(f) = self.gt_outliers
            && !(0.0..=1.0).contains(&f)
        {
            bail!("--gt-outliers {f} must be a fraction between 0 and 1");
        }
        Ok(EvalConfig {
            methods,
            norms,
            space: self.space,
            samples: self.samples,
            seeds: self.seeds,
            seed_base: self.seed_base,
            calib_frame: self.calib_frame.clone(),
            sampling: self.sampling,
            edge_margin_px: self.edge_margin_px,
            depth_range_m,
            workspace,
            realign,
            robust,
            gt_outliers: self.gt_outliers,
            protocol: self.cv.protocol,
            score_max_depth_m: self.score_max_gt_depth,
        })
    }
}

/// Loads a set with context; says which frames have no mask (scored over the whole image).
pub fn load_set(dir: &std::path::Path) -> Result<LoadedSet> {
    let set = moma_eval::data::load_set(dir)
        .with_context(|| format!("loading moma set {}", dir.display()))?;
    if let Some(note) = set.mask_note() {
        eprintln!("note: {note}");
    }
    Ok(set)
}

impl PredArgs {
    /// Predictions for set `index` of `n_sets`.
    pub fn predictions(
        &self,
        set: &LoadedSet,
        index: usize,
        n_sets: usize,
    ) -> Result<PredictionSet> {
        self.refuse_unused()?;
        if self.model.weights.is_some() || self.model.hub.is_some() {
            return model_predictions(set, &self.model);
        }
        if self.simulate || self.pred.is_empty() {
            if !self.simulate {
                bail!(
                    "give predictions with --pred DIR, --simulate (simulated predictions) or --weights FILE (a real model)"
                );
            }
            return Ok(simulated_predictions(
                set,
                self.sim.config()?,
                self.sim_seed,
                self.sim_kind,
                self.sim_transparency.into(),
            )?);
        }
        let dir = if self.pred.len() == n_sets {
            self.pred[index].clone()
        } else if self.pred.len() == 1 {
            per_set_dir(&self.pred[0], &set.name, n_sets)
        } else {
            bail!(
                "{} --pred folders for {} sets: give one per set or one root folder",
                self.pred.len(),
                n_sets
            );
        };
        if !dir.is_dir() {
            bail!(
                "no predictions folder {} for set '{}'{}",
                dir.display(),
                set.name,
                if self.pred.len() == 1 && n_sets > 1 {
                    " (with one --pred root for several sets, each set's predictions are in \
                     ROOT/<set name>, as `moma simulate` writes them)"
                } else {
                    ""
                }
            );
        }
        Ok(PredictionSet::read(set, &dir, self.pred_kind)?)
    }
}

impl PredArgs {
    /// The simulator's options that differ from their defaults, by flag.
    pub fn simulator_options_given(&self) -> Vec<&'static str> {
        [
            (
                "--sim-kind",
                self.sim_kind != PredictionKind::RelativeDisparity,
            ),
            ("--sim-seed", self.sim_seed != 0),
            (
                "--sim-transparency",
                self.sim_transparency != TransparencyArg::Auto,
            ),
            ("--sim-config", self.sim.sim_config.is_some()),
            ("--off", !self.sim.off.is_empty()),
        ]
        .into_iter()
        .filter_map(|(flag, given)| given.then_some(flag))
        .collect()
    }

    /// One source of predictions, and no option that belongs to another: `--weights`/`--hub`
    /// (a depth model on each frame's rgb.png), `--pred` folders or `--simulate`. Options of a
    /// source not used would be ignored (`--lora` beside `--simulate` ran the simulator).
    ///
    /// # Errors
    /// Two sources, or an option of an unused source, named.
    pub fn refuse_unused(&self) -> Result<()> {
        let model = self.model.weights.is_some() || self.model.hub.is_some();
        if !model && self.pred.is_empty() && !self.simulate {
            // no source at all: the caller says which to give
            return Ok(());
        }
        if model && (!self.pred.is_empty() || self.simulate) {
            bail!(
                "--weights/--hub (the depth model on each frame's rgb.png) does not combine \
                 with --pred or --simulate (give one source of predictions)"
            );
        }
        let sim = self.simulator_options_given();
        if !self.simulate && !sim.is_empty() {
            bail!(
                "{}: simulator options, which apply only to simulated predictions (with {} they \
                 would be ignored)",
                sim.join(", "),
                if model {
                    "a depth model"
                } else {
                    "--pred folders"
                }
            );
        }
        if !model {
            self.model.refuse_for(if self.simulate {
                "simulated predictions"
            } else {
                "--pred folders"
            })?;
        }
        if self.pred_kind.is_some() && self.pred.is_empty() {
            bail!(
                "--pred-kind describes --pred folders; {}",
                if model {
                    "a depth model's output kind is its head's"
                } else {
                    "simulated predictions are of --sim-kind"
                }
            );
        }
        Ok(())
    }
}

/// Runs a real depth model on every frame's rgb.png.
pub fn model_predictions(set: &LoadedSet, model: &ModelArgs) -> Result<PredictionSet> {
    let loaded = model.load()?;
    let label = loaded.label(model.lora.as_deref());
    let mut net = loaded.model;
    let mut maps = Vec::with_capacity(set.frames.len());
    for f in &set.frames {
        let rgb = f.rgb.as_ref().with_context(|| {
            format!(
                "set '{}', frame '{}': no rgb.png to run the model on",
                set.name, f.id
            )
        })?;
        let t = Instant::now();
        let p = net.predict(rgb).with_context(|| {
            format!(
                "set '{}', frame '{}': running the depth model",
                set.name, f.id
            )
        })?;
        eprintln!(
            "{}/{}: model {:.2} s",
            set.name,
            f.id,
            t.elapsed().as_secs_f64()
        );
        maps.push(p);
    }
    Ok(PredictionSet {
        label,
        simulated: false,
        maps,
    })
}

pub fn run(args: &EvalArgs) -> Result<()> {
    let t0 = Instant::now();
    super::common::check_unique_set_names(&args.set)?;
    let few_shot = !args.calib_frames.is_empty();
    if few_shot {
        check_calib_frame_counts(&args.calib_frames).context("--calib-frames")?;
    }
    let mut all = Vec::new();
    let mut notes = Vec::new();
    for (i, dir) in args.set.iter().enumerate() {
        let set = load_set(dir)?;
        let preds = args.pred.predictions(&set, i, args.set.len())?;
        let config = args.eval.config(preds.kind()?)?;
        let results = if few_shot {
            match evaluate_few_shot(&set, &preds, &config, &args.calib_frames) {
                Ok(r) => r,
                Err(e) => match EvalNote::from_error(&e, "few-shot") {
                    Some(note) => {
                        eprintln!("note: {e}; skipped");
                        notes.push(note);
                        continue;
                    }
                    None => return Err(e.into()),
                },
            }
        } else {
            evaluate(&set, &preds, &config)?
        };
        if args.figures {
            let out = args.out.join(&set.name);
            let files = moma_eval::demo::write_visuals(&set, &preds, &config, &out, false)?;
            eprintln!(
                "{}: {} figures -> {}",
                set.name,
                files.figures.len(),
                out.join("figures").display()
            );
        }
        all.extend(results);
    }
    super::common::check_some_rows(&all, &notes)?;
    create_dir(&args.out)?;
    let files = write_eval_outputs_with_notes(&args.out, "results", &all, &notes)?;
    let mut table = eval_table_with_notes(&all, &notes, false).to_text();
    if all.iter().any(|r| r.realign.is_some()) {
        table.push('\n');
        table.push_str(&moma_eval::realign::realign_table(&all).to_text());
    }
    if let Some(f) = args.eval.gt_outliers {
        eprintln!(
            "SIMULATED ground-truth outliers: {:.1} % of the calibration frame's valid pixels \
             replaced by truth ± U(0.1, 0.5) m before sampling (every variant; scoring uses the \
             true ground truth)",
            f * 100.0
        );
    }
    if args.json {
        eprintln!("{table}");
        println!("{}", contract_json(&all)?);
    } else {
        println!("{table}");
    }
    eprintln!(
        "wrote {} ({:.1} s)",
        join_paths(&files),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}
