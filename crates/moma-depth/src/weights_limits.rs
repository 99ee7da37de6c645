//! Resource limits on weight files: the header of a `.safetensors` checkpoint is checked against
//! the file's length before anything is mapped or allocated for it, and ONNX models are size-checked
//! before ONNX Runtime reads them.
//!
//! A `.safetensors` file is an 8-byte little-endian header length `n`, `n` bytes of JSON
//! (`name → {dtype, shape, data_offsets: [begin, end]}`, plus an optional `__metadata__` map of
//! strings), then the tensor data; offsets are relative to the end of the header.

use std::io::Read;
use std::path::Path;

use crate::{DepthError, Result};

/// Largest `.safetensors` JSON header accepted, bytes (the `safetensors` crate's own limit).
pub const MAX_SAFETENSORS_HEADER_BYTES: u64 = 100_000_000;

/// Largest weight file accepted (`.safetensors`, `.pth` or `.onnx`), bytes: 16 GiB, twice the
/// largest Depth Anything V2 checkpoint (ViT-G, about 5.3 GB in f32) with room to spare.
pub const MAX_WEIGHTS_FILE_BYTES: u64 = 16 << 30;

/// One tensor of a checked `.safetensors` header.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TensorEntry {
    /// Tensor name.
    pub name: String,
    /// Stored dtype name, e.g. `"F32"`.
    pub dtype: String,
    /// Shape.
    pub shape: Vec<u64>,
    /// Byte range in the data section, relative to its start.
    pub data_offsets: (u64, u64),
}

/// Bytes per element of a safetensors dtype name (`None` for unknown names).
fn dtype_bits(dtype: &str) -> Option<u64> {
    Some(match dtype {
        "BOOL" | "U8" | "I8" | "F8_E5M2" | "F8_E4M3" | "F8_E8M0" => 8,
        "I16" | "U16" | "F16" | "BF16" => 16,
        "I32" | "U32" | "F32" => 32,
        "I64" | "U64" | "F64" | "C64" => 64,
        "F4" => 4,
        "F6_E2M3" | "F6_E3M2" => 6,
        _ => return None,
    })
}

fn weights_err(path: &Path, reason: String) -> DepthError {
    DepthError::Weights {
        path: path.display().to_string(),
        reason,
    }
}

/// Checks the header of a `.safetensors` file of `file_len` bytes whose first bytes are
/// `prefix` (at least the 8-byte length and the JSON header): the header length is at most
/// [`MAX_SAFETENSORS_HEADER_BYTES`] and fits in the file, the JSON is a map of tensors with known
/// dtypes, and every tensor's data range holds exactly its shape's elements and lies inside the
/// file. Returns the tensors in header order.
///
/// # Errors
/// [`DepthError::Weights`] naming `path` and the first problem found.
pub fn check_safetensors_header(
    path: &Path,
    prefix: &[u8],
    file_len: u64,
) -> Result<Vec<TensorEntry>> {
    let bad =
        |reason: String| weights_err(path, format!("not a valid .safetensors file: {reason}"));
    if file_len > MAX_WEIGHTS_FILE_BYTES {
        return Err(bad(format!(
            "file is {file_len} bytes, over the limit of {MAX_WEIGHTS_FILE_BYTES}"
        )));
    }
    let Some(len_bytes) = prefix.get(..8) else {
        return Err(bad(format!(
            "file is {file_len} bytes, shorter than the 8-byte header length"
        )));
    };
    let mut n = [0u8; 8];
    n.copy_from_slice(len_bytes);
    let header_len = u64::from_le_bytes(n);
    if header_len > MAX_SAFETENSORS_HEADER_BYTES {
        return Err(bad(format!(
            "header claims {header_len} bytes, over the limit of {MAX_SAFETENSORS_HEADER_BYTES}"
        )));
    }
    let data_start = 8 + header_len;
    if data_start > file_len {
        return Err(bad(format!(
            "header claims {header_len} bytes but the file has only {file_len} bytes"
        )));
    }
    let data_len = file_len - data_start;
    let Some(json) = usize::try_from(data_start)
        .ok()
        .and_then(|end| prefix.get(8..end))
    else {
        return Err(bad(format!(
            "only {} bytes of the {header_len}-byte header were read",
            prefix.len().saturating_sub(8)
        )));
    };
    let map: serde_json::Map<String, serde_json::Value> = serde_json::from_slice(json)
        .map_err(|e| bad(format!("header is not a JSON object: {e}")))?;
    let mut tensors = Vec::with_capacity(map.len());
    for (name, info) in map {
        if name == "__metadata__" {
            let ok = info
                .as_object()
                .is_some_and(|m| m.values().all(serde_json::Value::is_string));
            if !ok {
                return Err(bad("__metadata__ is not a map of strings".into()));
            }
            continue;
        }
        let tensor = |what: &str| bad(format!("tensor '{name}': {what}"));
        let info = info
            .as_object()
            .ok_or_else(|| tensor("entry is not an object"))?;
        let dtype = info
            .get("dtype")
            .and_then(serde_json::Value::as_str)
            .ok_or_else(|| tensor("missing or non-string dtype"))?;
        let bits = dtype_bits(dtype).ok_or_else(|| tensor(&format!("unknown dtype '{dtype}'")))?;
        let shape = info
            .get("shape")
            .and_then(serde_json::Value::as_array)
            .and_then(|a| {
                a.iter()
                    .map(serde_json::Value::as_u64)
                    .collect::<Option<Vec<u64>>>()
            })
            .ok_or_else(|| tensor("shape is not a list of non-negative integers"))?;
        let offsets = info
            .get("data_offsets")
            .and_then(serde_json::Value::as_array)
            .and_then(|a| match a.as_slice() {
                [b, e] => Some((b.as_u64()?, e.as_u64()?)),
                _ => None,
            })
            .ok_or_else(|| tensor("data_offsets is not a pair of non-negative integers"))?;
        let elements = shape
            .iter()
            .try_fold(1u64, |acc, &d| acc.checked_mul(d))
            .ok_or_else(|| tensor(&format!("shape {shape:?} overflows")))?;
        let need = elements
            .checked_mul(bits)
            .map(|b| b.div_ceil(8))
            .ok_or_else(|| tensor(&format!("shape {shape:?} overflows")))?;
        let (begin, end) = offsets;
        if begin > end || end > data_len {
            return Err(tensor(&format!(
                "data_offsets [{begin}, {end}] lie outside the {data_len} data bytes of the file"
            )));
        }
        if end - begin != need {
            return Err(tensor(&format!(
                "shape {shape:?} of {dtype} needs {need} bytes, data_offsets [{begin}, {end}] hold {}",
                end - begin
            )));
        }
        tensors.push(TensorEntry {
            name,
            dtype: dtype.to_string(),
            shape,
            data_offsets: offsets,
        });
    }
    Ok(tensors)
}

/// Reads and checks the header of the `.safetensors` file at `path` ([`check_safetensors_header`]),
/// reading only the header bytes.
///
/// # Errors
/// [`DepthError::Weights`] when the file cannot be read or its header is refused.
pub fn check_safetensors_file(path: &Path) -> Result<Vec<TensorEntry>> {
    let io = |e: std::io::Error| weights_err(path, format!("cannot read: {e}"));
    let file_len = std::fs::metadata(path).map_err(io)?.len();
    let mut file = std::fs::File::open(path).map_err(io)?;
    let mut prefix = vec![0u8; 8.min(file_len as usize)];
    file.read_exact(&mut prefix).map_err(io)?;
    if let Ok(n) = <[u8; 8]>::try_from(prefix.as_slice()) {
        let header_len = u64::from_le_bytes(n);
        if header_len <= MAX_SAFETENSORS_HEADER_BYTES && 8 + header_len <= file_len {
            let mut json = vec![0u8; header_len as usize];
            file.read_exact(&mut json).map_err(io)?;
            prefix.extend_from_slice(&json);
        }
    }
    check_safetensors_header(path, &prefix, file_len)
}

/// Checks that the weight file at `path` is at most [`MAX_WEIGHTS_FILE_BYTES`] long.
///
/// # Errors
/// [`DepthError::Weights`] when it is larger or its size cannot be read.
pub fn check_weights_file_size(path: &Path) -> Result<u64> {
    let len = std::fs::metadata(path)
        .map_err(|e| weights_err(path, format!("cannot read: {e}")))?
        .len();
    if len > MAX_WEIGHTS_FILE_BYTES {
        return Err(weights_err(
            path,
            format!("file is {len} bytes, over the limit of {MAX_WEIGHTS_FILE_BYTES}"),
        ));
    }
    Ok(len)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(header: &str, data_len: usize) -> Vec<u8> {
        let mut b = (header.len() as u64).to_le_bytes().to_vec();
        b.extend_from_slice(header.as_bytes());
        b.extend(std::iter::repeat_n(0u8, data_len));
        b
    }

    fn check(bytes: &[u8]) -> Result<Vec<TensorEntry>> {
        check_safetensors_header(Path::new("w.safetensors"), bytes, bytes.len() as u64)
    }

    #[test]
    fn a_well_formed_header_lists_its_tensors() {
        let h = r#"{"__metadata__":{"format":"pt"},"a":{"dtype":"F32","shape":[2,2],"data_offsets":[0,16]},"b":{"dtype":"F16","shape":[3],"data_offsets":[16,22]}}"#;
        let t = check(&file(h, 22)).unwrap();
        assert_eq!(t.len(), 2);
        assert_eq!(t[0].shape, vec![2, 2]);
        assert_eq!(t[1].data_offsets, (16, 22));
    }

    #[test]
    fn headers_that_disagree_with_the_file_are_refused() {
        let msg = |b: &[u8]| check(b).unwrap_err().to_string();
        // Header length beyond the file / beyond the limit.
        let mut b = file("{}", 0);
        b[..8].copy_from_slice(&1000u64.to_le_bytes());
        assert!(msg(&b).contains("only 10 bytes"), "{}", msg(&b));
        b[..8].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(msg(&b).contains("over the limit"), "{}", msg(&b));
        // A tensor claiming 100000 × 100000 floats in a 16-byte data section.
        let h = r#"{"a":{"dtype":"F32","shape":[100000,100000],"data_offsets":[0,16]}}"#;
        let m = msg(&file(h, 16));
        assert!(
            m.contains("w.safetensors") && m.contains("needs 40000000000 bytes"),
            "{m}"
        );
        // Offsets beyond the data; overflowing shapes; unknown dtypes.
        let h = r#"{"a":{"dtype":"F32","shape":[4],"data_offsets":[0,16]}}"#;
        assert!(msg(&file(h, 8)).contains("outside the 8 data bytes"));
        let h = r#"{"a":{"dtype":"F32","shape":[4294967296,4294967296,4294967296],"data_offsets":[0,16]}}"#;
        assert!(msg(&file(h, 16)).contains("overflows"));
        let h = r#"{"a":{"dtype":"Q4","shape":[4],"data_offsets":[0,2]}}"#;
        assert!(msg(&file(h, 2)).contains("unknown dtype"));
        assert!(msg(&[1, 0]).contains("shorter than the 8-byte"));
    }
}
