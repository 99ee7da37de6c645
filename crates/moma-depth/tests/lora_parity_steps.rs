//! Multi-step parity of the Rust LoRA trainer with PyTorch + peft on the OFFICIAL Depth Anything
//! V2 metric network: six AdamW steps (weight decay 0.01, a warm-up + poly schedule,
//! gradient-norm clipping active with factors < 1 on five of the six steps), LoRA on q, k, v,
//! proj, fc1, fc2 and the DPT head trained with its own learning rate, all in f64. Reference:
//! `tests/data/lora_parity_steps_tiny_metric.safetensors`, written by
//! `benches/pytorch/lora_parity_steps.py` (which first reproduces `tiny-metric.output_net.npy`,
//! so it ran the official network). Random weights: this checks the optimiser, not a model.
//!
//! Checked after every step: the loss before the step (relative error ≤ 1e-6), the global
//! gradient norm before clipping (≤ 1e-6), and every trained tensor after the update
//! (`max |a − b| / max |b|` ≤ 1e-5). The reference stores the weights rounded to f32
//! (relative rounding ≤ 6e-8) and the losses and norms in f64. One step of the Adam update
//! depends on β1, β2, the bias corrections, ε, the decoupled weight decay, the clipping factor
//! and the schedule: the first step alone (≈ lr·sign(g)) checks none of them.
//!
//! Needs `../shared/reference/dav2`: `#[ignore]`d, run with `--include-ignored` (CI does).
#![cfg(feature = "candle")]

mod common;

use std::path::PathBuf;

use candle_core::{DType, Device};
use common::{ParityReference, flat, reference_dir, rel_max};
use moma_depth::candle::open_checkpoint;
use moma_depth::candle::train::{
    LoraConfig, LoraTarget, LossKind, OptimSettings, ParamSource, Sample, Schedule, TrainNet,
    Trainer, lr_factor,
};
use ndarray::Array2;

const LOSS_TOL: f64 = 1e-6;
const NORM_TOL: f64 = 1e-6;
const WEIGHT_TOL: f64 = 1e-5;

fn reference_file() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/lora_parity_steps_tiny_metric.safetensors")
}

fn load_reference() -> ParityReference {
    ParityReference::load(
        "lora_parity_steps_tiny_metric.safetensors",
        "moma-lora-parity-steps-v1",
    )
}

/// A stored scalar (shape (1,)).
fn scalar(r: &ParityReference, key: &str) -> f64 {
    flat(r.get(key))[0]
}

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn six_adamw_steps_with_clipping_schedule_and_head_match_pytorch_peft() {
    let r = load_reference();
    let st = r.meta_json("settings");
    let (config, input, gt, (h, w)) = r.training_crop();
    let name = r.meta["reference"].clone();
    let dir = reference_dir();
    let sample = Sample {
        input,
        gt_m: Array2::from_shape_vec((h, w), gt).unwrap(),
        mask: None,
    };

    assert!(st["train_head"].as_bool().unwrap());
    let path = dir.join(format!("{name}.safetensors"));
    let vb = open_checkpoint(&path, &config, &Device::Cpu, DType::F64).unwrap();
    let mut net = TrainNet::new(
        &config,
        ParamSource::new(vb, |n: &str| n.starts_with("depth_head.")),
    )
    .unwrap();
    let mut lora = LoraConfig::new(st["rank"].as_u64().unwrap() as usize);
    lora.alpha = st["alpha"].as_f64().unwrap();
    lora.targets = st["targets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_str().unwrap().parse::<LoraTarget>().unwrap())
        .collect();
    net.add_lora(&lora).unwrap();
    for (k, v) in net.lora_vars() {
        v.set(r.get(&format!("before/{k}"))).unwrap();
    }
    let trained: Vec<(String, candle_core::Var)> = net
        .lora_vars()
        .iter()
        .chain(net.base_vars())
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    assert_eq!(
        trained.len(),
        48 + 64,
        "LoRA A/B of 6 targets × 4 blocks, 64 head tensors"
    );

    let steps = st["steps"].as_u64().unwrap() as usize;
    let warmup = st["warmup"].as_u64().unwrap() as usize;
    assert_eq!(st["schedule"], "poly");
    let lr = st["lr"].as_f64().unwrap();
    let optim = OptimSettings {
        loss: LossKind::Silog,
        lr,
        head_lr: lr * st["head_lr_mult"].as_f64().unwrap(),
        weight_decay: st["weight_decay"].as_f64().unwrap(),
        steps,
        warmup,
        schedule: Schedule::Poly,
        accumulate: 1,
        min_depth_m: st["min_depth_m"].as_f64().unwrap() as f32,
        max_depth_m: st["max_depth_m"].as_f64().unwrap() as f32,
        clip_grad_norm: st["clip_grad_norm"].as_f64().unwrap(),
    };
    let clip = optim.clip_grad_norm;
    let mut trainer = Trainer::new(net, optim).unwrap();
    let mut clipped = 0;
    for k in 1..=steps {
        // The schedule of both sides (the reference stores PyTorch's LambdaLR factor).
        let f = lr_factor(Schedule::Poly, k - 1, steps, warmup);
        assert!(
            (f - scalar(&r, &format!("lr_factor/{k}"))).abs() < 1e-15,
            "step {k}: lr factor"
        );
        let got_loss = trainer.step(&[vec![&sample]]).unwrap();
        let want_loss = scalar(&r, &format!("loss/{k}"));
        let loss_err = (got_loss - want_loss).abs() / want_loss.abs();
        let norm = trainer.last_grad_norm();
        let want_norm = scalar(&r, &format!("grad_norm/{k}"));
        let norm_err = (norm - want_norm).abs() / want_norm;
        if clip / (want_norm + 1e-6) < 1.0 {
            clipped += 1;
        }
        let (mut worst, mut worst_name) = (0.0f64, String::new());
        for (name, v) in &trained {
            let e = rel_max(v.as_tensor(), r.get(&format!("after/{k}/{name}")));
            if e > worst {
                (worst, worst_name) = (e, name.clone());
            }
        }
        eprintln!(
            "step {k}: loss {got_loss:.12} (PyTorch {want_loss:.12}, rel {loss_err:.2e}); grad norm \
             {norm:.6e} (rel {norm_err:.2e}, clip factor {:.3}); weights worst rel {worst:.2e} ({worst_name})",
            (clip / (want_norm + 1e-6)).min(1.0)
        );
        assert!(loss_err <= LOSS_TOL, "step {k}: loss rel err {loss_err}");
        assert!(
            norm_err <= NORM_TOL,
            "step {k}: gradient norm rel err {norm_err}"
        );
        assert!(
            worst <= WEIGHT_TOL,
            "step {k}: {worst_name} after the update, rel err {worst}"
        );
    }
    assert!(clipped >= 2, "clipping acted on {clipped} step(s)");
}

/// The committed reference itself (runs without ../shared): every step's weights, settings that
/// exercise what the test claims.
#[test]
fn steps_reference_file_is_complete() {
    let size = std::fs::metadata(reference_file()).unwrap().len();
    assert!(size < 4 * 1024 * 1024, "reference file is {size} bytes");
    let r = load_reference();
    let st = r.meta_json("settings");
    let steps = st["steps"].as_u64().unwrap() as usize;
    assert!(steps >= 5);
    assert!(st["weight_decay"].as_f64().unwrap() > 0.0);
    assert!(st["train_head"].as_bool().unwrap());
    let clip = st["clip_grad_norm"].as_f64().unwrap();
    let clipped = (1..=steps)
        .filter(|k| clip / (scalar(&r, &format!("grad_norm/{k}")) + 1e-6) < 1.0)
        .count();
    assert!(clipped >= 2, "clip factor < 1 on {clipped} step(s)");
    for k in 1..=steps {
        let n = r
            .tensors
            .keys()
            .filter(|key| key.starts_with(&format!("after/{k}/")))
            .count();
        assert_eq!(n, 48 + 64, "step {k}: every trained tensor");
    }
}
