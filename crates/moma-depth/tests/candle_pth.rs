//! Loading PyTorch `.pth` checkpoints (the official release format): a reference model re-saved in
//! the `torch.save` zip layout gives the same network output as its `.safetensors` twin, and a
//! corrupt or legacy archive is a clear weights error.
#![cfg(feature = "candle")]

mod common;

use std::io::Write;
use std::path::Path;

use common::{reference_dir, reference_input, tiny_config};
use moma_depth::candle::{CandleDepthModel, DepthAnythingConfig};
use moma_depth::{DepthError, DepthModel, Head};

/// Writes `tensors` (f32) as `torch.save(state_dict)` does since PyTorch 1.6: a zip archive with
/// `archive/data.pkl` (protocol-2 pickle of an `OrderedDict` of `_rebuild_tensor_v2` calls whose
/// storages are persistent ids) and one little-endian file per storage under `archive/data/`.
fn write_torch_zip(path: &Path, tensors: &[(String, Vec<usize>, Vec<f32>)]) {
    fn unicode(p: &mut Vec<u8>, s: &str) {
        p.push(b'X');
        p.extend_from_slice(&(s.len() as u32).to_le_bytes());
        p.extend_from_slice(s.as_bytes());
    }
    fn int(p: &mut Vec<u8>, v: usize) {
        p.push(b'J');
        p.extend_from_slice(&(v as i32).to_le_bytes());
    }
    fn ints(p: &mut Vec<u8>, vs: &[usize]) {
        p.push(b'(');
        for &v in vs {
            int(p, v);
        }
        p.push(b't');
    }
    const ORDERED_DICT: &[u8] = b"ccollections\nOrderedDict\n)R";
    let mut pkl = b"\x80\x02".to_vec();
    pkl.extend_from_slice(ORDERED_DICT);
    pkl.push(b'(');
    for (key, (name, shape, _)) in tensors.iter().enumerate() {
        unicode(&mut pkl, name);
        pkl.extend_from_slice(b"ctorch._utils\n_rebuild_tensor_v2\n(");
        // Persistent id ('storage', torch.FloatStorage, key, 'cpu', numel).
        pkl.push(b'(');
        unicode(&mut pkl, "storage");
        pkl.extend_from_slice(b"ctorch\nFloatStorage\n");
        unicode(&mut pkl, &key.to_string());
        unicode(&mut pkl, "cpu");
        int(&mut pkl, shape.iter().product());
        pkl.extend_from_slice(b"tQ");
        int(&mut pkl, 0); // storage offset
        ints(&mut pkl, shape);
        let mut strides = vec![1usize; shape.len()];
        for i in (0..shape.len().saturating_sub(1)).rev() {
            strides[i] = strides[i + 1] * shape[i + 1];
        }
        ints(&mut pkl, &strides);
        pkl.push(0x89); // requires_grad = False
        pkl.extend_from_slice(ORDERED_DICT); // backward hooks
        pkl.extend_from_slice(b"tR");
    }
    pkl.extend_from_slice(b"u.");

    let mut zip = zip::ZipWriter::new(std::fs::File::create(path).unwrap());
    let stored =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    zip.start_file("archive/data.pkl", stored).unwrap();
    zip.write_all(&pkl).unwrap();
    zip.start_file("archive/byteorder", stored).unwrap();
    zip.write_all(b"little").unwrap();
    for (key, (_, _, values)) in tensors.iter().enumerate() {
        zip.start_file(format!("archive/data/{key}"), stored)
            .unwrap();
        for v in values {
            zip.write_all(&v.to_le_bytes()).unwrap();
        }
    }
    zip.start_file("archive/version", stored).unwrap();
    zip.write_all(b"3\n").unwrap();
    zip.finish().unwrap();
}

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn pth_checkpoint_matches_its_safetensors_twin() {
    let dir = reference_dir();
    let device = candle_core::Device::Cpu;
    let st = dir.join("tiny-rel.safetensors");
    let tensors = candle_core::safetensors::load(&st, &device).unwrap();
    let mut listing: Vec<(String, Vec<usize>, Vec<f32>)> = tensors
        .iter()
        .map(|(name, t)| {
            let values = t
                .to_dtype(candle_core::DType::F32)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap();
            (name.clone(), t.dims().to_vec(), values)
        })
        .collect();
    listing.sort_by(|a, b| a.0.cmp(&b.0));
    let tmp = tempfile::tempdir().unwrap();
    // Official file name; the loader sniffs the zip magic, not the extension.
    let pth = tmp.path().join("depth_anything_v2_tiny.pth");
    write_torch_zip(&pth, &listing);

    let input = reference_input(&dir, "tiny-rel");
    let config = tiny_config(&dir, "tiny-rel");
    let mut from_st =
        CandleDepthModel::load(&st, config.clone(), &device, candle_core::DType::F32, None)
            .unwrap();
    let mut from_pth =
        CandleDepthModel::load(&pth, config.clone(), &device, candle_core::DType::F32, None)
            .unwrap();
    let a = from_st.forward_net(&input).unwrap();
    let b = from_pth.forward_net(&input).unwrap();
    assert_eq!(a, b, "same weights, same kernels: bit-identical outputs");

    // A state dict missing a key is reported with the key's name, as for safetensors.
    let dropped = listing.remove(0);
    let broken = tmp.path().join("broken.pth");
    write_torch_zip(&broken, &listing);
    let err = CandleDepthModel::load(&broken, config, &device, candle_core::DType::F32, None)
        .unwrap_err();
    let DepthError::Weights { reason, path } = &err else {
        panic!("expected a weights error, got {err:?}")
    };
    assert!(path.ends_with("broken.pth"), "{path}");
    assert!(reason.contains(&dropped.0), "{reason}");
}

#[test]
fn corrupt_and_legacy_archives_are_weights_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let config = DepthAnythingConfig::vit_small(Head::Relative);
    let device = candle_core::Device::Cpu;
    // Zip magic, then garbage.
    let truncated = tmp.path().join("truncated.pth");
    std::fs::write(&truncated, b"PK\x03\x04 not really a zip archive").unwrap();
    // A pre-1.6 torch.save file starts with a pickle protocol header, not a zip.
    let legacy = tmp.path().join("legacy.pth");
    std::fs::write(&legacy, b"\x80\x02\x8a\x0al\xfc\x9cF\xf9 j\xa8P\x19.").unwrap();
    // The broken archive: candle's own error is kept as the typed source, under a message
    // naming the file.
    let err = CandleDepthModel::load(
        &truncated,
        config.clone(),
        &device,
        candle_core::DType::F32,
        None,
    )
    .unwrap_err();
    let DepthError::Candle { context, .. } = &err else {
        panic!("expected candle's error as the source, got {err:?}")
    };
    assert!(
        context.contains("cannot load weights from") && context.contains("truncated.pth"),
        "{context}"
    );
    let source = std::error::Error::source(&err).expect("candle error as source");
    assert!(!err.to_string().contains(&source.to_string()), "{err}");
    let err = CandleDepthModel::load(&legacy, config, &device, candle_core::DType::F32, None)
        .unwrap_err();
    let DepthError::Weights { reason, .. } = &err else {
        panic!("expected a weights error, got {err:?}")
    };
    assert!(reason.contains("legacy"), "{reason}");
}
