//! Weight files whose headers claim more than the file holds are refused before anything is
//! mapped or allocated, with a message naming the file and the claim.
#![cfg(feature = "candle")]

use moma_depth::candle::{CandleDepthModel, DepthAnythingConfig};
use moma_depth::{DepthError, Head};

fn safetensors(header: &str, data_len: usize) -> Vec<u8> {
    let mut b = (header.len() as u64).to_le_bytes().to_vec();
    b.extend_from_slice(header.as_bytes());
    b.extend(std::iter::repeat_n(0u8, data_len));
    b
}

fn load_err(bytes: &[u8]) -> (String, String) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("w.safetensors");
    std::fs::write(&path, bytes).unwrap();
    let err = CandleDepthModel::load(
        &path,
        DepthAnythingConfig::vit_small(Head::Relative),
        &candle_core::Device::Cpu,
        candle_core::DType::F32,
        None,
    )
    .unwrap_err();
    let DepthError::Weights { path, reason } = err else {
        panic!("expected a weights error, got {err:?}")
    };
    (path, reason)
}

#[test]
fn a_tensor_claiming_100000_squared_floats_is_refused() {
    let h =
        r#"{"pretrained.cls_token":{"dtype":"F32","shape":[100000,100000],"data_offsets":[0,16]}}"#;
    let (path, reason) = load_err(&safetensors(h, 16));
    assert!(path.ends_with("w.safetensors"), "{path}");
    assert!(
        reason.contains("pretrained.cls_token") && reason.contains("needs 40000000000 bytes"),
        "{reason}"
    );
}

#[test]
fn a_header_length_beyond_the_file_is_refused() {
    let mut b = safetensors("{}", 0);
    b[..8].copy_from_slice(&(1u64 << 40).to_le_bytes());
    let (_, reason) = load_err(&b);
    assert!(
        reason.contains("1099511627776") && reason.contains("over the limit of 100000000"),
        "{reason}"
    );
    b[..8].copy_from_slice(&5000u64.to_le_bytes());
    let (_, reason) = load_err(&b);
    assert!(reason.contains("only 10 bytes"), "{reason}");
}
