//! The encoder's matrix products at ViT-S 518×686 (1 814 tokens) through each CPU kernel, side
//! by side in one run: candle's f32 `matmul` (the `gemm` crate, what `--dtype f32` uses),
//! candle's quantised `Q8_0` matmul (ggml's: 8-bit weights and activations in blocks of 32),
//! and moma's int8 (VNNI) and bf16 layers (`--dtype int8|bf16`). Medians of `--reps` calls,
//! after one warm-up, and each output's max error against f32 over the f32 output's range.
//! Then the DPT head's stride-1 3×3 convolutions by im2col and by Winograd F(2×2, 3×3) (what
//! the model runs), each call including its output's allocation.
//!
//! ```text
//! cargo run --release -p moma-depth --example cpu_kernels -- [--reps 10]
//! ```

use std::time::Instant;

use candle_core::quantized::{GgmlDType, QMatMul, QTensor};
use candle_core::{Device, Module, Tensor};
use moma_depth::candle::{ConvPath, PackedLayer, conv3x3_by};

/// A seeded uniform value in [-1, 1).
fn uniform(state: &mut u64) -> f32 {
    *state = state
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
}

fn median(mut t: Vec<f64>) -> f64 {
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

fn time<T>(reps: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut out = f();
    let mut t = vec![];
    for _ in 0..reps {
        let s = Instant::now();
        out = f();
        t.push(s.elapsed().as_secs_f64());
    }
    (median(t), out)
}

fn error(got: &[f32], want: &[f32]) -> f64 {
    let (lo, hi) = want
        .iter()
        .fold((f32::MAX, f32::MIN), |(l, h), &v| (l.min(v), h.max(v)));
    let max = got
        .iter()
        .zip(want)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    f64::from(max / (hi - lo))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut reps = 10usize;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--reps" => reps = args.next().ok_or("--reps needs a value")?.parse()?,
            other => return Err(format!("unknown argument {other}").into()),
        }
    }
    let m = 1814;
    let dev = Device::Cpu;
    println!(
        "| layer (k → n) | f32 gemm | candle Q8_0 | moma int8 | moma bf16 | Q8_0 / int8 / bf16 max error |"
    );
    println!("|---|---:|---:|---:|---:|---|");
    let mut st = 1u64;
    for (name, k, n) in [
        ("qkv", 384, 1152),
        ("proj", 384, 384),
        ("fc1", 384, 1536),
        ("fc2", 1536, 384),
    ] {
        let x: Vec<f32> = (0..m * k).map(|_| uniform(&mut st)).collect();
        // W as nn.Linear stores it (n × k) and transposed (k × n)
        let w: Vec<f32> = (0..n * k).map(|_| uniform(&mut st) * 0.05).collect();
        let w_t: Vec<f32> = (0..k * n).map(|i| w[(i % n) * k + i / n]).collect();
        let xt = Tensor::from_slice(&x, (m, k), &dev)?;
        let wt = Tensor::from_slice(&w_t, (k, n), &dev)?;
        let (t_f32, y_f32) = time(reps, || xt.matmul(&wt).unwrap());
        let y_f32: Vec<f32> = y_f32.flatten_all()?.to_vec1()?;
        let q = QMatMul::from_qtensor(QTensor::quantize(
            &Tensor::from_slice(&w, (n, k), &dev)?,
            GgmlDType::Q8_0,
        )?)?;
        let (t_q8, y_q8) = time(reps, || q.forward(&xt).unwrap());
        let y_q8: Vec<f32> = y_q8.flatten_all()?.to_vec1()?;
        let zero = vec![0f32; n];
        let i8l = PackedLayer::int8(&w_t, k, n, &zero)?;
        let (t_i8, y_i8) = time(reps, || i8l.forward(&x, m));
        let b16 = PackedLayer::bf16(&w_t, k, n, &zero)?;
        let (t_b16, y_b16) = time(reps, || b16.forward(&x, m));
        println!(
            "| {name} ({k} → {n}) | {:.2} ms | {:.2} ms ({:.2}×) | {:.2} ms ({:.2}×) | {:.2} ms ({:.2}×) | {:.1e} / {:.1e} / {:.1e} |",
            t_f32 * 1e3,
            t_q8 * 1e3,
            t_q8 / t_f32,
            t_i8 * 1e3,
            t_i8 / t_f32,
            t_b16 * 1e3,
            t_b16 / t_f32,
            error(&y_q8, &y_f32),
            error(&y_i8, &y_f32),
            error(&y_b16, &y_f32)
        );
    }
    println!(
        "{} rayon threads, m = {m} tokens, medians of {reps}",
        rayon::current_num_threads()
    );

    // The DPT head's stride-1 3×3 convolutions (ViT-S at 518×686; ViT-B's widest level)
    println!();
    println!(
        "| convolution (c_in → c_out, h × w) | im2col | Winograd | Winograd max error vs im2col |"
    );
    println!("|---|---:|---:|---|");
    for (c_in, c_out, h, w) in [
        (32, 32, 518, 686),
        (64, 32, 296, 392),
        (64, 64, 148, 196),
        (48, 64, 148, 196),
        (64, 64, 74, 98),
        (64, 64, 37, 49),
        (128, 128, 148, 196),
        (768, 128, 19, 25),
    ] {
        let x: Vec<f32> = (0..c_in * h * w).map(|_| uniform(&mut st)).collect();
        let wt: Vec<f32> = (0..c_out * c_in * 9)
            .map(|_| uniform(&mut st) * 0.1)
            .collect();
        let b: Vec<f32> = (0..c_out).map(|_| uniform(&mut st)).collect();
        let x = Tensor::from_vec(x, (1, c_in, h, w), &dev)?;
        let wt = Tensor::from_vec(wt, (c_out, c_in, 3, 3), &dev)?;
        let b = Tensor::from_vec(b, c_out, &dev)?;
        let run = |path| {
            time(reps, || {
                let y = conv3x3_by(&x, &wt, &b, path).unwrap();
                y.flatten_all().unwrap().to_vec1::<f32>().unwrap()
            })
        };
        let (t_col, y_col) = run(ConvPath::Im2col);
        let (t_win, y_win) = run(ConvPath::Winograd);
        println!(
            "| {c_in} → {c_out}, {h} × {w} | {:.2} ms | {:.2} ms ({:.2}×) | {:.1e} |",
            t_col * 1e3,
            t_win * 1e3,
            t_win / t_col,
            error(&y_win, &y_col)
        );
    }
    Ok(())
}
