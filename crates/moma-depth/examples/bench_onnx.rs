//! Latency and peak memory of the ONNX Runtime backend on one Depth Anything V2 export.
//!
//! ```text
//! export ORT_DYLIB_PATH="$(.ci/install-onnxruntime.sh)"
//! cargo run -p moma-depth --release --no-default-features --features onnx --example bench_onnx -- \
//!     [MODEL.onnx] [--runs 10] [--threads 2] [--opt all|extended|basic|disable] [--no-spin] \
//!     [--ftz] [--no-mem-pattern] [--save-optimized PATH]
//! ```
//! `MODEL.onnx` defaults to `../shared/reference/dav2/vits-rel.onnx` (ViT-S, fixed 518×686 input).
//! The input is `NAME.input.npy` next to the model when present, else zeros of the model's fixed
//! size. Prints load time, the first (warm-up) run, the median/min/max of the timed runs, and the
//! peak resident set size (`VmHWM` of /proc/self/status).

use std::path::PathBuf;
use std::time::Instant;

use moma_depth::onnx::{OnnxDepthModel, OnnxOptions, OptimizationLevel};
use moma_depth::{Backbone, DepthModel, Head, ModelSpec};
use ndarray::Array3;

fn status_kib(key: &str) -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    s.lines()
        .find(|l| l.starts_with(key))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

/// CPU time of the whole process (all threads), seconds (`utime + stime` of /proc/self/stat,
/// assuming the usual 100 clock ticks per second).
fn cpu_seconds() -> f64 {
    let Ok(s) = std::fs::read_to_string("/proc/self/stat") else {
        return f64::NAN;
    };
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = s.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| {
        f.get(i)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(f64::NAN)
    };
    (tick(11) + tick(12)) / 100.0
}

fn usage() -> ! {
    eprintln!(
        "usage: bench_onnx [MODEL.onnx] [--runs N] [--threads N] [--opt all|extended|basic|disable] \
         [--no-spin] [--ftz] [--no-mem-pattern] [--save-optimized PATH]"
    );
    std::process::exit(2)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut model_path: Option<PathBuf> = None;
    let mut runs = 10usize;
    let mut opts = OnnxOptions {
        intra_threads: Some(2),
        ..OnnxOptions::default()
    };
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--runs" => {
                runs = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .unwrap_or_else(|| usage())
            }
            "--threads" => {
                opts.intra_threads = Some(
                    args.next()
                        .and_then(|v| v.parse().ok())
                        .unwrap_or_else(|| usage()),
                );
            }
            "--opt" => {
                opts.optimization_level = match args.next().as_deref() {
                    Some("all") => OptimizationLevel::All,
                    Some("extended") => OptimizationLevel::Extended,
                    Some("basic") => OptimizationLevel::Basic,
                    Some("disable") => OptimizationLevel::Disable,
                    _ => usage(),
                };
            }
            "--no-spin" => opts.intra_op_spinning = false,
            "--ftz" => opts.flush_to_zero = true,
            "--no-mem-pattern" => opts.memory_pattern = false,
            "--save-optimized" => {
                opts.optimized_model_path = Some(args.next().unwrap_or_else(|| usage()).into())
            }
            "-h" | "--help" => usage(),
            s if s.starts_with('-') => usage(),
            s => model_path = Some(s.into()),
        }
    }
    let model_path = model_path.unwrap_or_else(|| {
        let shared = std::env::var_os("MOMA_SHARED_DIR")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"));
        shared.join("reference/dav2/vits-rel.onnx")
    });

    let lib = moma_depth::onnx::init_runtime()?;
    println!("library   {}", lib.display());
    println!("build     {}", moma_depth::onnx::runtime_info()?);
    println!("model     {}", model_path.display());
    println!("options   {opts:?}");

    let spec = ModelSpec {
        backbone: Backbone::Vits,
        head: Head::Relative,
        input_size: 518,
    };
    let rss_before = status_kib("VmRSS:").unwrap_or(0);
    let t = Instant::now();
    let mut model = OnnxDepthModel::load(&model_path, spec, &opts)?;
    let load_s = t.elapsed().as_secs_f64();

    let npy = model_path.with_extension("input.npy");
    let input: Array3<f32> = if npy.is_file() {
        ndarray_npy::read_npy(&npy)?
    } else {
        let (h, w) = model.fixed_input_hw().unwrap_or((518, 686));
        Array3::zeros((3, h, w))
    };
    let (_, h, w) = input.dim();
    println!("input     3x{h}x{w}");
    println!("load      {load_s:.3} s");

    let t = Instant::now();
    let out = model.forward_net(&input)?;
    println!(
        "warm-up   {:.3} s  (output {}x{})",
        t.elapsed().as_secs_f64(),
        out.nrows(),
        out.ncols()
    );

    let mut times = Vec::with_capacity(runs);
    let cpu0 = cpu_seconds();
    for _ in 0..runs {
        let t = Instant::now();
        let out = model.forward_net(&input)?;
        times.push(t.elapsed().as_secs_f64());
        std::hint::black_box(out);
    }
    let cpu_per_run = (cpu_seconds() - cpu0) / runs.max(1) as f64;
    times.sort_by(f64::total_cmp);
    let median = if times.is_empty() {
        f64::NAN
    } else if times.len() % 2 == 1 {
        times[times.len() / 2]
    } else {
        0.5 * (times[times.len() / 2 - 1] + times[times.len() / 2])
    };
    println!(
        "runs      {runs}: median {median:.3} s, min {:.3} s, max {:.3} s",
        times.first().copied().unwrap_or(f64::NAN),
        times.last().copied().unwrap_or(f64::NAN)
    );
    println!("cpu       {cpu_per_run:.3} CPU-s per run (all threads; spinning counts)");
    let hwm = status_kib("VmHWM:").unwrap_or(0);
    println!(
        "peak RSS  {:.1} MiB (VmHWM; {:.1} MiB before loading the model)",
        hwm as f64 / 1024.0,
        rss_before as f64 / 1024.0
    );
    Ok(())
}
