//! The differentiable training path (issue 10): its forward equals the inference network, and
//! its gradients equal central finite differences in f64 (LoRA A and B in the first and last
//! block, head weights, the patch embedding). Random-weight reference models: these check the
//! machinery, not a depth model's accuracy.
#![cfg(feature = "candle")]

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::{reference_dir, reference_input, tiny_config};
use moma_depth::DepthModel;
use moma_depth::candle::train::{LoraConfig, LoraTarget, LossKind, ParamSource, TrainNet, loss};
use moma_depth::candle::{CandleDepthModel, open_checkpoint};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn training_forward_matches_inference() {
    let dir = reference_dir();
    for name in ["tiny-metric", "tiny-rel-392"] {
        let config = tiny_config(&dir, name);
        let path = dir.join(format!("{name}.safetensors"));
        let mut infer = CandleDepthModel::load(&path, config.clone(), &Device::Cpu).unwrap();
        let input = reference_input(&dir, name);
        let want = infer.forward_net(&input).unwrap();
        let vb = open_checkpoint(&path, &config, &Device::Cpu, DType::F32).unwrap();
        let mut net = TrainNet::new(&config, ParamSource::new(vb, |_| false)).unwrap();
        let (c, h, w) = input.dim();
        let x =
            Tensor::from_vec(input.iter().copied().collect(), (1, c, h, w), &Device::Cpu).unwrap();
        let got: Vec<f32> = net
            .forward(&x)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let range = want.iter().copied().fold(f32::NEG_INFINITY, f32::max)
            - want.iter().copied().fold(f32::INFINITY, f32::min);
        let err = got
            .iter()
            .zip(want.iter())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        eprintln!(
            "{name}: training forward vs inference: max abs err {err:.3e}, range {range:.4}, rel {:.3e}",
            err / range
        );
        assert!(err / range < 2e-5, "{name}: rel err {}", err / range);
    }
}

fn values(v: &Var) -> Vec<f64> {
    v.as_tensor().flatten_all().unwrap().to_vec1().unwrap()
}

fn set_values(v: &Var, vals: Vec<f64>) {
    let t = Tensor::from_vec(vals, v.as_tensor().shape(), &Device::Cpu).unwrap();
    v.set(&t).unwrap();
}

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn gradients_match_central_finite_differences_in_f64() {
    let dir = reference_dir();
    let name = "tiny-metric";
    let config = tiny_config(&dir, name);
    let path = dir.join(format!("{name}.safetensors"));
    let vb = open_checkpoint(&path, &config, &Device::Cpu, DType::F64).unwrap();
    let checked_base = [
        "pretrained.patch_embed.proj.weight",
        "depth_head.resize_layers.3.weight",
        "depth_head.scratch.refinenet2.resConfUnit1.conv1.weight",
        "depth_head.scratch.output_conv2.0.weight",
    ];
    let mut net = TrainNet::new(
        &config,
        ParamSource::new(vb, |n: &str| checked_base.contains(&n)),
    )
    .unwrap();
    let mut lora = LoraConfig::new(2);
    lora.alpha = 3.0;
    lora.targets = LoraTarget::ALL.to_vec();
    net.add_lora(&lora).unwrap();
    // Non-zero B (with B = 0 the gradient of A is zero).
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for (k, v) in net.lora_vars() {
        if k.ends_with("lora_B") {
            let n = v.as_tensor().elem_count();
            set_values(v, (0..n).map(|_| rng.random_range(-0.2..0.2)).collect());
        }
    }
    // Input 56×70 (patch grid 4×5: position-embedding interpolation, stride-2 conv on 4×5).
    let (h, w) = (56, 70);
    let x: Vec<f64> = (0..3 * h * w)
        .map(|_| rng.random_range(-2.0..2.0))
        .collect();
    let x = Tensor::from_vec(x, (1, 3, h, w), &Device::Cpu).unwrap();
    let gt: Vec<f64> = (0..h * w).map(|_| rng.random_range(1.0..15.0)).collect();
    let gt = Tensor::from_vec(gt, (1, h, w), &Device::Cpu).unwrap();
    let valid: Vec<u32> = (0..(h * w) as u32).filter(|i| i % 7 != 3).collect();

    let eval = |net: &mut TrainNet| -> f64 {
        let y = net.forward(&x).unwrap();
        loss(LossKind::Silog, &y, &gt, &valid)
            .unwrap()
            .to_scalar::<f64>()
            .unwrap()
    };
    let y = net.forward(&x).unwrap();
    let l = loss(LossKind::Silog, &y, &gt, &valid).unwrap();
    let grads = l.backward().unwrap();

    let last = config.depth - 1;
    let mut checked: Vec<(String, Var)> = vec![];
    for b in [0, last] {
        for t in ["attn.qkv.q", "attn.qkv.v", "attn.qkv.k", "mlp.fc2"] {
            for ab in ["lora_A", "lora_B"] {
                let key = format!("blocks.{b}.{t}.{ab}");
                checked.push((key.clone(), net.lora_vars()[&key].clone()));
            }
        }
    }
    for (k, v) in net.base_vars() {
        checked.push((k.clone(), v.clone()));
    }
    assert_eq!(net.base_vars().len(), checked_base.len());
    let eps = 1e-5;
    let mut worst = 0.0f64;
    for (key, var) in &checked {
        let g: Vec<f64> = grads
            .get(var.as_tensor())
            .unwrap_or_else(|| panic!("{key}: no gradient"))
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let base = values(var);
        // The 3 entries with the largest gradient, and one random entry.
        let mut order: Vec<usize> = (0..g.len()).collect();
        order.sort_by(|&a, &b| g[b].abs().total_cmp(&g[a].abs()));
        let mut picks: Vec<usize> = order.into_iter().take(3).collect();
        picks.push(rng.random_range(0..g.len()));
        let mut worst_key = 0.0f64;
        for &i in &picks {
            let mut plus = base.clone();
            plus[i] += eps;
            set_values(var, plus);
            let lp = eval(&mut net);
            let mut minus = base.clone();
            minus[i] -= eps;
            set_values(var, minus);
            let lm = eval(&mut net);
            set_values(var, base.clone());
            let fd = (lp - lm) / (2.0 * eps);
            let scale = fd.abs().max(g[i].abs()).max(1e-8);
            let rel = (fd - g[i]).abs() / scale;
            worst_key = worst_key.max(rel);
            assert!(
                rel <= 1e-4,
                "{key}[{i}]: autograd {} vs finite difference {fd} (rel {rel:.2e})",
                g[i]
            );
        }
        // The largest gradient must be a real signal, not zero (a layer with no backward).
        assert!(g.iter().any(|v| v.abs() > 1e-8), "{key}: zero gradient");
        eprintln!("{key}: max rel err {worst_key:.2e}");
        worst = worst.max(worst_key);
    }
    eprintln!("worst relative error over all checked entries: {worst:.2e}");
}
