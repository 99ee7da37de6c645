//! Parity of the Rust LoRA training path with PyTorch + peft on the OFFICIAL Depth Anything V2
//! metric network: loss, gradients and one AdamW step, against
//! `tests/data/lora_parity_tiny_metric.safetensors`, written by `benches/pytorch/lora_parity.py`
//! (which first reproduces `tiny-metric.output_net.npy`, so it ran the official network). Both
//! sides compute in f64; the reference stores the loss in f64 and every other value rounded to
//! f32 (relative rounding ≤ 6e-8). Random weights: this checks the machinery, not a depth model.
//!
//! Errors: loss `|a − b| / |b|`; a gradient or updated tensor `max |a − b| / max |b|` over the
//! tensor (the max-abs norm of the difference relative to the reference tensor's max-abs value),
//! the worst tensor reported.
//!
//! Needs `../shared/reference/dav2` (the base weights and the input the crop is taken from):
//! `#[ignore]`d, run with `--include-ignored` (CI does), which fails when the folder is missing.
#![cfg(feature = "candle")]

mod common;

use std::path::PathBuf;

use candle_core::{DType, Device, Tensor, Var};
use common::{ParityReference, flat, reference_dir, rel_max};
use moma_depth::candle::open_checkpoint;
use moma_depth::candle::train::{
    LoraConfig, LoraTarget, LossKind, OptimSettings, ParamSource, Sample, Schedule, TrainNet,
    Trainer, loss, valid_indices,
};
use ndarray::Array2;

const LOSS_TOL: f64 = 1e-5;
const GRAD_TOL: f64 = 1e-4;
/// Bound for the DPT head's weight gradients in the f32 run against the f64 reference. The head
/// is a ReLU network and, on this random-weight reference, a pre-activation of the
/// highest-resolution branch lies within f32 round-off of a kink: which side f32 lands on
/// decides a few pixels' contribution to `projects.0`, `resize_layers.0` and `layer1_rn`
/// (measured: 8.3e-4 with the LayerNorm op, 1.7e-6 with the composed LayerNorm, and 8.3e-4
/// again for the composed LayerNorm when the input is scaled by 1 ± 6e-6, i.e. a round-off
/// effect, not an op error). The f64 run, which has no such ambiguity, meets 1e-4.
const F32_HEAD_GRAD_TOL: f64 = 2e-3;
const WEIGHT_TOL: f64 = 1e-5;

fn reference_file() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/lora_parity_tiny_metric.safetensors")
}

/// The reference file: tensors (as f64 on the CPU) and metadata.
type Reference = ParityReference;

fn load_reference() -> Reference {
    ParityReference::load("lora_parity_tiny_metric.safetensors", "moma-lora-parity-v1")
}

fn meta_f64(r: &Reference, key: &str) -> f64 {
    r.meta[key].parse().unwrap()
}

/// Worst relative error over a family of tensors, with its name.
#[derive(Default)]
struct Worst {
    err: f64,
    name: String,
    count: usize,
}

impl Worst {
    fn add(&mut self, name: &str, err: f64) {
        self.count += 1;
        if err > self.err || self.name.is_empty() {
            self.err = err;
            self.name = name.to_string();
        }
    }
}

/// Worst gradient errors: over all compared tensors, the LoRA ones and the head's.
struct GradWorst {
    all: Worst,
    lora: Worst,
    head: Worst,
}

/// Runs one reference case; returns (loss rel err, worst grad, worst updated weight).
fn run_case(r: &Reference, case: &str, dtype: DType) -> (f64, GradWorst, Worst) {
    let dir = reference_dir();
    let name = r.meta["reference"].clone();
    let settings = r.meta_json(&format!("{case}/settings"));
    let (config, input, gt, (h, w)) = r.training_crop();
    let gt_m = Array2::from_shape_vec((h, w), gt.clone()).unwrap();

    let train_head = settings["train_head"].as_bool().unwrap();
    let path = dir.join(format!("{name}.safetensors"));
    let vb = open_checkpoint(&path, &config, &Device::Cpu, dtype).unwrap();
    let mut net = TrainNet::new(
        &config,
        ParamSource::new(vb, move |n: &str| {
            train_head && n.starts_with("depth_head.")
        }),
    )
    .unwrap();
    let targets: Vec<LoraTarget> = settings["targets"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_str().unwrap().parse().unwrap())
        .collect();
    let mut lora = LoraConfig::new(settings["rank"].as_u64().unwrap() as usize);
    lora.alpha = settings["alpha"].as_f64().unwrap();
    lora.targets = targets;
    net.add_lora(&lora).unwrap();
    // The same A and B as PyTorch (peft's lora_A (r, in) and lora_B (out, r), scale α/r).
    let lora_vars: Vec<(String, Var)> = net
        .lora_vars()
        .iter()
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    let stored = r
        .tensors
        .keys()
        .filter(|k| k.starts_with(&format!("{case}/before/")))
        .count();
    assert_eq!(stored, lora_vars.len(), "{case}: adapter count");
    for (k, v) in &lora_vars {
        let t = r.get(&format!("{case}/before/{k}"));
        v.set(&t.to_dtype(dtype).unwrap()).unwrap();
    }
    let head_vars: Vec<(String, Var)> = net
        .base_vars()
        .iter()
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();

    let min_depth_m = meta_f64(r, "min_depth_m") as f32;
    let max_depth_m = meta_f64(r, "max_depth_m") as f32;
    let lr = settings["lr"].as_f64().unwrap();

    // Loss and gradients.
    let x = Tensor::from_vec(input.iter().copied().collect(), (1, 3, h, w), &Device::Cpu).unwrap();
    let gt_t = Tensor::from_vec(gt.clone(), (1, h, w), &Device::Cpu).unwrap();
    let valid = valid_indices(&gt, None, min_depth_m, max_depth_m);
    let y = net.forward(&x).unwrap();
    let l = loss(LossKind::Silog, &y, &gt_t, &valid).unwrap();
    let grads = l.backward().unwrap();
    let want_loss = flat(r.get(&format!("{case}/loss")))[0];
    let got_loss = flat(&l)[0];
    let loss_err = (got_loss - want_loss).abs() / want_loss.abs();

    let mut grad_worst = Worst::default();
    let (mut grad_lora, mut grad_head) = (Worst::default(), Worst::default());
    for (k, v) in lora_vars.iter().chain(&head_vars) {
        let key = format!("{case}/grad/{k}");
        let Some(want) = r.tensors.get(&key) else {
            continue;
        };
        let got = grads
            .get(v.as_tensor())
            .unwrap_or_else(|| panic!("{case}: no gradient for {k}"));
        let e = rel_max(got, want);
        if std::env::var_os("LORA_PARITY_VERBOSE").is_some() {
            eprintln!("{case} {dtype:?} grad {k}: {e:.3e}");
        }
        grad_worst.add(k, e);
        if k.starts_with("depth_head.") {
            grad_head.add(k, e);
        } else {
            grad_lora.add(k, e);
        }
    }
    let head_stored = r
        .tensors
        .keys()
        .filter(|k| k.starts_with(&format!("{case}/grad/depth_head.")))
        .count();
    assert_eq!(
        grad_worst.count,
        lora_vars.len() + head_stored,
        "{case}: every stored gradient compared"
    );
    // PyTorch leaves unused head weights (refinenet4's first residual unit) without a gradient.
    for k in settings["head_without_grad"].as_array().unwrap() {
        let k = k.as_str().unwrap();
        let v = &head_vars.iter().find(|(n, _)| n == k).unwrap().1;
        assert!(grads.get(v.as_tensor()).is_none(), "{k} has a gradient");
    }
    drop(grads);

    // One AdamW step through the trainer: constant learning rate (no warm-up: factor 1 at step
    // 0), gradient-norm clipping as PyTorch's clip_grad_norm_.
    let optim = OptimSettings {
        loss: LossKind::Silog,
        lr,
        head_lr: lr * meta_f64(r, "head_lr_mult"),
        weight_decay: meta_f64(r, "weight_decay"),
        steps: 1,
        warmup: 0,
        schedule: Schedule::OneCycle,
        accumulate: 1,
        min_depth_m,
        max_depth_m,
        clip_grad_norm: settings["clip_grad_norm"].as_f64().unwrap(),
    };
    let mut trainer = Trainer::new(net, optim).unwrap();
    let sample = Sample {
        input,
        gt_m,
        mask: None,
    };
    let step_loss = trainer.step(&[vec![&sample]]).unwrap();
    assert!(
        (step_loss - got_loss).abs() <= 1e-12 * got_loss.abs().max(1.0) || dtype == DType::F32,
        "{case}: trainer loss {step_loss} vs forward {got_loss}"
    );
    let norm = trainer.last_grad_norm();
    let want_norm = settings["grad_norm"].as_f64().unwrap();
    let norm_err = (norm - want_norm).abs() / want_norm;
    eprintln!(
        "{case}: global gradient norm {norm:.9e} (PyTorch {want_norm:.9e}, rel err \
         {norm_err:.3e}), clip {}",
        settings["clip_grad_norm"]
    );
    // The norm decides the clipping factor (case `all`); it is a gradient quantity: same bound.
    assert!(
        norm_err <= GRAD_TOL,
        "{case}: global gradient norm {norm} vs PyTorch {want_norm} (rel err {norm_err})"
    );
    let mut after_worst = Worst::default();
    for (k, v) in lora_vars.iter().chain(&head_vars) {
        let key = format!("{case}/after/{k}");
        let Some(want) = r.tensors.get(&key) else {
            continue;
        };
        after_worst.add(k, rel_max(v.as_tensor(), want));
    }
    assert_eq!(after_worst.count, grad_worst.count);
    let grad = GradWorst {
        all: grad_worst,
        lora: grad_lora,
        head: grad_head,
    };
    (loss_err, grad, after_worst)
}

fn check(case: &str) {
    let r = load_reference();
    let (loss_err, grad, after) = run_case(&r, case, DType::F64);
    eprintln!(
        "{case} (f64 vs PyTorch+peft f64): loss rel err {loss_err:.3e}; gradients worst {:.3e} \
         ({}, {} tensors); after one AdamW step worst {:.3e} ({}, {} tensors)",
        grad.all.err, grad.all.name, grad.all.count, after.err, after.name, after.count
    );
    assert!(loss_err <= LOSS_TOL, "{case}: loss rel err {loss_err}");
    assert!(
        grad.all.err <= GRAD_TOL,
        "{case}: gradient of {} rel err {}",
        grad.all.name,
        grad.all.err
    );
    assert!(
        after.err <= WEIGHT_TOL,
        "{case}: updated {} rel err {}",
        after.name,
        after.err
    );
}

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn lora_qv_matches_pytorch_peft() {
    check("qv");
}

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn lora_all_targets_and_head_match_pytorch_peft() {
    check("all");
}

/// The committed reference itself: present, small, and what the script says it is (runs without
/// ../shared).
#[test]
fn reference_file_is_complete() {
    let size = std::fs::metadata(reference_file()).unwrap().len();
    assert!(size < 300 * 1024, "reference file is {size} bytes");
    let r = load_reference();
    for case in ["qv", "all"] {
        let s = r.meta_json(&format!("{case}/settings"));
        let rank = s["rank"].as_u64().unwrap() as i64;
        let targets = s["targets"].as_array().unwrap().len();
        let before: Vec<&String> = r
            .tensors
            .keys()
            .filter(|k| k.starts_with(&format!("{case}/before/")))
            .collect();
        assert_eq!(
            before.len(),
            4 * targets * 2,
            "{case}: 4 blocks × targets × (A, B)"
        );
        for k in before {
            let t = &r.tensors[k];
            let dims = t.dims();
            if k.ends_with("lora_A") {
                assert_eq!(dims[0] as i64, rank, "{k}: A is (r, in)");
            } else {
                assert_eq!(dims[1] as i64, rank, "{k}: B is (out, r)");
                assert!(flat(t).iter().any(|v| *v != 0.0), "{k}: B must be non-zero");
            }
        }
        assert!(flat(r.get(&format!("{case}/loss")))[0] > 0.0);
    }
}

/// The f32 training path (what `moma finetune` runs) against the same f64 PyTorch reference:
/// loss and LoRA gradients within the same bounds as the f64 path (1e-5, 1e-4); the trained
/// head's gradients within [`F32_HEAD_GRAD_TOL`]. The AdamW step is not compared in
/// f32: its first step moves each weight by about `lr · g/(|g| + ε)`, which for gradients of
/// order ε (1e-8) turns f32 round-off of the gradient into a change of the update itself.
#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn f32_training_path_is_close_to_the_f64_reference() {
    let r = load_reference();
    for case in ["qv", "all"] {
        let (loss_err, grad, after) = run_case(&r, case, DType::F32);
        eprintln!(
            "{case} (f32 vs PyTorch+peft f64): loss rel err {loss_err:.3e}; LoRA gradients worst \
             {:.3e} ({}); head gradients worst {:.3e} ({}); after one AdamW step worst {:.3e} \
             ({}; not checked)",
            grad.lora.err, grad.lora.name, grad.head.err, grad.head.name, after.err, after.name
        );
        assert!(loss_err <= LOSS_TOL, "{case}: f32 loss rel err {loss_err}");
        assert!(
            grad.lora.err <= GRAD_TOL,
            "{case}: f32 gradient of {} rel err {}",
            grad.lora.name,
            grad.lora.err
        );
        assert!(
            grad.head.err <= F32_HEAD_GRAD_TOL,
            "{case}: f32 gradient of {} rel err {}",
            grad.head.name,
            grad.head.err
        );
    }
}
