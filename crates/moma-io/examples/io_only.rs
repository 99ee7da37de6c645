//! The file I/O of `moma align` alone, as the anchor of its throughput (docs/benchmarks.md):
//! for every prediction file, read it (`read_prediction`), and write the same map as
//! `NAME.depth.png` (uint16 mm) and `NAME.depth.npy` (float32 m) into OUT, in bounded parallel
//! batches as `moma align` runs them (`moma_io::batch`). No normalisation, no alignment.
//!
//! `cargo run --release -p moma-io --example io_only -- OUT KIND FILE.npy...`

use moma_core::{MetricDepth, PredictionKind};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (out, kind, files) = match args.as_slice() {
        [out, kind, files @ ..] if !files.is_empty() => (out, kind, files),
        _ => return Err("usage: io_only OUT KIND FILE.npy...".into()),
    };
    let kind: PredictionKind = kind.parse()?;
    std::fs::create_dir_all(out)?;
    let t = std::time::Instant::now();
    moma_io::batch::map_bounded(
        files.len(),
        moma_io::batch::default_in_flight(),
        |i| -> Result<(), moma_io::IoError> {
            let path = std::path::Path::new(&files[i]);
            let p = moma_io::read_prediction(path, kind)?;
            // as metres (the reciprocal of a disparity): about the depth map `moma align` writes
            let inverse = p.kind == PredictionKind::RelativeDisparity;
            let depth = MetricDepth::new(p.values.mapv(|d| match (inverse, d > 0.0) {
                (false, _) => d,
                (true, true) => 1.0 / d,
                (true, false) => 0.0,
            }));
            let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("frame");
            let base = std::path::Path::new(out).join(stem);
            moma_io::write_depth(base.with_extension("depth.png"), &depth)?;
            moma_io::write_depth(base.with_extension("depth.npy"), &depth)?;
            Ok(())
        },
        |_, ()| Ok(()),
    )?;
    let s = t.elapsed().as_secs_f64();
    println!(
        "io only: {} frames in {s:.2} s, {:.1} frames/s",
        files.len(),
        files.len() as f64 / s
    );
    Ok(())
}
