//! The calibration file: a versioned JSON document holding a fitted [`Calibration`] and how it was made.

use std::collections::BTreeMap;
use std::path::Path;

use moma_core::normalise::NormalisationConfig;
use moma_core::pipeline::Calibration;
use moma_core::{ImageSize, Intrinsics, PredictionKind};
use serde::{Deserialize, Serialize};

use crate::atomic::{atomic_write, write_err};
use crate::error::{IoError, Result};

/// Value of the `format` field of every calibration file.
pub const CALIBRATION_FORMAT: &str = "moma-calibration";
/// The calibration-file version this build writes.
///
/// Versioning rule (docs/formats.md): the version changes whenever a field is added, removed or
/// changes meaning; this build writes only the newest version and reads every older one by
/// migrating it in memory (never silently: a version it cannot represent is an error that says
/// why). Version history: 1 — normalisation `{method, inverse_space}`, workspace as a file path;
/// 2 — normalisation `{method, space}`, the workspace mask embedded (run lengths + SHA-256),
/// unknown fields refused; 3 — optional additions: the fit report's `robust` block (with its
/// optional `auto` scale record, added within version 3: files without it read unchanged), the
/// `anchors` store for per-frame re-alignment, samples from several frames (few-shot), the
/// local variants' cross-validation settings (a version-2 file reads unchanged); within version 3,
/// `created.simulated_predictions` (written only when true: builds older than it refuse such a
/// file as an unknown field); 4 — the optional `error_model` of the aligned depth (a version-2 or
/// version-3 file reads unchanged, without one); 5 — `prediction_kind` is one of
/// `metric-depth`, `relative-depth`, `relative-disparity` (versions 1–4 wrote `depth` or
/// `inverse-depth`: `inverse-depth` reads as `relative-disparity`, `depth` as `metric-depth` for
/// method `raw`, which used the prediction as metres, else as `relative-depth`, which still
/// aligns a metric model's predictions, [`PredictionKind::accepts`]); 6 — the error model's
/// `relief_max_m`, the relief range its factor is fitted on and applied to (a version-5 file
/// reads with 0.1 m, the range every earlier build used); 7 — the error model's
/// `sigma_dense_m`, the calibration frames' own part of its flat σ (a version-6 file reads
/// without it: its `sigma_flat_m` stands in); 8 — the error model's `height_sigma`, the σ of a
/// per-frame relative error of heights above the support plane (written only when non-zero; a
/// version-7 file reads without it: no height part); 9 — the error model's
/// `sample_distance_gain`, the growth of its flat σ with the distance to the nearest
/// calibration sample (written only when non-zero; a version-8 file reads without it: no
/// distance part).
pub const CALIBRATION_VERSION: u32 = 9;

/// The oldest calibration-file version this build reads (migrated on reading).
pub const OLDEST_CALIBRATION_VERSION: u32 = 1;

/// How and when a calibration file was made.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreationInfo {
    /// Version of moma that wrote the file.
    pub moma_version: String,
    /// Creation time, seconds since the Unix epoch (UTC).
    pub created_unix_s: u64,
    /// The command line that produced it (program name first); empty when not from a command.
    #[serde(default)]
    pub command_line: Vec<String>,
    /// Input files by role, e.g. `"prediction"`, `"ground_truth"`, `"camera"`, `"mask"`.
    #[serde(default)]
    pub sources: BTreeMap<String, String>,
    /// `true` when the calibration was fitted on SIMULATED predictions (the `predictions.json`
    /// beside them said so): its parameters are not a depth model's, and every depth it aligns
    /// is labelled simulated. Absent (false) otherwise.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub simulated_predictions: bool,
}

impl CreationInfo {
    /// This moma's version, the current time and this process's command line; no sources.
    pub fn now() -> Self {
        Self {
            moma_version: env!("CARGO_PKG_VERSION").to_string(),
            created_unix_s: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_secs())
                .unwrap_or(0),
            command_line: std::env::args().collect(),
            sources: BTreeMap::new(),
            simulated_predictions: false,
        }
    }

    /// Adds an input file under `role`.
    pub fn with_source(mut self, role: impl Into<String>, path: impl AsRef<Path>) -> Self {
        self.sources
            .insert(role.into(), path.as_ref().display().to_string());
        self
    }
}

/// The content of a calibration file (JSON, see `docs/formats.md`).
///
/// `method`, `normalisation`, `prediction_kind` and `image_size` repeat what `calibration`
/// holds, at the top level for people and scripts; [`read_calibration`] rejects a file where
/// they disagree. The workspace mask (if any) is embedded in `calibration.workspace`, so the file
/// is self-contained and can be copied anywhere.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationFile {
    /// Always [`CALIBRATION_FORMAT`].
    pub format: String,
    /// Always [`CALIBRATION_VERSION`].
    pub version: u32,
    /// Alignment method (`ssra`, `gssa`, `lwlr`, `raw`, …), from the fit report.
    pub method: moma_core::align::MethodName,
    /// Normalisation applied before alignment (at calibration and at run time).
    pub normalisation: NormalisationConfig,
    /// Kind of prediction the calibration expects.
    pub prediction_kind: PredictionKind,
    /// The fitted calibration: model parameters, fit report and the samples used, and its
    /// anchor store (`anchors`, base64: [`crate::anchors`]).
    #[serde(with = "crate::anchors::calibration_json")]
    pub calibration: Calibration,
    /// Camera intrinsics (pixels), when known.
    pub intrinsics: Option<Intrinsics>,
    /// Size of the calibration image, pixels; run-time predictions must match.
    pub image_size: ImageSize,
    /// Provenance.
    pub created: CreationInfo,
}

impl CalibrationFile {
    /// Wraps a fitted calibration, filling the summary fields from it.
    pub fn new(
        calibration: Calibration,
        intrinsics: Option<Intrinsics>,
        created: CreationInfo,
    ) -> Self {
        Self {
            format: CALIBRATION_FORMAT.to_string(),
            version: CALIBRATION_VERSION,
            method: calibration.report.method,
            normalisation: calibration.normalisation,
            prediction_kind: calibration.prediction_kind,
            image_size: calibration.samples.image_size,
            calibration,
            intrinsics,
            created,
        }
    }

    /// Checks the header and that the summary fields agree with `calibration`.
    fn check(&self, path: &Path) -> Result<()> {
        if self.format != CALIBRATION_FORMAT || self.version != CALIBRATION_VERSION {
            return Err(IoError::CalibrationVersion {
                path: path.to_path_buf(),
                format: self.format.clone(),
                version: self.version.to_string(),
                supported: CALIBRATION_VERSION,
            });
        }
        let c = &self.calibration;
        c.validate().map_err(|e| IoError::core(path, e))?;
        let disagree = |field: &str, top: String, inner: String| {
            Err(IoError::invalid(
                path,
                format!(
                    "calibration file is inconsistent: '{field}' is {top} but the calibration holds {inner}"
                ),
            ))
        };
        if self.method != c.report.method {
            return disagree(
                "method",
                self.method.to_string(),
                c.report.method.to_string(),
            );
        }
        if self.normalisation != c.normalisation {
            return disagree(
                "normalisation",
                format!("{:?}", self.normalisation),
                format!("{:?}", c.normalisation),
            );
        }
        if self.prediction_kind != c.prediction_kind {
            return disagree(
                "prediction_kind",
                self.prediction_kind.to_string(),
                c.prediction_kind.to_string(),
            );
        }
        if self.image_size != c.samples.image_size {
            return disagree(
                "image_size",
                self.image_size.to_string(),
                c.samples.image_size.to_string(),
            );
        }
        if let Some(k) = &self.intrinsics {
            k.validate().map_err(|e| IoError::core(path, e))?;
            if k.size() != self.image_size {
                return disagree(
                    "intrinsics size",
                    k.size().to_string(),
                    self.image_size.to_string(),
                );
            }
        }
        Ok(())
    }
}

/// Just the header, parsed first so that another version's schema gives a version error.
#[derive(Deserialize)]
struct Header {
    format: Option<serde_json::Value>,
    version: Option<serde_json::Value>,
}

fn describe(v: &Option<serde_json::Value>) -> String {
    match v {
        None => "<missing>".to_string(),
        Some(serde_json::Value::String(s)) => s.clone(),
        Some(other) => other.to_string(),
    }
}

/// Reads and checks a calibration file (any version from [`OLDEST_CALIBRATION_VERSION`] to
/// [`CALIBRATION_VERSION`]; older versions are migrated in memory).
///
/// # Errors
/// [`IoError::Json`] with line and column for invalid or truncated JSON, a schema error or an
/// unknown field; [`IoError::CalibrationVersion`] naming the format and version found when the
/// file is not a `moma-calibration` this build reads; [`IoError::Invalid`] when the summary
/// fields disagree with the calibration or a version-1 file cannot be migrated;
/// [`IoError::Core`] when the model fails validation (non-finite parameters, bandwidth ≤ 0,
/// inconsistent SSRA parameters, a corrupt workspace); [`IoError::Io`] when unreadable.
pub fn read_calibration(path: impl AsRef<Path>) -> Result<CalibrationFile> {
    let path = path.as_ref();
    let text = crate::json_files::read_json_text(path, "calibration file")?;
    parse_calibration(path, &text)
}

/// [`read_calibration`] on text already in memory; `path` only names the source in errors.
///
/// # Errors
/// As [`read_calibration`].
pub fn parse_calibration(path: &Path, text: &str) -> Result<CalibrationFile> {
    let header: Header = serde_json::from_str(text).map_err(|e| IoError::json(path, &e))?;
    let format_ok =
        matches!(&header.format, Some(serde_json::Value::String(s)) if s == CALIBRATION_FORMAT);
    let version = header
        .version
        .as_ref()
        .and_then(serde_json::Value::as_u64)
        .filter(|v| {
            (u64::from(OLDEST_CALIBRATION_VERSION)..=u64::from(CALIBRATION_VERSION)).contains(v)
        });
    let version_error = || IoError::CalibrationVersion {
        path: path.to_path_buf(),
        format: describe(&header.format),
        version: match &header.version {
            // "9" would read as the supported 9: say it is text
            Some(serde_json::Value::String(s)) => format!("\"{s}\" (text, not a number)"),
            other => describe(other),
        },
        supported: CALIBRATION_VERSION,
    };
    if !format_ok {
        return Err(version_error());
    }
    let file: CalibrationFile = match version {
        // Versions 3, 4, 6, 7, 8 and 9 only added optional fields (6: the error model's
        // `relief_max_m`, which reads as 0.1 m without it; 7: its `sigma_dense_m`; 8: its
        // `height_sigma`, 0 without it; 9: its `sample_distance_gain`, 0 without it), and
        // version 5 renamed the kinds (the old names still parse): a version-2 to -8 document
        // is a version-9 one, once a version-2 to -4 one's kind is mapped.
        Some(v @ 2..=9) => {
            let mut file: CalibrationFile =
                serde_json::from_str(text).map_err(|e| IoError::json(path, &e))?;
            file.version = CALIBRATION_VERSION;
            if v < 5 {
                migrate_kind(&mut file);
            }
            file
        }
        Some(1) => {
            let mut file = migrate_v1(path, text)?;
            migrate_kind(&mut file);
            file
        }
        _ => return Err(version_error()),
    };
    file.check(path)?;
    Ok(file)
}

/// Versions 1–4 → 5: an old `depth` was parsed as `relative-depth`; a `raw` calibration used
/// the prediction as metres, so its predictions were a metric model's: `metric-depth`.
fn migrate_kind(file: &mut CalibrationFile) {
    if file.calibration.model == moma_core::align::AlignmentModel::Raw
        && file.calibration.prediction_kind == PredictionKind::RelativeDepth
    {
        file.calibration.prediction_kind = PredictionKind::MetricDepth;
        if file.prediction_kind == PredictionKind::RelativeDepth {
            file.prediction_kind = PredictionKind::MetricDepth;
        }
    }
}

/// Version 1 → 2: the normalisation gains its space (version 1 aligned in depth space unless
/// `inverse_space`, a mode version 2 dropped), and a workspace given as a file path is read and
/// embedded (a relative path is taken relative to the calibration file's folder).
fn migrate_v1(path: &Path, text: &str) -> Result<CalibrationFile> {
    let mut v: serde_json::Value =
        serde_json::from_str(text).map_err(|e| IoError::json(path, &e))?;
    let invalid = |msg: String| IoError::invalid(path, format!("version-1 calibration: {msg}"));
    let obj = v
        .as_object_mut()
        .ok_or_else(|| invalid("not a JSON object".into()))?;
    let migrate_norm = |n: &mut serde_json::Value| -> Result<()> {
        let n = n
            .as_object_mut()
            .ok_or_else(|| invalid("'normalisation' is not an object".into()))?;
        let inverse = n.remove("inverse_space");
        if inverse.as_ref().and_then(serde_json::Value::as_bool) == Some(true) {
            return Err(invalid(
                "it was fitted with --inverse-space (disparity as predictor, depth as target), \
                 a mode this version replaced by --space inverse (disparity predictor and \
                 inverse-depth target); run `moma calibrate` again"
                    .into(),
            ));
        }
        n.insert("space".into(), serde_json::Value::String("depth".into()));
        Ok(())
    };
    if let Some(n) = obj.get_mut("normalisation") {
        migrate_norm(n)?;
    }
    if let Some(n) = obj
        .get_mut("calibration")
        .and_then(|c| c.get_mut("normalisation"))
    {
        migrate_norm(n)?;
    }
    let workspace = obj.remove("workspace_mask");
    obj.insert(
        "version".into(),
        serde_json::Value::from(CALIBRATION_VERSION),
    );
    let mut file: CalibrationFile =
        serde_json::from_value(v).map_err(|e| invalid(format!("cannot migrate: {e}")))?;
    if let Some(serde_json::Value::String(mask_path)) = workspace {
        let mut mask_file = std::path::PathBuf::from(&mask_path);
        if mask_file.is_relative()
            && let Some(dir) = path.parent()
        {
            mask_file = dir.join(mask_file);
        }
        let mask = crate::raster::read_mask_sized(&mask_file, file.image_size).map_err(|e| {
            invalid(format!(
                "it names the workspace mask {mask_path}, which version 2 embeds, but it cannot \
                 be read: {e}"
            ))
        })?;
        let ws = moma_core::Workspace::new(mask).map_err(|e| IoError::core(path, e))?;
        file.calibration.workspace = Some(std::sync::Arc::new(ws));
    }
    // Version 1 named every LWLR variant "lwlr"; names now follow the preset.
    let name = moma_core::align::MethodName::from(&file.calibration.model);
    file.calibration.report.method = name;
    file.method = name;
    Ok(file)
}

/// Writes a calibration file atomically (pretty-printed JSON).
///
/// The JSON is parsed back before writing, so a file that [`read_calibration`] could not read
/// (e.g. a NaN or infinite parameter, which JSON cannot represent) is never written.
///
/// # Errors
/// [`IoError::CalibrationVersion`] / [`IoError::Invalid`] for a header or summary fields that
/// [`read_calibration`] would reject; [`IoError::Invalid`] for non-finite numbers; destination
/// not writable.
pub fn write_calibration(path: impl AsRef<Path>, file: &CalibrationFile) -> Result<()> {
    let path = path.as_ref();
    file.check(path)?;
    let mut text = serde_json::to_string_pretty(file)
        .map_err(|e| IoError::invalid(path, format!("cannot encode calibration as JSON: {e}")))?;
    text.push('\n');
    if let Err(e) = serde_json::from_str::<CalibrationFile>(&text) {
        return Err(IoError::invalid(
            path,
            format!(
                "calibration cannot be stored as JSON (a NaN or infinite number?): it would not read back: {e}"
            ),
        ));
    }
    atomic_write(path, |w| {
        w.write_all(text.as_bytes()).map_err(write_err(path))
    })
}
