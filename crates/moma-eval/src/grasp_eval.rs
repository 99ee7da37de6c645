//! Grasp success by proxy (METHOD.md §8, the paper's §V-E table): calibrate as [`crate::protocol`]
//! does, align every evaluated frame, plan the top-1 grasp per trial on the aligned depth, and
//! execute it in imagination on the ground-truth depth of the same frame.
//!
//! A trial is one object region: an 8-connected component of the frame's mask with at least
//! [`GraspEvalConfig::min_object_px`] pixels (the whole frame without a mask); planning and scoring
//! use that component as the object mask. A trial where no grasp is found is a failure with that
//! reason. Rows `gt` (planned on the ground truth itself: the planner's own ceiling) and `sensor`
//! (planned on the frame's `raw_depth.png`, where the set has one) are always added; they do not
//! depend on the sampling seed and are run once.
//!
//! **Every number is a proxy for a robot trial, not a robot result**, and is made from simulated
//! predictions whenever the predictions are simulated; tables say so.

use std::collections::BTreeMap;

use moma_core::normalise::NormalisedMap;
use moma_core::{Mask, MetricDepth};
use moma_grasp::{
    FailureReason, Gripper, MIN_TRIAL_COMPONENT_PX, ParallelConfig, ParallelJaw, Scene,
    SceneConfig, ScoreConfig, SuctionConfig, SuctionCup, mask_components, plan_parallel,
    plan_suction, score_grasp,
};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::data::LoadedSet;
use crate::error::{EvalError, Result};
use crate::protocol::{EvalConfig, PredictionSet, Prepared};
use crate::report::Table;

/// Which gripper a row is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GripperKind {
    /// Two-finger parallel jaw (Robotiq 2F-85 defaults).
    Parallel,
    /// Vacuum cup (10 mm radius).
    Suction,
}

impl GripperKind {
    /// Both grippers.
    pub const ALL: [GripperKind; 2] = [GripperKind::Parallel, GripperKind::Suction];

    /// `parallel` or `suction`.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Parallel => "parallel",
            Self::Suction => "suction",
        }
    }

    fn gripper(self) -> Gripper {
        match self {
            Self::Parallel => Gripper::Parallel(ParallelJaw::default()),
            Self::Suction => Gripper::Suction(SuctionCup::default()),
        }
    }
}

impl std::fmt::Display for GripperKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for GripperKind {
    type Err = EvalError;
    fn from_str(s: &str) -> Result<Self> {
        Self::ALL
            .into_iter()
            .find(|g| g.name() == s)
            .ok_or_else(|| {
                EvalError::InvalidParameter(format!(
                    "unknown gripper '{s}' (expected 'parallel' or 'suction')"
                ))
            })
    }
}

/// Settings of a grasp evaluation (the alignment settings are an [`EvalConfig`]).
#[derive(Debug, Clone, PartialEq)]
pub struct GraspEvalConfig {
    /// Alignment protocol: methods, normalisation (the first of `norms`), samples, seeds, ...
    pub eval: EvalConfig,
    /// Grippers, in table order.
    pub grippers: Vec<GripperKind>,
    /// Smallest mask component that counts as an object (trial), pixels (default 200).
    pub min_object_px: usize,
    /// Scene construction (support plane, objects without a mask).
    pub scene: SceneConfig,
    /// Proxy execution (friction μ, thresholds).
    pub score: ScoreConfig,
    /// Parallel-jaw planner settings.
    pub parallel: ParallelConfig,
    /// Suction planner settings.
    pub suction: SuctionConfig,
}

impl Default for GraspEvalConfig {
    fn default() -> Self {
        Self {
            eval: EvalConfig::default(),
            grippers: GripperKind::ALL.to_vec(),
            min_object_px: MIN_TRIAL_COMPONENT_PX,
            scene: SceneConfig::default(),
            score: ScoreConfig::default(),
            parallel: ParallelConfig::default(),
            suction: SuctionConfig::default(),
        }
    }
}

/// One row of the success-rate table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GraspRow {
    /// Set name.
    pub set: String,
    /// Method name, or `gt` (planned on ground truth) / `sensor` (planned on raw sensor depth).
    pub method: String,
    /// Gripper.
    pub gripper: GripperKind,
    /// Trials (object regions × evaluated frames × seeds; × 1 seed for `gt` and `sensor`).
    pub trials: usize,
    /// Successful top-1 grasps (proxy).
    pub successes: usize,
    /// successes / trials.
    pub success_rate: f64,
    /// Failures by reason (`collision`, `no_grasp`, ...).
    pub failures: BTreeMap<String, usize>,
    /// Prediction source label (`SIMULATED …` for simulated predictions).
    pub source: String,
    /// Whether the depth the grasps were planned on came from simulated predictions.
    pub simulated: bool,
}

/// The `--json` contract: one object per (set, method, gripper).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GraspJsonRow {
    /// Set name.
    pub set: String,
    /// Method (or `gt`, `sensor`).
    pub method: String,
    /// `parallel` or `suction`.
    pub gripper: GripperKind,
    /// Trials.
    pub trials: usize,
    /// Successes.
    pub successes: usize,
    /// successes / trials.
    pub success_rate: f64,
}

impl From<&GraspRow> for GraspJsonRow {
    fn from(r: &GraspRow) -> Self {
        Self {
            set: r.set.clone(),
            method: r.method.clone(),
            gripper: r.gripper,
            trials: r.trials,
            successes: r.successes,
            success_rate: r.success_rate,
        }
    }
}

/// One trial: the object region of a frame.
struct Trial {
    frame: usize,
    mask: Option<Mask>,
}

/// Outcome counts of a list of trials.
#[derive(Default)]
struct Tally {
    trials: usize,
    successes: usize,
    failures: BTreeMap<String, usize>,
}

impl Tally {
    fn add(&mut self, outcome: std::result::Result<(), FailureReason>) {
        self.trials += 1;
        match outcome {
            Ok(()) => self.successes += 1,
            Err(r) => *self.failures.entry(r.to_string()).or_default() += 1,
        }
    }

    fn merge(&mut self, other: Tally) {
        self.trials += other.trials;
        self.successes += other.successes;
        for (k, v) in other.failures {
            *self.failures.entry(k).or_default() += v;
        }
    }
}

/// Plans the top-1 grasp on `planned` (object `mask`) and executes it on the ground-truth scene.
fn run_trial(
    planned: &MetricDepth,
    gt_scene: &Scene,
    set: &LoadedSet,
    mask: Option<&Mask>,
    gripper: GripperKind,
    config: &GraspEvalConfig,
) -> Result<std::result::Result<(), FailureReason>> {
    let scene = match Scene::build(planned, &set.intrinsics, mask, &config.scene) {
        Ok(s) => s,
        // the aligned depth may hold no valid pixel in the object region: no grasp
        Err(_) => return Ok(Err(FailureReason::NoGrasp)),
    };
    let outcome = match gripper.gripper() {
        Gripper::Parallel(j) => plan_parallel(&scene, &j, &config.parallel),
        Gripper::Suction(c) => plan_suction(&scene, &c, &config.suction),
    }
    .map_err(|e| EvalError::InvalidParameter(format!("grasp planner: {e}")))?;
    let Some(grasp) = outcome.grasps.first() else {
        return Ok(Err(FailureReason::NoGrasp));
    };
    let score = score_grasp(gt_scene, grasp, &gripper.gripper(), &config.score)
        .map_err(|e| EvalError::InvalidParameter(format!("grasp scoring: {e}")))?;
    Ok(match score.failure {
        None if score.success => Ok(()),
        Some(r) => Err(r),
        None => Err(FailureReason::NoGrasp),
    })
}

/// Ground-truth scenes of every (evaluated frame, trial) pair, built once.
fn gt_scenes(
    set: &LoadedSet,
    trials: &[Trial],
    config: &GraspEvalConfig,
) -> Result<Vec<Option<Scene>>> {
    trials
        .par_iter()
        .map(|t| {
            let f = &set.frames[t.frame];
            // a trial whose ground truth holds no depth cannot be scored: reported as no grasp
            Ok(Scene::build(&f.gt, &set.intrinsics, t.mask.as_ref(), &config.scene).ok())
        })
        .collect()
}

/// Evaluates one set: rows for every (method, gripper), plus `gt` and (with raw depth) `sensor`.
/// One-shot calibrations with the first normalisation only: the re-alignment and robust variants
/// of [`EvalConfig`](crate::protocol::EvalConfig) are refused rather than silently skipped.
/// With [`EvalConfig::gt_outliers`](crate::protocol::EvalConfig::gt_outliers) the rows' source
/// says so.
///
/// # Errors
/// Bad input (see [`Prepared::new`]), alignment errors, an invalid planner configuration, an
/// unsupported variant or more than one normalisation.
pub fn grasp_evaluate(
    set: &LoadedSet,
    preds: &PredictionSet,
    config: &GraspEvalConfig,
) -> Result<Vec<GraspRow>> {
    if config.min_object_px == 0 {
        return Err(EvalError::InvalidParameter(
            "the smallest object region must be at least 1 pixel".into(),
        ));
    }
    let unsupported = [
        (config.eval.realign.is_some(), "re-alignment (--realign)"),
        (!config.eval.robust.is_empty(), "robust fits (--robust)"),
        (
            config.eval.norms.len() > 1,
            "more than one normalisation (--norm)",
        ),
    ];
    if let Some((_, what)) = unsupported.iter().find(|(given, _)| *given) {
        return Err(EvalError::InvalidParameter(format!(
            "the grasp evaluation plans on one-shot calibrations with one normalisation: {what} \
             is not supported here (use `moma eval` for it)"
        )));
    }
    let source = match config.eval.gt_outliers {
        Some(f) => format!(
            "{}; calibrated on ground truth with {:.1} % SIMULATED outliers",
            preds.label,
            100.0 * f
        ),
        None => preds.label.clone(),
    };
    let prep = Prepared::new(set, preds, &config.eval)?;
    let eval_idx = prep.eval_indices();
    let mut trials = Vec::new();
    for &i in &eval_idx {
        match &set.frames[i].mask {
            Some(m) => trials.extend(mask_components(m, config.min_object_px).into_iter().map(
                |c| Trial {
                    frame: i,
                    mask: Some(c),
                },
            )),
            None => trials.push(Trial {
                frame: i,
                mask: None,
            }),
        }
    }
    if trials.is_empty() {
        return Err(EvalError::NoGraspTrials {
            set: set.name.clone(),
            min_object_px: config.min_object_px,
            frames: eval_idx.len(),
        });
    }
    let gt = gt_scenes(set, &trials, config)?;
    let norm0 = config.eval.norms.first().copied().unwrap_or_default();
    let seeds: Vec<u64> = (0..config.eval.seeds as u64)
        .map(|s| config.eval.seed_base + s)
        .collect();
    let mut rows = Vec::new();
    let row =
        |method: String, gripper: GripperKind, t: Tally, source: &str, simulated: bool| GraspRow {
            set: set.name.clone(),
            method,
            gripper,
            success_rate: if t.trials > 0 {
                t.successes as f64 / t.trials as f64
            } else {
                f64::NAN
            },
            trials: t.trials,
            successes: t.successes,
            failures: t.failures,
            source: source.to_string(),
            simulated,
        };
    // planned on a depth map per evaluated frame (index into set.frames)
    // `depths[i]`: the depth planned on for frame i (None: nothing to plan on)
    let tally_on = |depths: &[Option<&MetricDepth>], gripper: GripperKind| -> Result<Tally> {
        let outcomes: Vec<std::result::Result<(), FailureReason>> = trials
            .par_iter()
            .zip(&gt)
            .map(|(t, g)| {
                let (Some(g), Some(d)) = (g, depths[t.frame]) else {
                    return Ok(Err(FailureReason::NoGrasp));
                };
                run_trial(d, g, set, t.mask.as_ref(), gripper, config)
            })
            .collect::<Result<_>>()?;
        let mut tally = Tally::default();
        for o in outcomes {
            tally.add(o);
        }
        Ok(tally)
    };
    for m in &config.eval.methods {
        let method = prep.method(m);
        let norm = prep.normalisation_for(&method, norm0);
        let maps: Vec<NormalisedMap> = (0..set.frames.len())
            .map(|i| prep.normalised(i, &norm))
            .collect::<Result<_>>()?;
        let mut per_gripper: Vec<Tally> =
            config.grippers.iter().map(|_| Tally::default()).collect();
        for &seed in &seeds {
            let cal =
                prep.calibrate(&method, &norm, &maps[prep.calib], config.eval.samples, seed)?;
            let aligned: Vec<Option<MetricDepth>> = (0..set.frames.len())
                .map(|i| {
                    if eval_idx.contains(&i) {
                        cal.align_normalised(&maps[i])
                            .map(Some)
                            .map_err(|e| EvalError::core(format!("set '{}'", set.name), e))
                    } else {
                        Ok(None)
                    }
                })
                .collect::<Result<_>>()?;
            let depths: Vec<Option<&MetricDepth>> = aligned.iter().map(Option::as_ref).collect();
            for (k, &g) in config.grippers.iter().enumerate() {
                per_gripper[k].merge(tally_on(&depths, g)?);
            }
        }
        for (k, &g) in config.grippers.iter().enumerate() {
            rows.push(row(
                method.to_string(),
                g,
                std::mem::take(&mut per_gripper[k]),
                &source,
                preds.simulated,
            ));
        }
    }
    let gt_depths: Vec<Option<&MetricDepth>> = set.frames.iter().map(|f| Some(&f.gt)).collect();
    for &g in &config.grippers {
        let t = tally_on(&gt_depths, g)?;
        rows.push(row("gt".into(), g, t, "ground-truth depth", false));
    }
    if eval_idx.iter().any(|&i| set.frames[i].raw_depth.is_some()) {
        let raw: Vec<Option<&MetricDepth>> =
            set.frames.iter().map(|f| f.raw_depth.as_ref()).collect();
        for &g in &config.grippers {
            let t = tally_on(&raw, g)?;
            rows.push(row("sensor".into(), g, t, "raw sensor depth", false));
        }
    }
    Ok(rows)
}

/// The success-rate table (proxy). Title says "proxy" and, for simulated predictions,
/// "SIMULATED predictions".
pub fn grasp_table(rows: &[GraspRow]) -> Table {
    let simulated = rows.iter().any(|r| r.simulated);
    let sources: Vec<String> = {
        let mut s: Vec<String> = rows
            .iter()
            .filter(|r| r.method != "gt" && r.method != "sensor")
            .map(|r| r.source.clone())
            .collect();
        s.dedup();
        s
    };
    let title = format!(
        "{}grasp success by PROXY (top-1 grasp planned on the method's depth, executed on the \
         ground-truth depth; METHOD.md §8) — not robot trials; predictions: {}",
        if simulated {
            "SIMULATED predictions — "
        } else {
            ""
        },
        sources.join(", ")
    );
    Table {
        title,
        headers: [
            "set",
            "method",
            "gripper",
            "trials",
            "successes",
            "success rate",
            "failures",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect(),
        rows: rows
            .iter()
            .map(|r| {
                vec![
                    r.set.clone(),
                    r.method.to_uppercase(),
                    r.gripper.to_string(),
                    r.trials.to_string(),
                    r.successes.to_string(),
                    format!("{:.0} %", 100.0 * r.success_rate),
                    r.failures
                        .iter()
                        .map(|(k, v)| format!("{k} {v}"))
                        .collect::<Vec<_>>()
                        .join(", "),
                ]
            })
            .collect(),
    }
}
