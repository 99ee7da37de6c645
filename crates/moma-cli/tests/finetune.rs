//! `moma finetune` / `--lora` / `moma lora merge` end to end on the tiny random-weight metric
//! model of `shared/reference/dav2` and a shared moma set. The loss falls because the adapters fit
//! this data; random weights predict nothing meaningful, so this checks the machinery only.
#![cfg(feature = "candle")]

use std::path::{Path, PathBuf};

mod common;
use common::{fails, ok, s};

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

const TINY: &str = r#"{"embed_dim":64,"depth":4,"num_heads":2,"intermediate_layers":[0,1,2,3],"features":16,"out_channels":[8,16,32,64],"head":"metric","max_depth":20}"#;

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn finetune_lowers_the_loss_and_the_adapter_loads_everywhere() {
    let Some(shared) = shared() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("tiny-metric.json");
    std::fs::write(&config, TINY).unwrap();
    let weights = shared.join("reference/dav2/tiny-metric.safetensors");
    let set = shared.join("data/gqcnn-primesense");
    let adapter = tmp.path().join("a.safetensors");
    let common = [
        "--weights",
        s(&weights),
        "--model",
        s(&config),
        "--input-size",
        "56",
        "--device",
        "cpu",
    ];
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
    // Nothing was written over the corrupt file by the failed runs.
    assert_eq!(std::fs::read(&corrupt).unwrap(), b"not an adapter");
}
