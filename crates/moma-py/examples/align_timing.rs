//! Times `Calibration::align` in Rust on a calibration file and a prediction, for comparison
//! with the same call from Python (`benches/python/bench_align.py` runs this example).
//!
//! Usage: `align_timing CALIB.json PRED.npy [REPEATS]`; prints one JSON line
//! `{"median_ms": …, "min_ms": …, "repeats": …}` (wall time of normalisation + alignment,
//! allocation of the output included, file I/O excluded).

use moma_core::AlignOptions;
use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let [_, calib, pred, rest @ ..] = args.as_slice() else {
        return Err("usage: align_timing CALIB.json PRED.npy [REPEATS]".into());
    };
    let repeats: usize = match rest.first() {
        Some(r) => r.parse()?,
        None => 200,
    };
    let file = moma_io::read_calibration(calib)?;
    let pred = moma_io::read_prediction(pred, file.prediction_kind)?;
    // Warm-up (first-touch page faults, LWLR map cache), then timed calls.
    for _ in 0..5 {
        std::hint::black_box(
            file.calibration
                .aligned(&pred, &AlignOptions::default())?
                .depth,
        );
    }
    let mut ms = Vec::with_capacity(repeats);
    for _ in 0..repeats.max(1) {
        let t = Instant::now();
        let depth = file
            .calibration
            .aligned(&pred, &AlignOptions::default())?
            .depth;
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        std::hint::black_box(depth);
    }
    ms.sort_by(f64::total_cmp);
    println!(
        "{{\"median_ms\": {:.4}, \"min_ms\": {:.4}, \"repeats\": {}}}",
        ms[ms.len() / 2],
        ms[0],
        ms.len()
    );
    Ok(())
}
