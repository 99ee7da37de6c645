//! `moma finetune` / `--lora` / `moma lora merge` end to end on the tiny random-weight metric
//! model of `shared/reference/dav2` and a shared moma set. The loss falls because the adapters fit
//! this data; random weights predict nothing meaningful, so this checks the machinery only.
#![cfg(feature = "candle")]

use std::path::{Path, PathBuf};

mod common;
use common::{fails, ok, s, tiny_metric_model};

/// The tiny metric model's flags, on the CPU: `--weights W --model C --input-size PX --device cpu`.
fn tiny_model_flags<'a>(weights: &'a Path, config: &'a Path, input_size: &'a str) -> [&'a str; 8] {
    [
        "--weights",
        s(weights),
        "--model",
        s(config),
        "--input-size",
        input_size,
        "--device",
        "cpu",
    ]
}

fn shared() -> Option<PathBuf> {
    let shared = std::env::var_os("MOMA_SHARED_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"));
    let ok = shared
        .join("reference/dav2/tiny-metric.safetensors")
        .is_file()
        && shared.join("data/gqcnn-primesense/camera.json").is_file();
    assert!(
        ok,
        "this test needs the shared folder (reference/dav2, data/gqcnn-primesense), not found at {} (set MOMA_SHARED_DIR)",
        shared.display()
    );
    Some(shared)
}

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn finetune_lowers_the_loss_and_the_adapter_loads_everywhere() {
    let Some(shared) = shared() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let (weights, config) = tiny_metric_model(&shared, tmp.path());
    let set = shared.join("data/gqcnn-primesense");
    let adapter = tmp.path().join("a.safetensors");
    let common = tiny_model_flags(&weights, &config, "56");
    let mut args: Vec<&str> = vec!["finetune", "--set", s(&set)];
    args.extend(common);
    args.extend([
        "--steps",
        "60",
        "--lr",
        "1e-2",
        "--lora-rank",
        "4",
        "--seed",
        "1",
        "-o",
        s(&adapter),
        "--json",
    ]);
    let out = ok(&args);
    let j: serde_json::Value = serde_json::from_str(&out).unwrap();
    eprintln!("{j:#}");
    let first = j["train_loss_first"].as_f64().unwrap();
    let last = j["train_loss_last"].as_f64().unwrap();
    assert_eq!(j["steps"], 60);
    assert!(
        last <= 0.8 * first,
        "training loss {first} -> {last}: less than 20 % lower"
    );
    let (vb, va) = (
        j["val_loss_before"].as_f64().unwrap(),
        j["val_loss_after"].as_f64().unwrap(),
    );
    assert!(va < vb, "validation loss {vb} -> {va}");
    assert!(adapter.is_file());

    // predict --lora equals predict on the merged weights, and differs from the base weights.
    let rgb = set
        .join("frames")
        .read_dir()
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path()
        .join("rgb.png");
    let run_predict = |extra: &[&str], w: &Path, out: &Path| {
        let mut a: Vec<&str> = vec!["predict", "--weights", s(w), "--model", s(&config)];
        a.extend([
            "--input-size",
            "56",
            "--device",
            "cpu",
            "-o",
            s(out),
            s(&rgb),
        ]);
        a.extend(extra);
        ok(&a);
        let name = std::fs::read_dir(out)
            .unwrap()
            .map(|e| e.unwrap().path())
            .find(|p| p.extension().is_some_and(|e| e == "npy"))
            .unwrap();
        let a: ndarray::Array2<f32> = ndarray_npy::read_npy(name).unwrap();
        a
    };
    let with_lora = run_predict(&["--lora", s(&adapter)], &weights, &tmp.path().join("p1"));
    let merged = tmp.path().join("merged.safetensors");
    let mut m: Vec<&str> = vec!["lora", "merge", "--lora", s(&adapter), "-o", s(&merged)];
    m.extend(common);
    ok(&m);
    let from_merged = run_predict(&[], &merged, &tmp.path().join("p2"));
    let base = run_predict(&[], &weights, &tmp.path().join("p3"));
    // the predictions' index records the adapter (and only where there is one)
    let index = |dir: &str| -> serde_json::Value {
        serde_json::from_str(
            &std::fs::read_to_string(tmp.path().join(dir).join("predictions.json")).unwrap(),
        )
        .unwrap()
    };
    assert_eq!(index("p1")["lora"].as_str(), Some(s(&adapter)));
    assert!(index("p3").get("lora").is_none());
    let diff = |a: &ndarray::Array2<f32>, b: &ndarray::Array2<f32>| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max)
    };
    eprintln!(
        "predict --lora vs merged: {:.3e}; vs base: {:.3e}",
        diff(&with_lora, &from_merged),
        diff(&with_lora, &base)
    );
    assert!(diff(&with_lora, &from_merged) < 1e-5);
    assert!(diff(&with_lora, &base) > 1e-3);

    // issue 26's error budget on a LoRA fine-tuned model: `--dtype int8|bf16` on the CPU (the
    // adapter merged, then the encoder's linear layers packed) against f32, relative to the
    // output range: max ≤ 1e-2, mean ≤ 2e-3, as on the random-weight references
    let range = with_lora.iter().fold(f32::MIN, |a, &b| a.max(b))
        - with_lora.iter().fold(f32::MAX, |a, &b| a.min(b));
    assert!(range > 0.0);
    for dtype in ["int8", "bf16"] {
        let q = run_predict(
            &["--lora", s(&adapter), "--dtype", dtype],
            &weights,
            &tmp.path().join(format!("q-{dtype}")),
        );
        let max = diff(&q, &with_lora) / range;
        let mean = q
            .iter()
            .zip(&with_lora)
            .map(|(x, y)| (x - y).abs())
            .sum::<f32>()
            / q.len() as f32
            / range;
        eprintln!(
            "LoRA fine-tuned tiny model, {dtype} vs f32: max {max:.3e}, mean {mean:.3e} of the range"
        );
        assert!(
            max <= 1e-2 && mean <= 2e-3,
            "{dtype}: max {max}, mean {mean}"
        );
        assert!(max > 0.0, "{dtype}: the same output as f32");
    }

    // Bad input: an adapter for other weights, a corrupt adapter, rank 0, an unknown target.
    let other = shared.join("reference/dav2/tiny-metric-392.safetensors");
    let e = fails(&[
        "predict",
        "--weights",
        s(&other),
        "--model",
        s(&config),
        "--input-size",
        "56",
        "--device",
        "cpu",
        "--lora",
        s(&adapter),
        "-o",
        s(&tmp.path().join("p4")),
        s(&rgb),
    ]);
    assert!(e.contains("other base weights"), "{e}");
    let corrupt = tmp.path().join("corrupt.safetensors");
    std::fs::write(&corrupt, b"not an adapter").unwrap();
    let e = fails(&[
        "predict",
        "--weights",
        s(&weights),
        "--model",
        s(&config),
        "--input-size",
        "56",
        "--device",
        "cpu",
        "--lora",
        s(&corrupt),
        "-o",
        s(&tmp.path().join("p5")),
        s(&rgb),
    ]);
    assert!(e.contains("corrupt.safetensors"), "{e}");
    let mut a: Vec<&str> = vec![
        "finetune",
        "--set",
        s(&set),
        "--steps",
        "1",
        "-o",
        s(&corrupt),
    ];
    a.extend(common);
    let mut rank0 = a.clone();
    rank0.extend(["--lora-rank", "0"]);
    assert!(fails(&rank0).contains("rank"));
    let mut unknown = a.clone();
    unknown.extend(["--lora-targets", "q,x"]);
    assert!(fails(&unknown).contains("unknown LoRA target"));
    let mut head = a.clone();
    head.extend(["--head", "relative"]);
    assert!(fails(&head).contains("disagrees"));
    // Sizes that used to abort or wrap: a batch reserved up front, batch × accumulate, a number
    // of steps reserved up front, epochs × frames.
    for (extra, want) in [
        (&["--batch", "1000000000000"][..], "at most 4096"),
        (
            &["--batch", "4096", "--accumulate", "9223372036854775807"],
            "at most 4096",
        ),
    ] {
        let mut big = a.clone();
        big.extend(extra);
        let e = fails(&big);
        assert!(e.contains(want), "{extra:?}: {e}");
    }
    for (option, want) in [("--steps", "at most 100000000"), ("--epochs", "overflows")] {
        let mut long: Vec<&str> = vec![
            "finetune",
            "--set",
            s(&set),
            option,
            "18446744073709551615",
            "-o",
            s(&corrupt),
        ];
        long.extend(common);
        let e = fails(&long);
        assert!(e.contains(want), "{option}: {e}");
    }
    // Refused before training: an output that is an input, an output folder that does not
    // exist, a set given twice (its validation frames would be trained on), a learning rate
    // that moves every weight by more than its size; merging into an input.
    let copy = tmp.path().join("base.safetensors");
    std::fs::copy(&weights, &copy).unwrap();
    let missing = tmp.path().join("no/such/dir/a.safetensors");
    let run = |w: &Path, out: &Path, extra: &[&str]| {
        let mut v = vec![
            "finetune",
            "--set",
            s(&set),
            "--steps",
            "1",
            "--weights",
            s(w),
        ];
        // the model settings of `common`, with other weights
        v.extend_from_slice(&common[2..]);
        v.extend(["-o", s(out)]);
        v.extend_from_slice(extra);
        fails(&v)
    };
    let fresh = tmp.path().join("fresh.safetensors");
    let onnx = shared.join("reference/dav2/tiny-metric.onnx");
    for (w, out, extra, want) in [
        (&copy, &copy, &[][..], "is an input of the run"),
        (&weights, &missing, &[], "does not exist"),
        (&weights, &fresh, &["--lr", "1e308"], "is above 1"),
        (
            &weights,
            &fresh,
            &["--lr", "0.5", "--head-lr-mult", "10"],
            "is above 1",
        ),
        (&weights, &fresh, &["--set", s(&set)], "is given twice"),
        (
            &weights,
            &fresh,
            &["--dtype", "int8"],
            "fine-tuning trains in f32",
        ),
        (&onnx, &fresh, &[], "an ONNX model cannot be trained"),
        (
            &weights,
            &fresh,
            &["--lora-alpha", "1e30"],
            "more than 1000 × the rank",
        ),
    ] {
        let e = run(w, out, extra);
        assert!(e.contains(want), "{extra:?}: {e}");
    }
    assert!(!fresh.exists());
    assert_eq!(
        std::fs::read(&copy).unwrap(),
        std::fs::read(&weights).unwrap()
    );
    // merging into an input, an ONNX model, a folder as the output, options of how a model
    // runs: refused by name
    let onnx = shared.join("reference/dav2/tiny-metric-392.onnx");
    let folder = tmp.path().join("a-folder");
    std::fs::create_dir(&folder).unwrap();
    for (w, out, extra, says) in [
        (copy.as_path(), adapter.as_path(), &[][..], "is an input"),
        (copy.as_path(), copy.as_path(), &[][..], "is an input"),
        (
            onnx.as_path(),
            fresh.as_path(),
            &[][..],
            "an ONNX model cannot be merged",
        ),
        (copy.as_path(), folder.as_path(), &[][..], "is a folder"),
        (
            copy.as_path(),
            fresh.as_path(),
            &["--dtype", "bf16"][..],
            "--dtype",
        ),
        (
            copy.as_path(),
            fresh.as_path(),
            &["--backend", "onnx"][..],
            "--backend onnx",
        ),
    ] {
        let mut args = vec![
            "lora",
            "merge",
            "--weights",
            s(w),
            "--model",
            s(&config),
            "--lora",
            s(&adapter),
            "-o",
            s(out),
        ];
        args.extend_from_slice(extra);
        let e = fails(&args);
        assert!(e.contains(says), "{extra:?}: {e}");
    }
    assert!(!fresh.exists());
    assert_eq!(
        std::fs::read(&copy).unwrap(),
        std::fs::read(&weights).unwrap()
    );
    // a predict run into a folder that holds an older index, stopped by an unreadable image,
    // leaves no index describing its files
    let stale = tmp.path().join("stale");
    std::fs::create_dir(&stale).unwrap();
    std::fs::copy(
        tmp.path().join("p1").join("predictions.json"),
        stale.join("predictions.json"),
    )
    .unwrap();
    let truncated = tmp.path().join("truncated.png");
    std::fs::write(&truncated, &std::fs::read(&rgb).unwrap()[..100]).unwrap();
    let e = fails(
        &[
            &["predict"][..],
            &common,
            &["-o", s(&stale), s(&rgb), s(&truncated)],
        ]
        .concat(),
    );
    assert!(e.contains("truncated.png"), "{e}");
    assert!(!stale.join("predictions.json").exists());
    // Nothing was written over the corrupt file by the failed runs.
    assert_eq!(std::fs::read(&corrupt).unwrap(), b"not an adapter");
}

/// Tensors of an adapter file (LoRA matrices and trained head tensors), by name, as f32 values.
fn adapter_values(p: &Path) -> Vec<(String, Vec<f32>)> {
    let a = moma_depth::candle::train::Adapter::load(p).unwrap();
    a.tensors
        .iter()
        .chain(&a.base)
        .map(|(k, t)| (k.clone(), t.flatten_all().unwrap().to_vec1().unwrap()))
        .collect()
}

/// SILog (official Depth Anything V2: `sqrt(mean d² − 0.5 mean² d)`, `d = ln gt − ln pred`) of
/// a prediction (metres, `moma predict`'s `.npy` at image resolution) against a ground-truth
/// PNG (uint16 mm, 0 = none), over pixels with ground truth in (0, 20] m; computed here in f64,
/// independently of moma's loss code. A prediction ≤ 0 at such a pixel fails the test.
fn silog_vs_png(pred: &ndarray::Array2<f32>, gt_png: &Path) -> f64 {
    let gt = image::open(gt_png).unwrap().to_luma16();
    assert_eq!(
        (gt.height() as usize, gt.width() as usize),
        pred.dim(),
        "{}",
        gt_png.display()
    );
    let (mut n, mut s1, mut s2) = (0.0f64, 0.0f64, 0.0f64);
    for ((y, x), &p) in pred.indexed_iter() {
        let g = f64::from(gt.get_pixel(x as u32, y as u32)[0]) / 1000.0;
        if g <= 0.0 || g > 20.0 {
            continue;
        }
        assert!(p > 0.0 && p.is_finite(), "prediction {p} at ({y}, {x})");
        let d = g.ln() - f64::from(p).ln();
        n += 1.0;
        s1 += d;
        s2 += d * d;
    }
    assert!(n > 0.0);
    (s2 / n - 0.5 * (s1 / n).powi(2)).sqrt()
}

/// Regression: the run that lost its trained head and the run that turned NaN at `--lr 1e-3`,
/// both with the default head multiplier. Every step finishes, the loss falls, the validation
/// loss recomputed from the written adapter through the inference path equals the trainer's to
/// 1e-5, and the SILog of `moma predict --lora` on the set's frames (computed here, outside moma)
/// falls from the base model's, with and without `--train-head`; with it, much further.
#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn trained_head_reaches_inference_and_lr_1e3_trains_without_nan() {
    let Some(shared) = shared() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let (weights, config) = tiny_metric_model(&shared, tmp.path());
    let set = shared.join("data/graspnet6dof-table");
    let model = tiny_model_flags(&weights, &config, "266");
    let mut frames: Vec<PathBuf> = std::fs::read_dir(set.join("frames"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    frames.sort();
    // Mean SILog over the set's frames of `moma predict` (with `extra`, e.g. `--lora A`).
    let predicted_silog = |extra: &[&str], tag: &str| -> f64 {
        let mut sum = 0.0;
        for (i, f) in frames.iter().enumerate() {
            let out = tmp.path().join(format!("{tag}-{i}"));
            let rgb = f.join("rgb.png");
            let mut a: Vec<&str> = vec!["predict"];
            a.extend(&model);
            a.extend(extra);
            a.extend(["-o", s(&out), s(&rgb)]);
            ok(&a);
            let npy = std::fs::read_dir(&out)
                .unwrap()
                .map(|e| e.unwrap().path())
                .find(|p| p.extension().is_some_and(|e| e == "npy"))
                .unwrap();
            let pred: ndarray::Array2<f32> = ndarray_npy::read_npy(npy).unwrap();
            sum += silog_vs_png(&pred, &f.join("depth.png"));
        }
        sum / frames.len() as f64
    };
    let base = predicted_silog(&[], "base");
    let mut adapted = vec![];
    for train_head in [true, false] {
        let adapter = tmp.path().join(format!("head-{train_head}.safetensors"));
        let mut a: Vec<&str> = vec!["finetune", "--set", s(&set)];
        a.extend(&model);
        a.extend([
            "--lora-rank",
            "8",
            "--steps",
            "60",
            "--seed",
            "1",
            "--lr",
            "1e-3",
            "-o",
            s(&adapter),
            "--json",
        ]);
        if train_head {
            a.push("--train-head");
        }
        let j: serde_json::Value = serde_json::from_str(&ok(&a)).unwrap();
        eprintln!("--train-head {train_head}: {j:#}");
        assert_eq!(j["steps"], 60);
        let f = |k: &str| {
            j[k].as_f64()
                .unwrap_or_else(|| panic!("{k} missing in {j}"))
        };
        assert!(
            f("train_loss_last") < f("train_loss_first"),
            "training loss did not fall"
        );
        assert!(
            f("val_loss_after") < f("val_loss_before"),
            "validation loss did not fall"
        );
        let (after, reload) = (f("val_loss_after"), f("val_loss_after_reload"));
        assert!(
            (after - reload).abs() <= 1e-5,
            "val_loss_after {after} vs val_loss_after_reload {reload}"
        );
        // The trained head is in the adapter (and only with --train-head).
        let loaded = moma_depth::candle::train::Adapter::load(&adapter).unwrap();
        assert_eq!(loaded.base.is_empty(), !train_head);
        let silog = predicted_silog(&["--lora", s(&adapter)], &format!("lora-{train_head}"));
        eprintln!(
            "SILog of moma predict on the set: base {base:.4}, adapter (--train-head {train_head}) {silog:.4}"
        );
        assert!(silog < base, "predict --lora SILog {silog} vs base {base}");
        adapted.push(silog);
    }
    // The head's training reaches inference: it lowers the SILog well below LoRA alone.
    assert!(
        adapted[0] < 0.5 * adapted[1],
        "with the head {} vs LoRA alone {}",
        adapted[0],
        adapted[1]
    );
}

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn resume_continues_bit_for_bit_and_crops_are_checked() {
    let Some(shared) = shared() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let (weights, config) = tiny_metric_model(&shared, tmp.path());
    let set = shared.join("data/gqcnn-primesense");
    // Non-square frames (640×480 → the whole network-size frame, 4:3), batch 2 with gradient
    // accumulation, LoRA dropout, augmentation, a trained head and clipping: every random draw
    // and every optimiser state must come back on resume.
    let base: Vec<&str> = [
        &["finetune", "--set", s(&set)][..],
        &tiny_model_flags(&weights, &config, "56"),
        &[
            "--steps",
            "4",
            "--batch",
            "2",
            "--accumulate",
            "2",
            "--lora-rank",
            "2",
            "--lora-dropout",
            "0.1",
            "--train-head",
            "--head-lr-mult",
            "0.1",
            "--clip-grad-norm",
            "0.5",
            "--lr",
            "1e-2",
            "--seed",
            "3",
            "--json",
        ][..],
    ]
    .concat();
    let run = |extra: &[&str]| -> serde_json::Value {
        let mut a = base.clone();
        a.extend(extra);
        serde_json::from_str(&ok(&a)).unwrap()
    };
    let straight = tmp.path().join("straight.safetensors");
    let j_straight = run(&["-o", s(&straight)]);
    assert_eq!(j_straight["steps"], 4);
    assert!(tmp.path().join("straight.optim.safetensors").is_file());
    let half = tmp.path().join("half.safetensors");
    let j = run(&["--stop-after", "2", "-o", s(&half)]);
    assert_eq!(j["steps"], 2);
    let resumed = tmp.path().join("resumed.safetensors");
    let j = run(&["--resume", s(&half), "-o", s(&resumed)]);
    assert_eq!(j["steps"], 2);
    let (a, b) = (adapter_values(&straight), adapter_values(&resumed));
    assert_eq!(a.len(), b.len());
    for ((ka, va), (kb, vb)) in a.iter().zip(&b) {
        assert_eq!(ka, kb);
        assert!(
            va.iter().zip(vb).all(|(x, y)| x.to_bits() == y.to_bits()),
            "{ka}: 2 + resume + 2 steps differ from 4 steps"
        );
    }
    // The GPU's operations on the CPU (hidden `--portable-ops`): the same 4 steps to f32
    // round-off (their gradients agree to ~1e-6; AdamW's first steps move each weight by about
    // lr · sign(g), so a weight whose gradient is near zero may move differently: compared to
    // the largest weight).
    let portable = tmp.path().join("portable.safetensors");
    let jp = run(&["--portable-ops", "-o", s(&portable)]);
    let (l, lp) = (
        j_straight["train_loss_last"].as_f64().unwrap(),
        jp["train_loss_last"].as_f64().unwrap(),
    );
    assert!(((l - lp) / l).abs() < 1e-4, "train loss {lp} vs {l}");
    // The trained head (in the adapter since format v2) gets a wider bound: its ReLU
    // pre-activations lie within f32 round-off of a kink on this random-weight model, so a few
    // pixels' gradients differ between the two op sets (see F32_HEAD_GRAD_TOL in
    // moma-depth/tests/lora_parity.rs), and Adam turns a small gradient's sign into a whole step.
    let mut worst = 0f32;
    for ((ka, va), (_, vp)) in a.iter().zip(&adapter_values(&portable)) {
        let scale = va.iter().fold(0f32, |m, v| m.max(v.abs()));
        let diff = va
            .iter()
            .zip(vp)
            .fold(0f32, |m, (x, y)| m.max((x - y).abs()));
        let bound = if ka.starts_with("depth_head.") {
            3e-3
        } else {
            1e-3
        };
        worst = worst.max(diff / scale);
        assert!(
            diff <= bound * scale,
            "{ka}: portable ops differ by {diff} (max {scale})"
        );
    }
    eprintln!(
        "--portable-ops: train loss {lp} vs {l}; adapters differ by at most {worst:.1e} of their largest value"
    );
    // Resume with other settings: refused, naming the setting.
    let (x_out, y_out) = (
        tmp.path().join("x.safetensors"),
        tmp.path().join("y.safetensors"),
    );
    let mut other_lr = base.clone();
    other_lr.extend(["--resume", s(&half), "-o", s(&x_out)]);
    let i = other_lr.iter().position(|&x| x == "1e-2").unwrap();
    other_lr[i] = "2e-2";
    let e = fails(&other_lr);
    assert!(e.contains("optim.lr (state 0.01, this run 0.02)"), "{e}");
    // An adapter without its optimiser state: refused.
    let lonely = tmp.path().join("lonely.safetensors");
    std::fs::copy(&half, &lonely).unwrap();
    let mut a = base.clone();
    a.extend(["--resume", s(&lonely), "-o", s(&y_out)]);
    assert!(fails(&a).contains("no optimiser state"));
    assert!(!x_out.exists() && !y_out.exists());

    // Crops: a non-square crop trains; too large or not multiples of 14 is an error.
    let crop = tmp.path().join("crop.safetensors");
    let j = run(&["--crop", "42x56", "--stop-after", "1", "-o", s(&crop)]);
    assert_eq!(j["steps"], 1);
    let e = fails(&[&base[..], &["--crop", "560x560", "-o", s(&crop)]].concat());
    assert!(e.contains("larger than the network-size frames"), "{e}");
    let e = fails(&[&base[..], &["--crop", "50x56", "-o", s(&crop)]].concat());
    assert!(e.contains("multiples of 14"), "{e}");
}

/// Text output to a log file (stderr not a terminal: the progress bar is hidden) still has every
/// validation loss (`bar.println` on a hidden bar printed nothing).
#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn validation_losses_reach_a_log_file() {
    let Some(shared) = shared() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let (weights, config) = tiny_metric_model(&shared, tmp.path());
    let adapter = tmp.path().join("a.safetensors");
    let set = shared.join("data/gqcnn-primesense");
    let args = [
        &["finetune", "--set", s(&set)][..],
        &tiny_model_flags(&weights, &config, "28"),
        &["--steps", "2", "--val-every", "1", "-o", s(&adapter)],
    ]
    .concat();
    let out = common::moma(&args);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    for step in [1, 2] {
        assert!(
            stderr.contains(&format!("step {step}: validation loss ")),
            "{stderr}"
        );
    }
    // and what the numbers are (random-weight models: not depth accuracy)
    assert!(
        stderr.contains("note: losses of the given weights"),
        "{stderr}"
    );
    // --json lists them, and the last is the report's final validation loss (the same
    // network on the same frames)
    let j: serde_json::Value =
        serde_json::from_str(&ok(&[&args[..], &["--json"]].concat())).unwrap();
    let v = j["validations"].as_array().expect("validations");
    assert_eq!(
        v.iter()
            .map(|x| x["step"].as_u64().unwrap())
            .collect::<Vec<_>>(),
        [1, 2],
        "{j}"
    );
    let last = v[1]["loss"].as_f64().unwrap();
    let after = j["val_loss_after"].as_f64().unwrap();
    assert!((last - after).abs() <= 1e-6 * after.abs().max(1.0), "{j}");
}
