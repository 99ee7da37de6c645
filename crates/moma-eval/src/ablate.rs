//! Ablations (docs/method.md §4 a–d): number of samples with calibration time, normalisation,
//! prediction source, transparent objects. Each returns rows and writes a table and a PNG plot.
//!
//! Every ablation takes `calib_frames` = K: 1 is the paper's one-shot protocol
//! ([`crate::protocol::evaluate`]: the calibration frame, every other frame scored); K > 1
//! calibrates on the first K frames in sorted frame-id order (one fit, `samples` per frame,
//! [`crate::protocol::evaluate_few_shot`]) and scores the frames after K; the tables' titles say
//! so. A set with too few frames for K is an [`EvalError::TooFewFrames`] the caller may turn into
//! an [`EvalNote`], which the `write_*` functions show as a row.

use std::path::{Path, PathBuf};

use moma_core::metrics::DepthMetrics;
use moma_core::normalise::Normalisation;
use moma_core::{MetricDepth, is_valid_depth};
use serde::{Deserialize, Serialize};

use crate::data::LoadedSet;
use crate::error::{EvalError, Result};
use crate::protocol::{
    EvalConfig, EvalNote, EvalResult, MetricSummary, PredictionSet, Prepared, Stat, Variant,
    check_few_shot, evaluate, evaluate_few_shot, evaluate_one, evaluate_variant, few_shot_variant,
};
use crate::render::{LinePanel, Series, bar_plot, line_plot, source_caption};
use crate::report::{Table, headers_with_metrics, metric_cells, write_table};
use moma_core::align::Method;

/// The sample counts of the paper's ablation (a).
pub const SAMPLE_COUNTS: &[usize] = &[20, 50, 100, 200, 400, 1000, 3000];

/// Files written by an ablation.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct AblationOutput {
    /// Table files (md, csv, json).
    pub tables: Vec<PathBuf>,
    /// Plot files (PNG).
    pub plots: Vec<PathBuf>,
}

fn aligned_methods(config: &EvalConfig) -> Vec<Method> {
    config
        .methods
        .iter()
        .filter(|m| **m != Method::Raw)
        .cloned()
        .collect()
}

/// The frames an ablation calibrates on and scores: `calib_frames` = 1, the calibration frame
/// and every other frame; K > 1, the first K frames and the frames after K (checked as
/// [`check_few_shot`]).
fn frames_for(prep: &Prepared<'_>, calib_frames: usize) -> Result<(Vec<usize>, Vec<usize>)> {
    prep.require_fixed_camera("the ablation")?;
    if calib_frames == 0 {
        return Err(EvalError::InvalidParameter(
            "calibration frame counts must be at least 1, got 0".into(),
        ));
    }
    if calib_frames == 1 {
        return Ok((vec![prep.calib], prep.eval_indices()));
    }
    check_few_shot(prep.set, &prep.config, calib_frames)?;
    Ok((
        (0..calib_frames).collect(),
        (calib_frames..prep.set.frames.len()).collect(),
    ))
}

/// [`evaluate`] for `calib_frames` = 1, else [`evaluate_few_shot`] with K = `calib_frames`.
fn evaluate_k(
    set: &LoadedSet,
    preds: &PredictionSet,
    config: &EvalConfig,
    calib_frames: usize,
) -> Result<Vec<EvalResult>> {
    if calib_frames == 1 {
        evaluate(set, preds, config)
    } else {
        evaluate_few_shot(set, preds, config, &[calib_frames])
    }
}

/// (a) Accuracy and median calibration (fit) time against the number of samples n, calibrated
/// on `calib_frames` frames (module documentation; n samples per frame). RAW is skipped (it has
/// nothing to fit).
///
/// # Errors
/// As [`evaluate`] (`calib_frames` = 1) or [`evaluate_few_shot`].
pub fn samples(
    set: &LoadedSet,
    preds: &PredictionSet,
    config: &EvalConfig,
    counts: &[usize],
    calib_frames: usize,
) -> Result<Vec<EvalResult>> {
    let prep = Prepared::new(set, preds, config)?;
    let (calib, eval_idx) = frames_for(&prep, calib_frames)?;
    let name = few_shot_variant(calib_frames);
    let mut out = Vec::new();
    for &n in counts {
        for m in aligned_methods(config) {
            let norm = prep.normalisation_for(&m, prep.first_norm());
            out.push(if calib_frames == 1 {
                evaluate_one(&prep, &m, &norm, n)?
            } else {
                let spec = Variant {
                    name: &name,
                    calib: &calib,
                    eval_idx: &eval_idx,
                    robust: None,
                };
                evaluate_variant(&prep, &m, &norm, n, spec)?
            });
        }
    }
    Ok(out)
}

/// Table and plot (MAE and fit time against n, one line per method) of [`samples`]; `notes`
/// (sets that could not be evaluated, e.g. too few frames) become rows of the table.
///
/// # Errors
/// I/O or drawing failure.
pub fn write_samples(
    dir: &Path,
    rows: &[EvalResult],
    notes: &[EvalNote],
) -> Result<AblationOutput> {
    let mut headers = headers_with_metrics(&["set", "method", "n"]);
    headers.push("median fit ms".into());
    let mut table = Table {
        title: title("ablation (a): number of calibration samples n", rows),
        headers,
        rows: rows
            .iter()
            .map(|r| {
                let mut row = vec![
                    r.set.clone(),
                    r.method.to_uppercase(),
                    r.samples.to_string(),
                ];
                row.extend(metric_cells(&r.per_image));
                row.push(format!("{:.3}", r.fit_time_median_s * 1e3));
                row
            })
            .collect(),
    };
    push_notes(&mut table, 3, notes);
    let mut out = AblationOutput {
        tables: write_table(dir, "ablation_samples", &table, rows)?,
        plots: Vec::new(),
    };
    for set in unique(rows.iter().map(|r| r.set.clone())) {
        let rs: Vec<&EvalResult> = rows.iter().filter(|r| r.set == set).collect();
        let methods = unique(rs.iter().map(|r| r.method.clone()));
        let series = |f: &dyn Fn(&EvalResult) -> (f64, f64)| -> Vec<Series> {
            methods
                .iter()
                .map(|m| Series {
                    name: m.to_uppercase(),
                    points: rs
                        .iter()
                        .filter(|r| &r.method == m)
                        .map(|r| {
                            let (y, s) = f(r);
                            (r.samples as f64, y, s)
                        })
                        .collect(),
                })
                .collect()
        };
        let path = dir.join(format!("ablation_samples_{set}.png"));
        line_plot(
            &path,
            &plot_source(&rs),
            &[
                LinePanel {
                    title: format!("{set}: MAE vs n"),
                    x_label: "calibration samples n".into(),
                    y_label: "MAE [mm] (mean ± std over seeds)".into(),
                    log_x: true,
                    log_y: false,
                    series: series(&|r| (r.per_image.mae.mean * 1e3, r.per_image.mae.std * 1e3)),
                },
                LinePanel {
                    title: format!("{set}: calibration time vs n"),
                    x_label: "calibration samples n".into(),
                    y_label: "median fit time [ms]".into(),
                    log_x: true,
                    log_y: true,
                    series: series(&|r| (r.fit_time_median_s.max(1e-7) * 1e3, 0.0)),
                },
            ],
            620,
            460,
        )?;
        out.plots.push(path);
    }
    Ok(out)
}

/// (b) Every normalisation × method, calibrated on `calib_frames` frames (module documentation).
///
/// # Errors
/// As [`evaluate`] (`calib_frames` = 1) or [`evaluate_few_shot`]; the per-frame protocol.
pub fn norms(
    set: &LoadedSet,
    preds: &PredictionSet,
    config: &EvalConfig,
    norms: &[Normalisation],
    calib_frames: usize,
) -> Result<Vec<EvalResult>> {
    crate::protocol::require_fixed_camera(config.protocol, "the ablation")?;
    let cfg = EvalConfig {
        norms: norms.to_vec(),
        ..config.clone()
    };
    evaluate_k(set, preds, &cfg, calib_frames)
}

/// Grouped-bar plot of MAE per `group_of(row)` with one bar per method.
fn bar_by(
    path: &Path,
    title: &str,
    rows: &[&EvalResult],
    group_of: &dyn Fn(&EvalResult) -> String,
) -> Result<()> {
    let groups = unique(rows.iter().map(|r| group_of(r)));
    let methods = unique(rows.iter().map(|r| r.method.clone()));
    let series: Vec<(String, Vec<(f64, f64)>)> = methods
        .iter()
        .map(|m| {
            (
                m.to_uppercase(),
                groups
                    .iter()
                    .map(|g| {
                        rows.iter()
                            .find(|r| &r.method == m && &group_of(r) == g)
                            .map(|r| (r.per_image.mae.mean * 1e3, r.per_image.mae.std * 1e3))
                            .unwrap_or((f64::NAN, 0.0))
                    })
                    .collect(),
            )
        })
        .collect();
    bar_plot(
        path,
        title,
        &plot_source(rows),
        "MAE [mm] (mean ± std over seeds)",
        &groups,
        &series,
    )
}

/// Table and plot of [`norms`]; `notes` become rows of the table.
///
/// # Errors
/// I/O or drawing failure.
pub fn write_norms(dir: &Path, rows: &[EvalResult], notes: &[EvalNote]) -> Result<AblationOutput> {
    write_grouped(
        dir,
        rows,
        notes,
        Grouping {
            title: "ablation (b): normalisation × method",
            column: "norm",
            file_stem: "ablation_norm",
            plot_label: "normalisation",
            key: |r| r.norm.clone(),
        },
    )
}

/// How a one-factor ablation groups its rows in the table and the per-set bar plots.
struct Grouping {
    title: &'static str,
    column: &'static str,
    file_stem: &'static str,
    plot_label: &'static str,
    key: fn(&EvalResult) -> String,
}

/// Writes the table of `rows` and one bar plot per set, grouped by `g.key`.
fn write_grouped(
    dir: &Path,
    rows: &[EvalResult],
    notes: &[EvalNote],
    g: Grouping,
) -> Result<AblationOutput> {
    let mut table = simple_table(title(g.title, rows), g.column, rows, g.key);
    push_notes(&mut table, 3, notes);
    let mut out = AblationOutput {
        tables: write_table(dir, g.file_stem, &table, rows)?,
        plots: Vec::new(),
    };
    for set in unique(rows.iter().map(|r| r.set.clone())) {
        let rs: Vec<&EvalResult> = rows.iter().filter(|r| r.set == set).collect();
        let path = dir.join(format!("{}_{set}.png", g.file_stem));
        bar_by(&path, &format!("{set}: {}", g.plot_label), &rs, &g.key)?;
        out.plots.push(path);
    }
    Ok(out)
}

/// (c) Several prediction sources (e.g. simulated depth vs simulated inverse depth, or models),
/// calibrated on `calib_frames` frames (module documentation).
///
/// # Errors
/// As [`evaluate`] (`calib_frames` = 1) or [`evaluate_few_shot`].
pub fn sources(
    set: &LoadedSet,
    sources: &[PredictionSet],
    config: &EvalConfig,
    calib_frames: usize,
) -> Result<Vec<EvalResult>> {
    crate::protocol::require_fixed_camera(config.protocol, "the ablation")?;
    let mut out = Vec::new();
    for s in sources {
        // RAW uses a prediction as metres: only for metric-depth sources.
        let mut cfg = config.clone();
        if !s.kind()?.is_metric() {
            cfg.methods.retain(|m| *m != Method::Raw);
        }
        out.extend(evaluate_k(set, s, &cfg, calib_frames)?);
    }
    Ok(out)
}

/// Table and plot of [`sources`]; `notes` become rows of the table.
///
/// # Errors
/// I/O or drawing failure.
pub fn write_sources(
    dir: &Path,
    rows: &[EvalResult],
    notes: &[EvalNote],
) -> Result<AblationOutput> {
    write_grouped(
        dir,
        rows,
        notes,
        Grouping {
            title: "ablation (c): prediction source",
            column: "source",
            file_stem: "ablation_source",
            plot_label: "prediction source",
            key: |r| r.source.clone(),
        },
    )
}

/// What the depth sensor itself achieved on a transparent set (its `raw_depth.png`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SensorRow {
    /// Set name.
    pub set: String,
    /// Frames scored (the same frames as the methods).
    pub frames: Vec<String>,
    /// Per-image metrics of the sensor (pixels where the sensor measured something).
    pub per_frame: Vec<DepthMetrics>,
    /// Per-image mean.
    pub mean: DepthMetrics,
    /// Pixel-pooled.
    pub pooled: DepthMetrics,
    /// Fraction of the evaluated mask pixels where the sensor returned a depth.
    pub coverage: f64,
}

/// The transparent-objects ablation (d): the methods on the set, plus the raw sensor depth
/// scored against the ground truth inside the masks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TransparentResult {
    /// The methods.
    pub methods: Vec<EvalResult>,
    /// The sensor.
    pub sensor: SensorRow,
}

/// (d) Transparent objects, calibrated on `calib_frames` frames (module documentation); the
/// sensor is scored on the same frames as the methods. Needs `raw_depth.png` in the evaluated
/// frames.
///
/// # Errors
/// As [`evaluate`] (`calib_frames` = 1) or [`evaluate_few_shot`]; a frame without
/// `raw_depth.png` (named).
pub fn transparent(
    set: &LoadedSet,
    preds: &PredictionSet,
    config: &EvalConfig,
    calib_frames: usize,
) -> Result<TransparentResult> {
    let prep = Prepared::new(set, preds, config)?;
    let (_, eval_idx) = frames_for(&prep, calib_frames)?;
    let methods = evaluate_k(set, preds, config, calib_frames)?;
    let mut per_frame = Vec::new();
    let mut frames = Vec::new();
    let (mut covered, mut total) = (0usize, 0usize);
    for i in eval_idx {
        let f = &set.frames[i];
        let raw = f.raw_depth.as_ref().ok_or_else(|| {
            EvalError::frame(
                &set.name,
                &f.id,
                "no raw_depth.png (the transparent ablation needs what the sensor saw)",
            )
        })?;
        // 0 = no measurement: not a prediction of 0 m
        let raw_nan = MetricDepth::new(
            raw.depth_m
                .mapv(|z| if is_valid_depth(z) { z } else { f32::NAN }),
        );
        let region = &prep.eval_masks[i];
        total += region.count();
        covered += ndarray::Zip::from(region.data())
            .and(&raw_nan.depth_m)
            .fold(0, |acc, &m, &z| acc + usize::from(m && z.is_finite()));
        let m = DepthMetrics::compute(&raw_nan, &f.gt, Some(region)).map_err(|e| {
            EvalError::core(
                format!(
                    "set '{}', frame '{}': scoring raw sensor depth",
                    set.name, f.id
                ),
                e,
            )
        })?;
        per_frame.push(m);
        frames.push(f.id.clone());
    }
    let sensor = SensorRow {
        set: set.name.clone(),
        frames,
        mean: DepthMetrics::mean(&per_frame)
            .map_err(|e| EvalError::core(format!("set '{}', sensor depth", set.name), e))?,
        pooled: DepthMetrics::pooled(&per_frame)
            .map_err(|e| EvalError::core(format!("set '{}', sensor depth", set.name), e))?,
        per_frame,
        coverage: covered as f64 / total.max(1) as f64,
    };
    Ok(TransparentResult { methods, sensor })
}

/// Table and plot of [`transparent`] (possibly several sets); `notes` become rows of the table.
///
/// # Errors
/// I/O or drawing failure.
pub fn write_transparent(
    dir: &Path,
    results: &[TransparentResult],
    notes: &[EvalNote],
) -> Result<AblationOutput> {
    let headers = headers_with_metrics(&["set", "method", "coverage"]);
    let mut rows = Vec::new();
    let all: Vec<EvalResult> = results.iter().flat_map(|r| r.methods.clone()).collect();
    for r in results {
        for m in &r.methods {
            let mut row = vec![
                m.set.clone(),
                format!("{} ({})", m.method.to_uppercase(), m.norm),
                "1.000".into(),
            ];
            row.extend(metric_cells(&m.per_image));
            rows.push(row);
        }
        let s = &r.sensor;
        let single = |x: f64| Stat { mean: x, std: 0.0 };
        let ms = MetricSummary {
            d105: single(s.mean.d105),
            d110: single(s.mean.d110),
            d125: single(s.mean.d125),
            rel: single(s.mean.rel),
            rmse: single(s.mean.rmse),
            mae: single(s.mean.mae),
        };
        let mut row = vec![
            s.set.clone(),
            "SENSOR raw depth".into(),
            format!("{:.3}", s.coverage),
        ];
        row.extend(metric_cells(&ms));
        rows.push(row);
    }
    let mut table = Table {
        title: format!(
            "{}; SENSOR = raw_depth.png (what the depth camera saw through glass), scored where it measured (coverage = fraction of mask pixels with a measurement)",
            title(
                "ablation (d): transparent objects, inside the transparent-object masks",
                &all
            )
        ),
        headers,
        rows,
    };
    push_notes(&mut table, 3, notes);
    let mut out = AblationOutput {
        tables: write_table(dir, "ablation_transparent", &table, results)?,
        plots: Vec::new(),
    };
    for r in results {
        let path = dir.join(format!("ablation_transparent_{}.png", r.sensor.set));
        let mut groups: Vec<String> = r.methods.iter().map(|m| m.method.to_uppercase()).collect();
        groups.push("SENSOR".into());
        let mut vals: Vec<(f64, f64)> = r
            .methods
            .iter()
            .map(|m| (m.per_image.mae.mean * 1e3, m.per_image.mae.std * 1e3))
            .collect();
        vals.push((r.sensor.mean.mae * 1e3, 0.0));
        let method_rows: Vec<&EvalResult> = r.methods.iter().collect();
        bar_plot(
            &path,
            &format!(
                "{}: transparent objects (MAE inside the mask)",
                r.sensor.set
            ),
            &format!("{}; SENSOR = raw depth", plot_source(&method_rows)),
            "MAE [mm]",
            &groups,
            &[("MAE".into(), vals)],
        )?;
        out.plots.push(path);
    }
    Ok(out)
}

fn simple_table(
    title: String,
    key: &str,
    rows: &[EvalResult],
    f: impl Fn(&EvalResult) -> String,
) -> Table {
    let headers = headers_with_metrics(&["set", key, "method"]);
    Table {
        title,
        headers,
        rows: rows
            .iter()
            .map(|r| {
                let mut row = vec![
                    r.set.clone(),
                    f(r),
                    format!("{} ({})", r.method.to_uppercase(), r.norm),
                ];
                row.extend(metric_cells(&r.per_image));
                row
            })
            .collect(),
    }
}

fn title(what: &str, rows: &[EvalResult]) -> String {
    let sim = rows.iter().any(|r| r.simulated);
    match rows.first() {
        Some(r) => format!(
            "{}{what}{}{} — {} seeds, per-image mean (mean ± std over seeds), RMSE/MAE in mm",
            if sim {
                "SIMULATED predictions — "
            } else {
                ""
            },
            few_shot_clause(r),
            crate::report::edge_margin_clause(r.edge_margin_px),
            r.seeds
        ),
        None => what.to_string(),
    }
}

/// `""` for one-shot rows (the paper's protocol, the titles as before); for few-shot rows what
/// they were calibrated on and scored.
fn few_shot_clause(r: &EvalResult) -> String {
    match r
        .variant
        .strip_prefix("few-shot-")
        .and_then(|k| k.parse::<usize>().ok())
    {
        Some(k) => format!(
            ", few-shot: calibrated on the first {k} frames in sorted order (one fit, n samples \
             per frame), scored on the frames after the first {k}"
        ),
        None => String::new(),
    }
}

/// Appends one row per note: the set, `—` in the other `keys - 1` key columns, then the
/// variant and the note, `—` in the remaining columns.
fn push_notes(table: &mut Table, keys: usize, notes: &[EvalNote]) {
    let width = table.headers.len();
    for n in notes {
        let mut row = vec![n.set.clone()];
        row.resize(keys, "—".to_string());
        row.push(format!("{}: {}", n.variant, n.note));
        row.resize(width, "—".to_string());
        table.rows.push(row);
    }
}

/// The prediction source(s) of a plot's rows, for the strip above it: every distinct source once,
/// simulated ones marked SIMULATED (see [`source_caption`]).
fn plot_source(rows: &[&EvalResult]) -> String {
    let mut seen: Vec<(&str, bool)> = Vec::new();
    for r in rows {
        if !seen.contains(&(r.source.as_str(), r.simulated)) {
            seen.push((r.source.as_str(), r.simulated));
        }
    }
    match seen.as_slice() {
        [] => "predictions: none".into(),
        [(label, sim)] => source_caption(label, *sim),
        many if many.iter().all(|(_, sim)| *sim) => format!(
            "SIMULATED predictions ({})",
            many.iter().map(|(l, _)| *l).collect::<Vec<_>>().join("; ")
        ),
        many => many
            .iter()
            .map(|(l, sim)| source_caption(l, *sim))
            .collect::<Vec<_>>()
            .join("; "),
    }
}

fn unique(it: impl Iterator<Item = String>) -> Vec<String> {
    let mut v: Vec<String> = Vec::new();
    for s in it {
        if !v.contains(&s) {
            v.push(s);
        }
    }
    v
}
