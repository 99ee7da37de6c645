//! The file form of a calibration's anchor store (`calibration.anchors` in a calibration file):
//! the arrays of [`moma_core::realign::AnchorStore`] as standard base64 (RFC 4648, with padding,
//! through the `base64` crate), little-endian, row-major at half resolution.
//!
//! ```json
//! "anchors": { "width": 640, "height": 480, "grey_b64": "…", "depth_mm_b64": "…",
//!              "one_shot_mm_b64": "…", "normalised_b64": "…" }
//! ```
//!
//! `one_shot_mm_b64` and `normalised_b64` are optional (stores written before they existed).

use base64::Engine as _;
use moma_core::ImageSize;
use moma_core::realign::AnchorStore;
use ndarray::{Array2, ArrayView2};
use serde::{Deserialize, Serialize};

/// The serialised form of an [`AnchorStore`].
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct AnchorStoreFile {
    /// Full-resolution width, pixels.
    width: usize,
    /// Full-resolution height, pixels.
    height: usize,
    /// Grey at half resolution, (height/2)×(width/2) bytes row-major, base64.
    grey_b64: String,
    /// Depth in mm at half resolution, u16 little-endian row-major, base64.
    depth_mm_b64: String,
    /// The calibration's own one-shot result on the calibration frame at the same pixels, mm,
    /// u16 little-endian, base64 (absent: only the ground-truth target is available).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    one_shot_mm_b64: Option<String>,
    /// The calibration's normalised prediction ẑ on the calibration frame at the same pixels,
    /// f32 little-endian, base64 (NaN where none; absent in stores written before the
    /// `prediction-affine` correction).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    normalised_b64: Option<String>,
}

fn b64_encode(data: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(data)
}

/// Standard base64 with padding; refuses non-canonical input (a length not a multiple of 4,
/// misplaced padding, other characters).
fn b64_decode(s: &str) -> Result<Vec<u8>, String> {
    base64::engine::general_purpose::STANDARD
        .decode(s)
        .map_err(|e| e.to_string())
}

fn u16_bytes(a: ArrayView2<'_, u16>) -> Vec<u8> {
    a.iter().flat_map(|d| d.to_le_bytes()).collect()
}

impl From<&AnchorStore> for AnchorStoreFile {
    fn from(s: &AnchorStore) -> Self {
        let size = s.image_size();
        Self {
            width: size.width,
            height: size.height,
            grey_b64: b64_encode(&s.grey().iter().copied().collect::<Vec<u8>>()),
            depth_mm_b64: b64_encode(&u16_bytes(s.depth_mm())),
            one_shot_mm_b64: s.one_shot_mm().map(|a| b64_encode(&u16_bytes(a))),
            normalised_b64: s
                .normalised()
                .map(|a| b64_encode(&a.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>())),
        }
    }
}

impl AnchorStoreFile {
    /// Decodes the arrays (each of `N` bytes per half-resolution pixel) and checks the store.
    ///
    /// # Errors
    /// A message naming the field: bad base64, a byte count that does not match the size,
    /// or what [`AnchorStore::from_parts`] refuses.
    pub(crate) fn decode(self) -> Result<AnchorStore, String> {
        let size = ImageSize::new(self.width, self.height);
        if !size.is_within_limits() {
            return Err(format!("anchor store size {size} is too large or empty"));
        }
        let (hh, hw) = (size.height / 2, size.width / 2);
        let bytes = |field: &str, text: &str, per_px: usize| -> Result<Vec<u8>, String> {
            let b = b64_decode(text).map_err(|e| format!("anchor store {field}: {e}"))?;
            if b.len() != per_px * hh * hw {
                return Err(format!(
                    "anchor store {field} holds {} bytes, expected {} ({hw}x{hh}, {per_px} per pixel)",
                    b.len(),
                    per_px * hh * hw
                ));
            }
            Ok(b)
        };
        let array = |v| Array2::from_shape_vec((hh, hw), v).map_err(|e| e.to_string());
        let u16s = |field: &str, text: &str| -> Result<Array2<u16>, String> {
            let b = bytes(field, text, 2)?;
            Array2::from_shape_vec(
                (hh, hw),
                b.chunks_exact(2)
                    .map(|c| u16::from_le_bytes([c[0], c[1]]))
                    .collect(),
            )
            .map_err(|e| e.to_string())
        };
        let grey = array(bytes("grey_b64", &self.grey_b64, 1)?)?;
        let depth_mm = u16s("depth_mm_b64", &self.depth_mm_b64)?;
        let one_shot_mm = self
            .one_shot_mm_b64
            .as_deref()
            .map(|t| u16s("one_shot_mm_b64", t))
            .transpose()?;
        let normalised = self
            .normalised_b64
            .as_deref()
            .map(|t| -> Result<Array2<f32>, String> {
                let b = bytes("normalised_b64", t, 4)?;
                Array2::from_shape_vec(
                    (hh, hw),
                    b.chunks_exact(4)
                        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                        .collect(),
                )
                .map_err(|e| e.to_string())
            })
            .transpose()?;
        AnchorStore::from_parts(size, grey, depth_mm, one_shot_mm, normalised)
            .map_err(|e| e.to_string())
    }
}

/// `CalibrationFile::calibration`: the core calibration's fields, then its anchor store under
/// `anchors` (moma-core serialises no file form of its own).
pub(crate) mod calibration_json {
    use std::sync::Arc;

    use moma_core::pipeline::Calibration;
    use serde::de::Error as _;
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    use super::AnchorStoreFile;

    #[derive(Serialize)]
    struct WithAnchors<'a> {
        #[serde(flatten)]
        calibration: &'a Calibration,
        #[serde(skip_serializing_if = "Option::is_none")]
        anchors: Option<AnchorStoreFile>,
    }

    pub(crate) fn serialize<S: Serializer>(c: &Calibration, s: S) -> Result<S::Ok, S::Error> {
        WithAnchors {
            calibration: c,
            anchors: c.anchors.as_deref().map(AnchorStoreFile::from),
        }
        .serialize(s)
    }

    pub(crate) fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Calibration, D::Error> {
        let mut v = serde_json::Value::deserialize(d)?;
        let anchors = v
            .as_object_mut()
            .and_then(|o| o.remove("anchors"))
            .filter(|a| !a.is_null());
        let mut c: Calibration = serde_json::from_value(v).map_err(D::Error::custom)?;
        if let Some(a) = anchors {
            let file: AnchorStoreFile =
                serde_json::from_value(a).map_err(|e| D::Error::custom(format!("anchors: {e}")))?;
            c.anchors = Some(Arc::new(file.decode().map_err(D::Error::custom)?));
        }
        Ok(c)
    }
}

#[cfg(test)]
mod tests {
    use super::{b64_decode, b64_encode};

    #[test]
    fn standard_base64_with_padding_and_canonical_decoding() {
        // RFC 4648 §10 test vectors.
        for (plain, coded) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(b64_encode(plain.as_bytes()), coded);
            assert_eq!(b64_decode(coded).unwrap(), plain.as_bytes());
        }
        let all: Vec<u8> = (0..=255).collect();
        assert_eq!(b64_decode(&b64_encode(&all)).unwrap(), all);
        for bad in ["Zg=", "Zg", "Z===", "Zm9v!A==", "Zg==Zg=="] {
            assert!(b64_decode(bad).is_err(), "{bad}");
        }
    }
}
