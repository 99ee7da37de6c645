//! `moma simulate`: simulated depth-model predictions for moma sets (docs/method.md §6).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};
use moma_eval::simulate::{Simulator, SimulatorConfig, TransparencySource, simulate_set};

use super::common::create_dir;

/// Write SIMULATED depth-model predictions for moma sets (no trained model involved).
///
/// Turns each frame's ground truth into a plausible monocular-depth-model output with the
/// seeded simulator of docs/method.md §6, in this order: viewpoint/intrinsics mismatch (a planar scale
/// field), smooth non-planar bumps, relief compression, per-frame fluctuation in inverse depth,
/// edge smoothing + correlated noise, transparent objects pulled towards the surface behind.
/// Writes OUT/<frame-id>.npy (float32, H×W, of the given kind) and OUT/predictions.json (the
/// "simulated" label: config, seed, kind, random draws). With several sets: OUT/<set-name>/.
///
/// Examples:
///   moma simulate --set data/gqcnn-primesense -o preds/gqcnn
///   moma simulate --set data/m2t2-table --kind metric-depth --seed 3 -o preds/m2t2-metric
///   moma simulate --set data/gqcnn-primesense --off bumps,noise -o preds/gqcnn-clean
///   moma simulate --set data/a --set data/b -o preds/        # preds/a/, preds/b/
#[derive(Debug, Clone, Args)]
#[command(verbatim_doc_comment)]
pub struct SimulateArgs {
    /// Moma set folder(s).
    #[arg(long, value_name = "DIR", required = true)]
    pub set: Vec<PathBuf>,
    /// Output prediction folder (with several sets: one sub-folder per set name).
    #[arg(short, long, visible_alias = "output", value_name = "DIR")]
    pub out: PathBuf,
    /// Kind of prediction to simulate: relative-disparity (arbitrary scale and shift, like Depth
    /// Anything V2's relative models), metric-depth (a metric head: metres with a global scale
    /// error of ±25 %) or relative-depth (depth with an arbitrary scale).
    #[arg(long, default_value = "relative-disparity", value_name = "KIND")]
    pub kind: moma_core::PredictionKind,
    /// Seed of the per-set draws (per-frame parts are seeded by seed + frame id).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Transparency mask for component 6: auto = the frame's mask.png in sets whose frames have
    /// raw_depth.png (transparent sets such as cleargrasp), mask = always, none = never.
    #[arg(long, value_enum, default_value_t = TransparencyArg::Auto)]
    pub transparency: TransparencyArg,
    #[command(flatten)]
    pub sim: SimOptions,
}

/// Simulator strength options shared by `simulate`, `eval`, `ablate` and `demo`.
#[derive(Debug, Clone, Args, Default)]
pub struct SimOptions {
    /// JSON file with simulator strengths (any subset of the SimulatorConfig fields; the rest
    /// keep their defaults), e.g. {"bump_amplitude": 0.04, "noise_std": 0.01}.
    #[arg(long, value_name = "JSON")]
    pub sim_config: Option<PathBuf>,
    /// Components to switch off (strength 0), comma-separated.
    #[arg(long, value_enum, value_delimiter = ',', value_name = "COMPONENT")]
    pub off: Vec<Component>,
}

/// Simulator components that `--off` can disable.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Component {
    /// 1. viewpoint / intrinsics mismatch.
    Viewpoint,
    /// 2. smooth non-planar bumps.
    Bumps,
    /// 3. relief compression.
    Relief,
    /// 4. per-frame fluctuation.
    Fluctuation,
    /// 5a. edge smoothing.
    Edges,
    /// 5b. correlated multiplicative noise.
    Noise,
    /// 6. transparent objects.
    Transparency,
    /// the output's global scale error (metric-depth) / arbitrary scale (the relative kinds).
    Scale,
    /// the disparity shift of relative-disparity output.
    Shift,
}

/// `--transparency` values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum TransparencyArg {
    /// The frame's mask in transparent sets (frames with raw_depth.png).
    Auto,
    /// Always the frame's mask.
    Mask,
    /// Never.
    None,
}

impl From<TransparencyArg> for TransparencySource {
    fn from(t: TransparencyArg) -> Self {
        match t {
            TransparencyArg::Auto => TransparencySource::Auto,
            TransparencyArg::Mask => TransparencySource::Mask,
            TransparencyArg::None => TransparencySource::None,
        }
    }
}

impl SimOptions {
    /// The simulator configuration these options describe.
    pub fn config(&self) -> Result<SimulatorConfig> {
        let mut c = match &self.sim_config {
            Some(p) => {
                let text = std::fs::read_to_string(p)
                    .with_context(|| format!("reading {}", p.display()))?;
                serde_json::from_str(&text)
                    .with_context(|| format!("{}: not a simulator config", p.display()))?
            }
            None => SimulatorConfig::default(),
        };
        for comp in &self.off {
            match comp {
                Component::Viewpoint => {
                    c.view_angle_deg = 0.0;
                    c.focal_error = 0.0;
                    c.principal_point_error = 0.0;
                }
                Component::Bumps => c.bump_amplitude = 0.0,
                Component::Relief => c.relief_compression = 0.0,
                Component::Fluctuation => c.frame_fluctuation = 0.0,
                Component::Edges => c.edge_sigma_px = 0.0,
                Component::Noise => c.noise_std = 0.0,
                Component::Transparency => c.transparency_pull = 0.0,
                Component::Scale => {
                    c.depth_scale_error = 0.0;
                    c.inverse_log_scale = 0.0;
                }
                Component::Shift => {
                    c.disparity_shift_min = 0.0;
                    c.disparity_shift_max = 0.0;
                }
            }
        }
        c.validate()?;
        Ok(c)
    }
}

/// Output folder of set `i` of `n`: OUT itself for one set, OUT/<set-name> for several.
pub fn per_set_dir(out: &Path, set_name: &str, n: usize) -> PathBuf {
    if n > 1 {
        out.join(set_name)
    } else {
        out.to_path_buf()
    }
}

pub fn run(args: &SimulateArgs) -> Result<()> {
    super::common::check_unique_set_names(&args.set)?;
    let config = args.sim.config()?;
    for dir in &args.set {
        let set = moma_eval::data::load_set(dir)
            .with_context(|| format!("loading set {}", dir.display()))?;
        let out = per_set_dir(&args.out, &set.name, args.set.len());
        create_dir(&out)?;
        let sim = Simulator::new(config, args.seed, args.kind, set.intrinsics)?;
        let (meta, _) = simulate_set(&set, &sim, args.transparency.into(), &out)?;
        eprintln!(
            "{}: {} SIMULATED {} predictions -> {} (transparency from mask: {})",
            set.name,
            meta.frames.len(),
            meta.head.prediction_kind,
            out.display(),
            meta.transparency_from_mask
        );
    }
    Ok(())
}
