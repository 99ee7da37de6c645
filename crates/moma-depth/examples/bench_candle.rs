//! Latency and peak memory of the candle backend on one frame.
//!
//! ```text
//! cargo run --release -p moma-depth --example bench_candle -- \
//!     [--weights W.safetensors] [--model vits|vitb|vitl] [--height 518] [--width 686] [--runs 5] \
//!     [--dtype f32,int8]
//! ```
//! With several `--dtype`s the models run side by side, alternating run by run; each one's
//! output is compared with the first's (max and mean absolute difference over the first's
//! output range).
//! Without `--weights` it loads `$MOMA_SHARED_DIR/reference/dav2/vits-rel.safetensors` (random
//! ViT-S weights; latency does not depend on the values). Prints every run (wall and CPU seconds),
//! the medians of the runs after one warm-up, and the process's peak RSS (`VmHWM` of
//! `/proc/self/status`).

use std::path::PathBuf;
use std::time::Instant;

use moma_depth::candle::{CandleDepthModel, DepthAnythingConfig, open_device};
use moma_depth::{DepthModel, Head};
use ndarray::Array3;

fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// User + system CPU seconds of this process so far (`/proc/self/stat`, 100 ticks per second).
fn cpu_seconds() -> f64 {
    std::fs::read_to_string("/proc/self/stat")
        .ok()
        .and_then(|s| {
            let rest = s.rsplit_once(')')?.1;
            let f: Vec<&str> = rest.split_whitespace().collect();
            let u: f64 = f.get(11)?.parse().ok()?;
            let k: f64 = f.get(12)?.parse().ok()?;
            Some((u + k) / 100.0)
        })
        .unwrap_or(f64::NAN)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut weights: Option<PathBuf> = None;
    let mut model = "vits".to_string();
    let (mut height, mut width, mut runs) = (518usize, 686usize, 5usize);
    let mut dtypes = vec![moma_depth::Precision::F32];
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut val = || args.next().ok_or(format!("{a} needs a value"));
        match a.as_str() {
            "--weights" => weights = Some(PathBuf::from(val()?)),
            "--model" => model = val()?,
            "--height" => height = val()?.parse()?,
            "--width" => width = val()?.parse()?,
            "--runs" => runs = val()?.parse()?,
            "--dtype" => {
                dtypes = val()?
                    .split(',')
                    .map(str::parse)
                    .collect::<Result<_, String>>()?
            }
            other => return Err(format!("unknown argument {other}").into()),
        }
    }
    let weights = weights.unwrap_or_else(|| {
        let shared = std::env::var_os("MOMA_SHARED_DIR")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"));
        shared.join("reference/dav2/vits-rel.safetensors")
    });
    let config = match model.as_str() {
        "vits" => DepthAnythingConfig::vit_small(Head::Relative),
        "vitb" => DepthAnythingConfig::vit_base(Head::Relative),
        "vitl" => DepthAnythingConfig::vit_large(Head::Relative),
        other => return Err(format!("unknown model {other}").into()),
    };
    let device = open_device(moma_depth::DeviceRequest::Auto)?;
    let mut nets = vec![];
    for &p in &dtypes {
        let t = Instant::now();
        let net =
            CandleDepthModel::load_with_precision(&weights, config.clone(), &device, p, None)?;
        println!(
            "loaded {} ({p:?}) on {device:?} in {:.2} s",
            weights.display(),
            t.elapsed().as_secs_f64()
        );
        nets.push(net);
    }
    let input = Array3::<f32>::from_shape_fn((3, height, width), |(c, y, x)| {
        ((c * 7 + y * 3 + x) % 17) as f32 / 17.0 - 0.5
    });
    let mut times = vec![vec![]; nets.len()];
    let mut cpu = vec![vec![]; nets.len()];
    let mut outs = vec![None; nets.len()];
    for i in 0..=runs {
        for (d, net) in nets.iter_mut().enumerate() {
            let (t, c) = (Instant::now(), cpu_seconds());
            let out = net.forward_net(&input)?;
            let (s, cs) = (t.elapsed().as_secs_f64(), cpu_seconds() - c);
            println!(
                "run {i} {:?}{}: {s:.3} s, {cs:.2} CPU-s (out {:?})",
                dtypes[d],
                if i == 0 { " (warm-up)" } else { "" },
                out.dim()
            );
            if i > 0 {
                times[d].push(s);
                cpu[d].push(cs);
            }
            outs[d] = Some(out);
        }
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let anchor = median(&mut times[0].clone());
    for d in 0..nets.len() {
        let (m, mc) = (median(&mut times[d]), median(&mut cpu[d]));
        let err = match (&outs[0], &outs[d]) {
            (Some(a), Some(b)) if d > 0 => {
                let (lo, hi) = a
                    .iter()
                    .fold((f32::MAX, f32::MIN), |(l, h), &v| (l.min(v), h.max(v)));
                let range = f64::from(hi - lo).max(1e-12);
                let diffs: Vec<f64> = a
                    .iter()
                    .zip(b)
                    .map(|(x, y)| f64::from((x - y).abs()))
                    .collect();
                let max = diffs.iter().copied().fold(0.0, f64::max);
                let mean = diffs.iter().sum::<f64>() / diffs.len() as f64;
                format!(
                    ", vs {:?}: max {:.2e}, mean {:.2e} of the output range",
                    dtypes[0],
                    max / range,
                    mean / range
                )
            }
            _ => String::new(),
        };
        println!(
            "{model} {height}x{width} {:?}: median {m:.3} s ({:.2}× the {:?} time), {mc:.2} CPU-s over {runs} runs{err}",
            dtypes[d],
            m / anchor,
            dtypes[0]
        );
    }
    println!(
        "peak RSS {:.0} MiB (all models), {} rayon threads",
        peak_rss_mib().unwrap_or(f64::NAN),
        rayon::current_num_threads()
    );
    Ok(())
}
