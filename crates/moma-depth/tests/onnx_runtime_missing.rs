//! A missing or unusable ONNX Runtime library is a clear [`DepthError::Unavailable`], never a
//! panic. Needs no runtime library: this test binary never loads a real one (one process, one
//! library), so it runs everywhere.
#![cfg(feature = "onnx")]

use moma_depth::DepthError;
use moma_depth::onnx::init_runtime_from;

#[test]
fn unusable_runtime_library_is_an_unavailable_error() {
    let dir = tempfile::tempdir().expect("tempdir");

    let missing = dir.path().join("libonnxruntime.so");
    match init_runtime_from(&missing) {
        Err(DepthError::Unavailable(msg)) => {
            assert!(msg.contains("ORT_DYLIB_PATH"), "names the variable: {msg}");
            assert!(
                msg.contains("install-onnxruntime.sh"),
                "says how to install: {msg}"
            );
        }
        other => panic!("expected Unavailable, got {other:?}"),
    }

    // A file that is not a shared library: dlopen fails, reported as an error.
    let bogus = dir.path().join("libonnxruntime.so.1.99.0");
    std::fs::write(&bogus, b"not an ELF file").expect("write");
    match init_runtime_from(&bogus) {
        Err(DepthError::Unavailable(msg)) => {
            assert!(
                msg.contains(&bogus.display().to_string()),
                "names the file: {msg}"
            );
        }
        other => panic!("expected Unavailable, got {other:?}"),
    }
}
