//! `predictions.json`: the index a prediction folder carries beside its `<name>.npy` maps.
//!
//! Written by `moma predict` (a depth model's output) and `moma simulate` (simulated output);
//! read by every command that takes predictions, so that the prediction kind is never guessed and
//! a simulated prediction is always labelled as such.
//!
//! ```json
//! {"format": "moma-predictions", "prediction_kind": "relative-disparity", "simulated": true,
//!  "source": "SIMULATED ...", ...tool-specific fields (model, weights, runtime, frames, simulator)}
//! ```
//!
//! `prediction_kind` is `metric-depth`, `relative-depth` or `relative-disparity`. Indexes written
//! before these names existed are read with the mapping of docs/formats.md ("Prediction kinds"):
//! `inverse-depth` is `relative-disparity`; `depth` is `metric-depth` where the writer recorded a
//! metric model (a metric head, a simulation of one, or a source that says "metric depth"), else
//! `relative-depth`.

use std::path::{Path, PathBuf};

use moma_core::PredictionKind;
use serde::{Deserialize, Serialize};

use crate::error::{IoError, Result};

/// File name of the index in a prediction folder.
pub const PREDICTIONS_INDEX_FILE: &str = "predictions.json";
/// Value of its `format` field.
pub const PREDICTIONS_FORMAT: &str = "moma-predictions";
/// Value of its `version` field as this build writes it: 1 (no `version` field) named the kinds
/// `depth` / `inverse-depth`; 2 names the three kinds `metric-depth`, `relative-depth`,
/// `relative-disparity`. Both are read; a newer version is refused.
pub const PREDICTIONS_VERSION: u32 = 2;
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
    /// The names of the maps it lists (`<name>.npy` beside it): the `frames` field, as names or
    /// records with a `name`; empty when absent (legacy indexes).
    pub frames: Vec<String>,
}

impl PredictionIndex {
    /// Whether it lists the map named `name` (a file stem, e.g. `frame_00`): an entry may be the
    /// name, the map's file or a path to it. A legacy index (no `frames`) lists nothing.
    pub fn lists(&self, name: &str) -> bool {
        self.frames.iter().any(|n| {
            n == name
                || Path::new(n)
                    .file_stem()
                    .is_some_and(|s| s.to_string_lossy() == name)
        })
    }

    /// Whether it lists maps (`frames`), but not `file` (by its stem): a map beside it that the
    /// run it describes did not write, whose kind it does not tell. A legacy index (no
    /// `frames`) disowns nothing.
    pub fn disowns(&self, file: &Path) -> bool {
        !self.frames.is_empty()
            && !file
                .file_stem()
                .is_some_and(|s| self.lists(&s.to_string_lossy()))
    }
}

#[derive(Deserialize)]
struct IndexHead {
    format: String,
    /// Absent in version 1.
    #[serde(default)]
    version: Option<u64>,
    /// A name, new or old: mapped by [`legacy_depth_kind`].
    prediction_kind: String,
    #[serde(default)]
    simulated: bool,
    #[serde(default)]
    source: Option<String>,
    #[serde(default)]
    model: Option<serde_json::Value>,
    /// The writer's own list: `moma simulate` writes names, `moma predict` records with a
    /// `name`; read leniently (other entries are skipped, another type lists nothing), since
    /// third-party indexes may hold anything here.
    #[serde(default)]
    frames: serde_json::Value,
}

#[derive(Deserialize)]
struct LegacySimulated {
    kind: String,
    label: String,
}

/// What an old index's kind `depth` means, from what its writer recorded: `metric-depth` when
/// - `model` records a metric head (`moma predict` writes the model's spec, with
///   `"head": "metric"`), or
/// - it is simulated (`moma simulate`'s `depth` was always g·z: metres with a scale error, the
///   simulation of a metric head), or
/// - `source` says "metric depth" (an index written by hand for a metric model's output, such as
///   ../shared/data/zed-da3-office's, whose README says the maps are metres);
///
/// else `relative-depth`, the kind that claims no unit.
fn legacy_depth_kind(
    model: Option<&serde_json::Value>,
    simulated: bool,
    source: Option<&str>,
) -> PredictionKind {
    let metric_head = model.is_some_and(|m| {
        let head = &m["head"];
        head.as_str() == Some("metric") || head["head"].as_str() == Some("metric")
    });
    let says_metric = source.is_some_and(says_metric_depth);
    if metric_head || simulated || says_metric {
        PredictionKind::MetricDepth
    } else {
        PredictionKind::RelativeDepth
    }
}

/// Whether a hand-written `source` says its maps are metric depth: the words "metric depth"
/// (whole words: not "geometric depth") that no negation before them undoes — "not", "no",
/// "non" ("non-metric"), "without", "nor", "never", "isn't", "aren't", an article between them
/// and the negation allowed ("not a metric depth model").
fn says_metric_depth(source: &str) -> bool {
    let text = source.to_ascii_lowercase();
    let words: Vec<&str> = text
        .split(|c: char| !(c.is_ascii_alphanumeric() || c == '\''))
        .filter(|w| !w.is_empty())
        .collect();
    let negation = |w: &str| {
        matches!(
            w,
            "not" | "no" | "non" | "without" | "nor" | "never" | "isn't" | "aren't"
        )
    };
    words.windows(2).enumerate().any(|(i, pair)| {
        if pair != ["metric", "depth"] {
            return false;
        }
        let mut before = words[..i].iter().rev();
        let negated = match before.next() {
            Some(&"a" | &"an" | &"the") => before.next().is_some_and(|w| negation(w)),
            Some(&w) => negation(w),
            None => false,
        };
        !negated
    })
}

/// The common fields a writer puts at the top of `predictions.json` (flatten it into the
/// writer's own record).
#[derive(Debug, Clone, Serialize)]
pub struct PredictionIndexHead {
    /// Always [`PREDICTIONS_FORMAT`].
    pub format: &'static str,
    /// Always [`PREDICTIONS_VERSION`].
    pub version: u32,
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
            version: PREDICTIONS_VERSION,
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
        let text = crate::json_files::read_json_text(&path, "predictions index")?;
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
        if let Some(v) = head
            .version
            .filter(|v| !(1..=u64::from(PREDICTIONS_VERSION)).contains(v))
        {
            return Err(IoError::invalid(
                &path,
                format!(
                    "version {v}: this moma reads prediction indexes of versions 1 to \
                     {PREDICTIONS_VERSION} (a newer moma wrote it?)"
                ),
            ));
        }
        let legacy = legacy_depth_kind(head.model.as_ref(), head.simulated, head.source.as_deref());
        let kind = PredictionKind::from_name(&head.prediction_kind, legacy)
            .map_err(|e| IoError::invalid(&path, format!("prediction_kind: {e}")))?;
        let source = head
            .source
            .or_else(|| head.model.map(|m| format!("depth model {m}")))
            .unwrap_or_else(|| format!("{kind} predictions"));
        return Ok(Some(PredictionIndex {
            path,
            kind,
            simulated: head.simulated,
            source,
            frames: head
                .frames
                .as_array()
                .map(|entries| {
                    entries
                        .iter()
                        .filter_map(|f| f.as_str().or_else(|| f["name"].as_str()))
                        .map(str::to_string)
                        .collect()
                })
                .unwrap_or_default(),
        }));
    }
    let legacy = dir.join(LEGACY_SIMULATED_FILE);
    if legacy.is_file() {
        let text = crate::json_files::read_json_text(&legacy, "predictions index")?;
        let meta: LegacySimulated =
            serde_json::from_str(&text).map_err(|e| IoError::json(&legacy, &e))?;
        let kind = PredictionKind::from_name(&meta.kind, PredictionKind::MetricDepth)
            .map_err(|e| IoError::invalid(&legacy, format!("kind: {e}")))?;
        return Ok(Some(PredictionIndex {
            path: legacy,
            kind,
            simulated: true,
            source: meta.label,
            frames: Vec::new(),
        }));
    }
    Ok(None)
}

/// The index of the folder holding the prediction file `file` (see [`read_prediction_index`]).
///
/// # Errors
/// As [`read_prediction_index`].
pub fn read_prediction_index_for(file: &Path) -> Result<Option<PredictionIndex>> {
    read_prediction_index(crate::atomic::folder_of(file))
}

/// The index that lists `file` as one of its raw predictions (`<name>.npy` beside a
/// `predictions.json` whose `frames` name it), else `None`. Commands that take metres use it to
/// refuse a depth model's raw output, which is not metres.
///
/// # Errors
/// As [`read_prediction_index`].
pub fn prediction_index_listing(file: &Path) -> Result<Option<PredictionIndex>> {
    let is_npy = file
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("npy"));
    let Some(stem) = file.file_stem().and_then(|s| s.to_str()) else {
        return Ok(None);
    };
    if !is_npy {
        return Ok(None);
    }
    Ok(read_prediction_index_for(file)?.filter(|i| i.lists(stem)))
}

/// The kind of the predictions from every source that states one, which must agree, checked
/// against the kind a calibration expects.
///
/// `sources` are `(what, kind)` pairs that describe the predictions, e.g.
/// `("--pred-kind", Some(k))`, `("predictions.json", …)`, `("the model's head", …)`; where none
/// states a kind, the calibration's (`(what, kind)`, e.g. `("the calibration file", k)`) is used.
/// A calibration accepts the kinds of [`PredictionKind::accepts`]: its own, and `metric-depth`
/// under a `relative-depth` calibration.
///
/// # Errors
/// A message for the user: no kind stated anywhere (the kind is never guessed), two sources that
/// disagree, or a kind the calibration does not accept.
pub fn resolve_prediction_kind(
    sources: &[(&str, Option<PredictionKind>)],
    calibration: Option<(&str, PredictionKind)>,
) -> std::result::Result<PredictionKind, String> {
    let stated: Vec<(&str, PredictionKind)> = sources
        .iter()
        .filter_map(|(w, k)| k.map(|k| (*w, k)))
        .collect();
    let Some(&(first_what, first)) = stated.first().or(calibration.as_ref()) else {
        return Err(format!(
            "the prediction kind is unknown: pass --pred-kind {} (Depth Anything's relative \
             heads output {}, metric heads {}), or keep the predictions.json that `moma \
             predict`/`moma simulate` wrote beside the predictions",
            PredictionKind::ALL.map(PredictionKind::name).join("|"),
            PredictionKind::RelativeDisparity,
            PredictionKind::MetricDepth
        ));
    };
    for &(what, k) in stated.iter().skip(1) {
        if k != first {
            return Err(format!(
                "prediction kind mismatch: {first_what} says '{first}' but {what} says '{k}'"
            ));
        }
    }
    if let Some((what, expected)) = calibration
        && !expected.accepts(first)
    {
        return Err(format!(
            "prediction kind mismatch: {first_what} says '{first}' but {what} says '{expected}'"
        ));
    }
    Ok(first)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `frames` as `moma simulate` writes it (names) and as `moma predict` does (records); only a
    /// listed `<name>.npy` is a prediction: the aligned `<name>.depth.npy` beside it is not.
    #[test]
    fn listing_finds_only_the_predictions_an_index_names() {
        let dir = tempfile::tempdir().unwrap();
        let index = |frames: &str| {
            std::fs::write(
                dir.path().join(PREDICTIONS_INDEX_FILE),
                format!(
                    r#"{{"format": "moma-predictions", "prediction_kind": "relative-disparity",
                        "simulated": true, "source": "SIMULATED", "frames": {frames}}}"#
                ),
            )
            .unwrap();
        };
        let file = |name: &str| dir.path().join(name);
        for frames in [
            r#"["f_01", "f_02"]"#,
            r#"[{"name": "f_01", "predict_ms": 3.0}]"#,
        ] {
            index(frames);
            let found = prediction_index_listing(&file("f_01.npy"))
                .unwrap()
                .unwrap();
            assert_eq!(found.kind, PredictionKind::RelativeDisparity);
            assert!(found.simulated && found.frames.contains(&"f_01".to_string()));
            assert!(
                prediction_index_listing(&file("f_01.depth.npy"))
                    .unwrap()
                    .is_none()
            );
            assert!(
                prediction_index_listing(&file("f_01.png"))
                    .unwrap()
                    .is_none()
            );
            assert!(
                prediction_index_listing(&file("other.npy"))
                    .unwrap()
                    .is_none()
            );
        }
        // an index without `frames` (older writers), or with entries of another form, lists
        // nothing and still reads
        std::fs::write(
            dir.path().join(PREDICTIONS_INDEX_FILE),
            r#"{"format": "moma-predictions", "prediction_kind": "depth"}"#,
        )
        .unwrap();
        assert!(
            prediction_index_listing(&file("f_01.npy"))
                .unwrap()
                .is_none()
        );
        for odd in ["[]", r#"[{"file": "f_01.npy"}, 3]"#, r#"{"f_01": 1}"#] {
            index(odd);
            assert!(
                prediction_index_listing(&file("f_01.npy"))
                    .unwrap()
                    .is_none()
            );
        }
        index(r#"[{"file": "x"}, "f_01"]"#);
        assert!(
            prediction_index_listing(&file("f_01.npy"))
                .unwrap()
                .is_some()
        );
        // a corrupt index is an error, not "no index"
        std::fs::write(dir.path().join(PREDICTIONS_INDEX_FILE), "{").unwrap();
        assert!(prediction_index_listing(&file("f_01.npy")).is_err());
        // no index at all
        let empty = tempfile::tempdir().unwrap();
        assert!(
            prediction_index_listing(&empty.path().join("f_01.npy"))
                .unwrap()
                .is_none()
        );
    }

    /// docs/formats.md "Prediction kinds": new names as they are; an old `inverse-depth` is
    /// `relative-disparity`; an old `depth` is `metric-depth` only where the writer recorded a
    /// metric model (a metric head in `model`, a simulation, a source saying "metric depth").
    #[test]
    fn old_kind_names_follow_what_the_writer_recorded() {
        let dir = tempfile::tempdir().unwrap();
        let kind_of = |fields: &str| {
            std::fs::write(
                dir.path().join(PREDICTIONS_INDEX_FILE),
                format!(r#"{{"format": "moma-predictions", {fields}}}"#),
            )
            .unwrap();
            read_prediction_index(dir.path()).map(|i| i.unwrap().kind)
        };
        use PredictionKind::*;
        let cases = [
            (r#""prediction_kind": "relative-depth""#, RelativeDepth),
            (r#""prediction_kind": "metric-depth""#, MetricDepth),
            (
                r#""prediction_kind": "relative-disparity""#,
                RelativeDisparity,
            ),
            (r#""prediction_kind": "inverse-depth""#, RelativeDisparity),
            (r#""prediction_kind": "depth""#, RelativeDepth),
            (
                r#""prediction_kind": "depth", "model": {"backbone": "vits", "head": {"head": "metric", "max_depth_m": 20.0}}"#,
                MetricDepth,
            ),
            (
                r#""prediction_kind": "depth", "model": {"backbone": "vits", "head": {"head": "relative"}}"#,
                RelativeDepth,
            ),
            (
                r#""prediction_kind": "depth", "simulated": true"#,
                MetricDepth,
            ),
            (
                r#""prediction_kind": "depth", "source": "DA3 metric, Metric depth in metres""#,
                MetricDepth,
            ),
            (
                r#""prediction_kind": "depth", "source": "MiDaS""#,
                RelativeDepth,
            ),
            (
                r#""prediction_kind": "depth", "source": "MiDaS: relative, not metric depth""#,
                RelativeDepth,
            ),
            (
                r#""prediction_kind": "depth", "source": "a non-metric depth model""#,
                RelativeDepth,
            ),
            (
                r#""prediction_kind": "depth", "source": "no metric depth here, but metric depth from DA3 in b/""#,
                MetricDepth,
            ),
            (
                r#""prediction_kind": "depth", "source": "geometric depth cues""#,
                RelativeDepth,
            ),
            (
                r#""prediction_kind": "depth", "source": "not a metric depth model""#,
                RelativeDepth,
            ),
            (
                r#""prediction_kind": "depth", "source": "relative, without metric depth""#,
                RelativeDepth,
            ),
        ];
        for (fields, want) in cases {
            assert_eq!(kind_of(fields).unwrap(), want, "{fields}");
        }
        assert_eq!(
            kind_of(r#""version": 2, "prediction_kind": "metric-depth""#).unwrap(),
            MetricDepth
        );
        let e = kind_of(r#""version": 3, "prediction_kind": "metric-depth""#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("version 3") && e.contains("1 to 2"), "{e}");
        let e = kind_of(r#""prediction_kind": "metres""#)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("predictions.json") && e.contains("metres") && e.contains("metric-depth"),
            "{e}"
        );
        // the legacy simulator label: its `depth` was metres × a scale error
        std::fs::remove_file(dir.path().join(PREDICTIONS_INDEX_FILE)).unwrap();
        std::fs::write(
            dir.path().join(LEGACY_SIMULATED_FILE),
            r#"{"kind": "depth", "label": "SIMULATED"}"#,
        )
        .unwrap();
        let legacy = read_prediction_index(dir.path()).unwrap().unwrap();
        assert_eq!((legacy.kind, legacy.simulated), (MetricDepth, true));
    }
}
