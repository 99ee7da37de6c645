//! CPU time (not wall time) of anchor selection + re-alignment per 640×480 frame, for a loaded
//! shared machine where criterion's wall-clock numbers include waiting for a core.
//! `cargo run --release -p moma-core --example realign_cputime`

use moma_core::MetricDepth;
use moma_core::normalise::AlignSpace;
use moma_core::realign::{AnchorStore, RealignConfig, realign_in_place};
use ndarray::{Array2, Array3};

fn cpu_s() -> f64 {
    // utime + stime of this process, clock ticks (100 Hz) from /proc/self/stat
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let t = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok()).unwrap_or(0.0);
    (t(11) + t(12)) / 100.0
}

fn main() {
    let (w, h) = (640usize, 480usize);
    let grey = |u: usize, v: usize| {
        let (x, y) = (u as f32, v as f32);
        110.0 + 35.0 * (x / 12.0).sin() * (y / 18.0).cos() + 25.0 * ((x + 2.0 * y) / 26.0).sin()
    };
    let gt = MetricDepth::new(Array2::from_shape_fn((h, w), |(v, _)| {
        0.8 + 2.5e-4 * v as f32
    }));
    let calib = Array3::from_shape_fn((h, w, 3), |(v, u, _)| grey(u, v) as u8);
    let frame = Array3::from_shape_fn((h, w, 3), |(v, u, _)| {
        if (200..400).contains(&u) && (160..320).contains(&v) {
            200
        } else {
            (0.9 * grey(u, v)) as u8
        }
    });
    let store = AnchorStore::new(&moma_io::grey_half(calib.view()).expect("grey"), &gt)
        .and_then(|s| s.with_one_shot(&gt))
        .expect("store");
    let one_shot = gt.depth_m.mapv(|z| 1.05 * z);
    let config = RealignConfig::default();
    let mut depth = one_shot.clone();
    let n = 2000;
    let t0 = cpu_s();
    for _ in 0..n {
        depth.assign(&one_shot);
        let grey = moma_io::grey_half(frame.view()).expect("grey");
        let r = realign_in_place(
            &store,
            &grey,
            AlignSpace::Inverse,
            &config,
            &mut depth.view_mut(),
        )
        .expect("realign");
        assert!(r.accepted);
    }
    let per = (cpu_s() - t0) / n as f64;
    println!(
        "anchor selection + re-alignment (incl. a 1.2 MB copy): {:.3} ms CPU per 640x480 frame ({n} frames)",
        per * 1e3
    );
}
