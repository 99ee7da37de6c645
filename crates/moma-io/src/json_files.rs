//! Small JSON files of a robot cell: the camera-to-base extrinsics and gripper settings (any
//! serde type), read with errors that name the file, written atomically.

use std::path::Path;

use serde::Serialize;
use serde::de::DeserializeOwned;

use crate::atomic::{atomic_write, write_err};
use crate::error::{IoError, Result};

/// Largest JSON settings file read, bytes: far above any extrinsics or gripper file; an absurd
/// file (a depth map passed by mistake) is refused before it is parsed.
pub const MAX_SETTINGS_JSON_BYTES: u64 = 1 << 20;

/// The text of a JSON file (`what` names it in errors): a file that is not UTF-8 text (an image
/// given where a camera.json belongs) is said to be so, not "stream did not contain valid
/// UTF-8".
///
/// # Errors
/// [`IoError::Io`] when unreadable; [`IoError::Invalid`] when not text.
pub(crate) fn read_json_text(path: &Path, what: &str) -> Result<String> {
    std::fs::read_to_string(path).map_err(|e| {
        if e.kind() == std::io::ErrorKind::InvalidData {
            IoError::invalid(
                path,
                format!("{what}: not a JSON text file (binary content, e.g. an image)"),
            )
        } else {
            IoError::io(path, "read", e)
        }
    })
}

/// Reads a JSON file into `T` (`what` names it in errors, e.g. "gripper config").
///
/// # Errors
/// [`IoError::Io`] when unreadable; [`IoError::Invalid`] when larger than
/// [`MAX_SETTINGS_JSON_BYTES`]; [`IoError::Json`] (line and column) when not valid JSON of `T`.
pub fn read_json<T: DeserializeOwned>(path: impl AsRef<Path>, what: &str) -> Result<T> {
    let path = path.as_ref();
    let len = std::fs::metadata(path)
        .map_err(|e| IoError::io(path, "read", e))?
        .len();
    if len > MAX_SETTINGS_JSON_BYTES {
        return Err(IoError::invalid(
            path,
            format!(
                "{what}: {len} bytes is not a settings file (at most {MAX_SETTINGS_JSON_BYTES})"
            ),
        ));
    }
    let text = read_json_text(path, what)?;
    parse_json(path, &text)
}

/// [`read_json`] on text already in memory; `path` names it in errors.
///
/// # Errors
/// [`IoError::Json`] when not valid JSON of `T`.
pub fn parse_json<T: DeserializeOwned>(path: &Path, text: &str) -> Result<T> {
    serde_json::from_str(text).map_err(|e| IoError::json(path, &e))
}

/// Writes `value` as pretty JSON with a final newline, atomically.
///
/// # Errors
/// [`IoError::Invalid`] when it cannot be encoded; destination not writable.
pub fn write_json<T: Serialize>(path: impl AsRef<Path>, value: &T) -> Result<()> {
    let path = path.as_ref();
    let mut bytes = serde_json::to_vec_pretty(value)
        .map_err(|e| IoError::invalid(path, format!("cannot encode as JSON: {e}")))?;
    bytes.push(b'\n');
    atomic_write(path, |w| w.write_all(&bytes).map_err(write_err(path)))
}

/// The extrinsics file: `{"camera_to_base": [[r00,r01,r02,tx],…,[0,0,0,1]]}` (rows; metres).
#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ExtrinsicsFile {
    /// The camera-to-base transform, rows: `p_base = R p_camera + t`.
    pub camera_to_base: [[f64; 4]; 4],
}

/// Reads an extrinsics file (the matrix only; `moma_grasp::Extrinsics::new` checks rigidity).
///
/// # Errors
/// As [`read_json`]; unknown fields are an error.
pub fn read_extrinsics(path: impl AsRef<Path>) -> Result<[[f64; 4]; 4]> {
    Ok(read_json::<ExtrinsicsFile>(path, "extrinsics file")?.camera_to_base)
}

/// Writes an extrinsics file atomically.
///
/// # Errors
/// A non-finite entry ([`IoError::Invalid`]); destination not writable.
pub fn write_extrinsics(path: impl AsRef<Path>, camera_to_base: &[[f64; 4]; 4]) -> Result<()> {
    let path = path.as_ref();
    if camera_to_base.iter().flatten().any(|v| !v.is_finite()) {
        return Err(IoError::invalid(path, "extrinsics with a non-finite entry"));
    }
    write_json(
        path,
        &ExtrinsicsFile {
            camera_to_base: *camera_to_base,
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn extrinsics_round_trip_and_bad_files_name_themselves() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.json");
        let m = [
            [0.0, -1.0, 0.0, 0.4],
            [-1.0, 0.0, 0.0, 0.1],
            [0.0, 0.0, -1.0, 0.9],
            [0.0, 0.0, 0.0, 1.0],
        ];
        write_extrinsics(&p, &m).unwrap();
        assert_eq!(read_extrinsics(&p).unwrap(), m);
        std::fs::write(&p, r#"{"camera_to_base": [[1,0,0]], "x": 1}"#).unwrap();
        let e = read_extrinsics(&p).unwrap_err().to_string();
        assert!(e.contains("x.json"), "{e}");
        let mut bad = m;
        bad[0][3] = f64::NAN;
        assert!(write_extrinsics(&p, &bad).is_err());
        std::fs::write(&p, vec![b' '; (MAX_SETTINGS_JSON_BYTES + 1) as usize]).unwrap();
        let e = read_extrinsics(&p).unwrap_err().to_string();
        assert!(e.contains("not a settings file"), "{e}");
    }
}
