//! Sanity checks on the real RGB-D sets of the shared data directory.
//!
//! The directory is `$MOMA_SHARED_DIR/data`, else `<workspace root>/../shared/data`. The tests are
//! `#[ignore]`d (cargo lists them as ignored) and run with `-- --include-ignored` (CI does); then a
//! missing folder or set fails.

use std::path::PathBuf;

use moma_io::{MomaSet, read_camera, rgb_size};

/// The shared folder: `$MOMA_SHARED_DIR`, else `../shared` beside the workspace.
///
/// # Panics
/// When it does not exist, naming where it was looked for.
fn shared_dir() -> PathBuf {
    let (dir, from) = match std::env::var_os("MOMA_SHARED_DIR") {
        Some(d) => (PathBuf::from(d), "$MOMA_SHARED_DIR"),
        None => (
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"),
            "../shared beside the workspace (MOMA_SHARED_DIR unset)",
        ),
    };
    assert!(
        dir.is_dir(),
        "this test needs the shared folder, not found at {} ({from}); set MOMA_SHARED_DIR, \
         or run without --include-ignored to skip it",
        dir.display()
    );
    dir
}

/// `shared_dir()/data`.
///
/// # Panics
/// As [`shared_dir`]; when it has no `data/`.
fn shared_data() -> PathBuf {
    let data = shared_dir().join("data");
    assert!(
        data.is_dir(),
        "shared data not found at {} (set MOMA_SHARED_DIR to the directory holding data/)",
        data.display()
    );
    data
}

const SETS: [(&str, usize); 4] = [
    ("gqcnn-primesense", 15),
    ("graspnet6dof-table", 7),
    ("m2t2-table", 3),
    ("cleargrasp-transparent", 2),
];

#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn every_shared_set_opens_and_loads() {
    let data = shared_data();
    for (name, n_frames) in SETS {
        let root = data.join(name);
        assert!(
            root.is_dir(),
            "shared set {name} not present under {}",
            data.display()
        );
        let set = MomaSet::open(&root).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(set.camera, read_camera(root.join("camera.json")).unwrap());
        assert_eq!(set.frames.len(), n_frames, "{name}");
        let ids: Vec<&String> = set.frames.iter().map(|f| &f.id).collect();
        let mut sorted = ids.clone();
        sorted.sort();
        assert_eq!(ids, sorted);
        for frame in &set.frames {
            let ctx = format!("{name}/{}", frame.id);
            let depth = frame.load_depth().unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(depth.size(), set.size(), "{ctx}");
            let valid = depth.valid_count();
            assert!(
                valid > depth.size().pixels() / 4,
                "{ctx}: only {valid} valid depth pixels"
            );
            // Ground truth in plausible metres (tabletop sets: 0.1 m to 10 m).
            let (lo, hi) = depth
                .depth_m
                .iter()
                .filter(|z| z.is_finite())
                .fold((f32::MAX, f32::MIN), |(a, b), &z| (a.min(z), b.max(z)));
            assert!(lo >= 0.1 && hi <= 10.0, "{ctx}: depth range {lo}..{hi} m");
            let rgb = frame.load_rgb().unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(rgb_size(&rgb), set.size(), "{ctx}");
            if let Some(mask) = frame.load_mask().unwrap_or_else(|e| panic!("{e}")) {
                assert_eq!(mask.size(), set.size(), "{ctx}");
                assert!(mask.count() > 0, "{ctx}: empty mask");
            }
            if let Some(raw) = frame.load_raw_depth().unwrap_or_else(|e| panic!("{e}")) {
                assert_eq!(raw.size(), set.size(), "{ctx}");
            }
        }
        if name == "cleargrasp-transparent" {
            assert!(
                set.frames
                    .iter()
                    .all(|f| f.raw_depth.is_some() && f.mask.is_some())
            );
        }
    }
}

/// The one index in ../shared written before the three prediction kinds: zed-da3-office's says
/// `depth`, and its README and `source` say the maps are a metric model's metres, so it reads as
/// `metric-depth` (docs/formats.md "Prediction kinds"), which `raw` and `moma metrics` accept.
#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn the_real_da3_index_reads_as_metric_depth() {
    let dir = shared_data().join("zed-da3-office/predictions");
    let index = moma_io::read_prediction_index(&dir)
        .unwrap()
        .expect("zed-da3-office/predictions has a predictions.json");
    assert_eq!(index.kind, moma_core::PredictionKind::MetricDepth);
    assert!(!index.simulated);
    assert_eq!(index.frames.len(), 3);
}
