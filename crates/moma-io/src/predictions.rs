//! `predictions.json`: the index a prediction folder carries beside its `<name>.npy` maps.
//!
//! Written by `moma predict` (a depth model's output) and `moma simulate` (simulated output);
//! read by every command that takes predictions, so that the prediction kind is never guessed and
//! a simulated prediction is always labelled as such.
//!
//! ```json
//! {"format": "moma-predictions", "prediction_kind": "inverse-depth", "simulated": true,
//!  "source": "SIMULATED ...", ...tool-specific fields (model, weights, runtime, frames, simulator)}
//! ```

use std::path::{Path, PathBuf};

use moma_core::PredictionKind;
use serde::{Deserialize, Serialize};

use crate::error::{IoError, Result};

/// File name of the index in a prediction folder.
pub const PREDICTIONS_INDEX_FILE: &str = "predictions.json";
/// Value of its `format` field.
pub const PREDICTIONS_FORMAT: &str = "moma-predictions";
/// The index written by moma versions before `predictions.json` was shared with `moma simulate`.
const LEGACY_SIMULATED_FILE: &str = "simulated.json";

/// What every prediction index says (other fields are the writing tool's own).
#[derive(Debug, Clone, PartialEq)]
pub struct PredictionIndex {
    /// The file it was read from.
    pub path: PathBuf,
    /// Kind of the maps.
    pub kind: PredictionKind,
    /// `true` for simulated predictions (not a depth model's output).
    pub simulated: bool,
    /// Where the maps come from, for labels (model and weights, or the simulator).
    pub source: String,
}

#[derive(Deserialize)]
struct IndexHead {
    format: String,
    prediction_kind: PredictionKind,
    #[serde(default)]
    simulated: bool,
    #[serde(default)]
    source: Option<String>,
    #[serde(default)]
    model: Option<serde_json::Value>,
}

#[derive(Deserialize)]
struct LegacySimulated {
    kind: PredictionKind,
    label: String,
}

/// The common fields a writer puts at the top of `predictions.json` (flatten it into the
/// writer's own record).
#[derive(Debug, Clone, Serialize)]
pub struct PredictionIndexHead {
    /// Always [`PREDICTIONS_FORMAT`].
    pub format: &'static str,
    /// Kind of the maps.
    pub prediction_kind: PredictionKind,
    /// `true` for simulated predictions.
    pub simulated: bool,
    /// Label of the source.
    pub source: String,
}

impl PredictionIndexHead {
    /// The head for maps of `kind` from `source`.
    pub fn new(
        prediction_kind: PredictionKind,
        simulated: bool,
        source: impl Into<String>,
    ) -> Self {
        Self {
            format: PREDICTIONS_FORMAT,
            prediction_kind,
            simulated,
            source: source.into(),
        }
    }
}

/// Reads the index of the prediction folder `dir`: `predictions.json`, else a legacy
/// `simulated.json`; `Ok(None)` when the folder has neither.
///
/// # Errors
/// [`IoError::Json`] / [`IoError::Invalid`] for an index that exists but cannot be read as one
/// (a corrupt index is never ignored).
pub fn read_prediction_index(dir: &Path) -> Result<Option<PredictionIndex>> {
    let path = dir.join(PREDICTIONS_INDEX_FILE);
    if path.is_file() {
        let text = std::fs::read_to_string(&path).map_err(|e| IoError::io(&path, "read", e))?;
        let head: IndexHead = serde_json::from_str(&text).map_err(|e| IoError::json(&path, &e))?;
        if head.format != PREDICTIONS_FORMAT {
            return Err(IoError::invalid(
                &path,
                format!(
                    "format is '{}', expected '{PREDICTIONS_FORMAT}'",
                    head.format
                ),
            ));
        }
        let source = head
            .source
            .or_else(|| head.model.map(|m| format!("depth model {m}")))
            .unwrap_or_else(|| format!("{} predictions", head.prediction_kind));
        return Ok(Some(PredictionIndex {
            path,
            kind: head.prediction_kind,
            simulated: head.simulated,
            source,
        }));
    }
    let legacy = dir.join(LEGACY_SIMULATED_FILE);
    if legacy.is_file() {
        let text = std::fs::read_to_string(&legacy).map_err(|e| IoError::io(&legacy, "read", e))?;
        let meta: LegacySimulated =
            serde_json::from_str(&text).map_err(|e| IoError::json(&legacy, &e))?;
        return Ok(Some(PredictionIndex {
            path: legacy,
            kind: meta.kind,
            simulated: true,
            source: meta.label,
        }));
    }
    Ok(None)
}

/// The index of the folder holding the prediction file `file` (see [`read_prediction_index`]).
///
/// # Errors
/// As [`read_prediction_index`].
pub fn read_prediction_index_for(file: &Path) -> Result<Option<PredictionIndex>> {
    let dir = match file.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    read_prediction_index(dir)
}

/// The prediction kind from every source that states one, which must agree; at least one must.
///
/// `sources` are `(what, kind)` pairs, e.g. `("--pred-kind", Some(k))`,
/// `("predictions.json", …)`, `("the calibration file", …)`, `("the model's head", …)`.
///
/// # Errors
/// A message for the user: none stated (the kind is never guessed), or two that disagree.
pub fn resolve_prediction_kind(
    sources: &[(&str, Option<PredictionKind>)],
) -> std::result::Result<PredictionKind, String> {
    let stated: Vec<(&str, PredictionKind)> = sources
        .iter()
        .filter_map(|(w, k)| k.map(|k| (*w, k)))
        .collect();
    let Some(&(first_what, first)) = stated.first() else {
        return Err(
            "the prediction kind is unknown: pass --pred-kind depth|inverse-depth (relative \
             Depth Anything heads output inverse-depth, metric heads depth), or keep the \
             predictions.json that `moma predict`/`moma simulate` wrote beside the predictions"
                .into(),
        );
    };
    for &(what, k) in &stated[1..] {
        if k != first {
            return Err(format!(
                "prediction kind mismatch: {first_what} says '{first}' but {what} says '{k}'"
            ));
        }
    }
    Ok(first)
}
