//! Result tables: console / Markdown / CSV / JSON.

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::data::write_text;
use crate::error::{EvalError, Result};
use crate::protocol::{EvalNote, EvalResult, JsonRow, MetricSummary, Stat};

/// How the calibration samples were drawn, for table titles: `""` for MOMA's protocol (margin
/// 0), else " (more than R px from depth edges)" ([`crate::protocol::EvalConfig::edge_margin_px`]).
pub fn edge_margin_clause(edge_margin_px: u32) -> String {
    if edge_margin_px > 0 {
        format!(" (more than {edge_margin_px} px from depth edges)")
    } else {
        String::new()
    }
}

/// A plain table of strings with a title.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Table {
    /// Title (printed above the table).
    pub title: String,
    /// Column headers.
    pub headers: Vec<String>,
    /// Rows (same length as `headers`).
    pub rows: Vec<Vec<String>>,
}

impl Table {
    /// GitHub-flavoured Markdown.
    pub fn to_markdown(&self) -> String {
        let mut s = String::new();
        if !self.title.is_empty() {
            s.push_str(&format!("**{}**\n\n", self.title));
        }
        s.push_str(&format!("| {} |\n", self.headers.join(" | ")));
        s.push_str(&format!(
            "|{}|\n",
            self.headers
                .iter()
                .enumerate()
                .map(|(i, _)| if i < 2 { "---" } else { "---:" })
                .collect::<Vec<_>>()
                .join("|")
        ));
        for r in &self.rows {
            s.push_str(&format!("| {} |\n", r.join(" | ")));
        }
        s
    }

    /// Fixed-width text for the terminal.
    pub fn to_text(&self) -> String {
        let mut widths: Vec<usize> = self.headers.iter().map(|h| h.chars().count()).collect();
        for r in &self.rows {
            for (w, c) in widths.iter_mut().zip(r) {
                *w = (*w).max(c.chars().count());
            }
        }
        let line = |cells: &[String]| -> String {
            cells
                .iter()
                .zip(&widths)
                .enumerate()
                .map(|(i, (c, &w))| {
                    let pad = w - c.chars().count();
                    if i < 2 {
                        format!("{c}{}", " ".repeat(pad))
                    } else {
                        format!("{}{c}", " ".repeat(pad))
                    }
                })
                .collect::<Vec<_>>()
                .join("  ")
        };
        let mut s = String::new();
        if !self.title.is_empty() {
            s.push_str(&self.title);
            s.push('\n');
        }
        s.push_str(&line(&self.headers));
        s.push('\n');
        s.push_str(&"-".repeat(widths.iter().sum::<usize>() + 2 * widths.len().saturating_sub(1)));
        s.push('\n');
        for r in &self.rows {
            s.push_str(&line(r));
            s.push('\n');
        }
        s
    }

    /// CSV (RFC 4180 quoting where needed).
    pub fn to_csv(&self) -> String {
        let q = |c: &str| {
            if c.contains([',', '"', '\n']) {
                format!("\"{}\"", c.replace('"', "\"\""))
            } else {
                c.to_string()
            }
        };
        let mut s = self
            .headers
            .iter()
            .map(|h| q(h))
            .collect::<Vec<_>>()
            .join(",");
        s.push('\n');
        for r in &self.rows {
            s.push_str(&r.iter().map(|c| q(c)).collect::<Vec<_>>().join(","));
            s.push('\n');
        }
        s
    }
}

/// `mean ± std` with `prec` decimals, scaled by `k`.
pub fn pm(s: &Stat, k: f64, prec: usize) -> String {
    format!("{:.p$} ± {:.p$}", s.mean * k, s.std * k, p = prec)
}

/// The six metric cells of a summary (δ with 3 decimals, REL 4, RMSE/MAE in mm with 1).
pub fn metric_cells(m: &MetricSummary) -> Vec<String> {
    vec![
        pm(&m.d105, 1.0, 3),
        pm(&m.d110, 1.0, 3),
        pm(&m.d125, 1.0, 3),
        pm(&m.rel, 1.0, 4),
        pm(&m.rmse, 1000.0, 1),
        pm(&m.mae, 1000.0, 1),
    ]
}

/// Table headers: the `keys` columns, then the six metric cells.
pub fn headers_with_metrics(keys: &[&str]) -> Vec<String> {
    let metrics = [
        "δ1.05 ↑",
        "δ1.10 ↑",
        "δ1.25 ↑",
        "REL ↓",
        "RMSE mm ↓",
        "MAE mm ↓",
    ];
    keys.iter().chain(&metrics).map(|s| s.to_string()).collect()
}

/// The paper-style table of an evaluation (per-image mean, mean ± std over seeds).
pub fn eval_table(results: &[EvalResult], pooled: bool) -> Table {
    eval_table_with_notes(results, &[], pooled)
}

/// [`eval_table`] followed by one row per note (a set that could not be evaluated as asked,
/// e.g. too few frames for few-shot calibration): set, variant, and the note in the first
/// metric column.
pub fn eval_table_with_notes(results: &[EvalResult], notes: &[EvalNote], pooled: bool) -> Table {
    let mut headers = headers_with_metrics(&["set", "method", "variant", "norm"]);
    headers.push("fit ms".into());
    let mut rows: Vec<Vec<String>> = results
        .iter()
        .map(|r| {
            let mut row = vec![
                r.set.clone(),
                r.method.to_uppercase(),
                r.variant.clone(),
                r.norm.clone(),
            ];
            row.extend(metric_cells(if pooled { &r.pooled } else { &r.per_image }));
            row.push(format!("{:.3}", r.fit_time_median_s * 1e3));
            row
        })
        .collect();
    for n in notes {
        let mut row = vec![
            n.set.clone(),
            "—".to_string(),
            n.variant.clone(),
            "—".to_string(),
            n.note.clone(),
        ];
        row.resize(headers.len(), "—".to_string());
        rows.push(row);
    }
    let first = results.first();
    let sim = results.iter().any(|r| r.simulated);
    let title = match first {
        Some(r) => format!(
            "{}{} — n = {} samples{}, {} seeds, {}; {} (mean ± std over seeds{})",
            if sim {
                "SIMULATED predictions — "
            } else {
                ""
            },
            r.source,
            r.samples,
            edge_margin_clause(r.edge_margin_px),
            r.seeds,
            if results
                .iter()
                .all(|r| r.protocol == crate::protocol::Protocol::PerFrame)
            {
                "per-frame protocol: each frame calibrated on its own samples and scored on its \
                 own ground truth"
                    .to_string()
            } else {
                format!("calibration frame(s): {}", calib_list(results))
            },
            if pooled {
                "pixel-pooled"
            } else {
                "per-image mean"
            },
            ", RMSE/MAE in mm"
        ),
        None => String::new(),
    };
    Table {
        title,
        headers,
        rows,
    }
}

fn calib_list(results: &[EvalResult]) -> String {
    let mut v: Vec<String> = Vec::new();
    for r in results {
        let s = format!("{}:{}", r.set, r.calib_frame);
        if !v.contains(&s) {
            v.push(s);
        }
    }
    v.join(", ")
}

/// Machine-readable CSV of an evaluation: metres, mean and std columns, per-image and pooled.
pub fn eval_csv(results: &[EvalResult]) -> String {
    let names = ["d105", "d110", "d125", "rel", "rmse", "mae"];
    let mut headers: Vec<String> = [
        "set",
        "source",
        "simulated",
        "pred_kind",
        "method",
        "variant",
        "norm",
        "samples",
        "seeds",
        "calib_frame",
        "eval_frames",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    for prefix in ["", "pooled_"] {
        for n in names {
            headers.push(format!("{prefix}{n}_mean"));
            headers.push(format!("{prefix}{n}_std"));
        }
    }
    headers.push("fit_time_median_s".into());
    headers.push("protocol".into());
    let stats = |m: &MetricSummary| -> Vec<String> {
        [m.d105, m.d110, m.d125, m.rel, m.rmse, m.mae]
            .iter()
            .flat_map(|s| [format!("{:.9}", s.mean), format!("{:.9}", s.std)])
            .collect()
    };
    let rows = results
        .iter()
        .map(|r| {
            let mut row = vec![
                r.set.clone(),
                r.source.clone(),
                r.simulated.to_string(),
                r.pred_kind.to_string(),
                r.method.clone(),
                r.variant.clone(),
                r.norm.clone(),
                r.samples.to_string(),
                r.seeds.to_string(),
                r.calib_frame.clone(),
                r.eval_frames.to_string(),
            ];
            row.extend(stats(&r.per_image));
            row.extend(stats(&r.pooled));
            row.push(format!("{:.9}", r.fit_time_median_s));
            row.push(r.protocol.to_string());
            row
        })
        .collect();
    Table {
        title: String::new(),
        headers,
        rows,
    }
    .to_csv()
}

/// The `--json` stdout contract: one array, one object per (set, method, norm).
///
/// # Errors
/// Serialisation failure (should not happen).
pub fn contract_json(results: &[EvalResult]) -> Result<String> {
    let rows: Vec<JsonRow> = results.iter().map(JsonRow::from).collect();
    to_json(&rows)
}

/// Pretty JSON of any serialisable value.
///
/// # Errors
/// Serialisation failure.
pub fn to_json<T: Serialize + ?Sized>(v: &T) -> Result<String> {
    serde_json::to_string_pretty(v).map_err(|e| EvalError::InvalidParameter(e.to_string()))
}

/// Writes `<dir>/<stem>.md`, `.csv` and `.json` for an evaluation; returns the paths.
///
/// # Errors
/// I/O failure.
pub fn write_eval_outputs(dir: &Path, stem: &str, results: &[EvalResult]) -> Result<Vec<PathBuf>> {
    write_eval_outputs_with_notes(dir, stem, results, &[])
}

/// [`write_eval_outputs`] with notes as rows of the Markdown tables (see
/// [`eval_table_with_notes`]); CSV and JSON hold the results only.
///
/// # Errors
/// I/O failure.
pub fn write_eval_outputs_with_notes(
    dir: &Path,
    stem: &str,
    results: &[EvalResult],
    notes: &[EvalNote],
) -> Result<Vec<PathBuf>> {
    let md = format!(
        "{}\n{}\n",
        eval_table_with_notes(results, notes, false).to_markdown(),
        eval_table_with_notes(results, notes, true).to_markdown()
    );
    let paths = vec![
        dir.join(format!("{stem}.md")),
        dir.join(format!("{stem}.csv")),
        dir.join(format!("{stem}.json")),
    ];
    write_text(&paths[0], &md)?;
    write_text(&paths[1], &eval_csv(results))?;
    write_text(&paths[2], &to_json(results)?)?;
    Ok(paths)
}

/// Writes a generic table as `<dir>/<stem>.md` and `.csv`, plus `json` (any serialisable detail).
///
/// # Errors
/// I/O failure.
pub fn write_table<T: Serialize + ?Sized>(
    dir: &Path,
    stem: &str,
    table: &Table,
    detail: &T,
) -> Result<Vec<PathBuf>> {
    let paths = vec![
        dir.join(format!("{stem}.md")),
        dir.join(format!("{stem}.csv")),
        dir.join(format!("{stem}.json")),
    ];
    write_text(&paths[0], &table.to_markdown())?;
    write_text(&paths[1], &table.to_csv())?;
    write_text(&paths[2], &to_json(detail)?)?;
    Ok(paths)
}
