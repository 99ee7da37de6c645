//! `DepthModel: Send`: a loaded model moves to a worker thread and predicts there, as a robot
//! program's camera loop would.
#![cfg(feature = "candle")]

mod common;

use common::{max_abs_err, reference_dir, reference_image, reference_output, tiny_config};
use moma_depth::DepthModel;
use moma_depth::candle::CandleDepthModel;

fn assert_send<T: Send + ?Sized>() {}
fn assert_sync<T: Sync + ?Sized>() {}

#[test]
fn models_are_send_at_compile_time() {
    assert_send::<dyn DepthModel>();
    assert_send::<Box<dyn DepthModel>>();
    assert_send::<CandleDepthModel>();
    assert_sync::<CandleDepthModel>();
    #[cfg(feature = "onnx")]
    {
        assert_send::<moma_depth::onnx::OnnxDepthModel>();
        assert_sync::<moma_depth::onnx::OnnxDepthModel>();
    }
}

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn a_loaded_model_predicts_on_another_thread() {
    let dir = reference_dir();
    let name = "tiny-metric";
    let model = CandleDepthModel::load(
        dir.join(format!("{name}.safetensors")),
        tiny_config(&dir, name),
        &candle_core::Device::Cpu,
        candle_core::DType::F32,
        None,
    )
    .unwrap();
    let mut model: Box<dyn DepthModel> = Box::new(model);
    let rgb = reference_image(&dir);
    let worker = std::thread::spawn(move || {
        let pred = model.predict(&rgb).unwrap();
        (pred, model)
    });
    let (pred, model) = worker.join().unwrap();
    // The same output as the official implementation (the parity tests' bound), computed on
    // the worker thread; the model came back and is usable.
    let want = reference_output(&dir, name, "full");
    let (err, range) = max_abs_err(&pred.values, &want);
    assert!(
        err / range < 1e-3,
        "max abs err {err:.3e} of range {range:.4}"
    );
    assert_eq!(pred.kind, model.spec().head.prediction_kind());
}
