//! Parallel grasps planned on ALIGNED depth of a real set, scored on its ground truth (proxy).
//! Runs only when `MOMA_GRASP_ALIGNED_DIR` names a folder of `<frame>.depth.npy` files written by
//! `moma align` for the set `MOMA_GRASP_ALIGNED_SET` (default `graspnet6dof-table`) under
//! `MOMA_SHARED_DIR/data`; with SIMULATED predictions these are not depth-model results.
//! Asserts at least `MOMA_GRASP_ALIGNED_MIN_RATE` (default 0.6) success; prints every trial.
//!
//! ```text
//! moma calibrate --pred PREDS/blue_mug.npy --gt SET/frames/blue_mug/depth.png \
//!     --camera SET/camera.json -o /tmp/cal.json
//! moma align --calib /tmp/cal.json --pred PREDS/*.npy --output /tmp/aligned
//! MOMA_GRASP_ALIGNED_DIR=/tmp/aligned cargo test -p moma-grasp --release --test aligned_real \
//!     -- --nocapture
//! ```

use std::path::PathBuf;

use moma_grasp::{
    Gripper, MIN_TRIAL_COMPONENT_PX, ParallelConfig, ParallelJaw, Scene, SceneConfig, ScoreConfig,
    mask_components, plan_parallel, score_grasp,
};
use moma_io::MomaSet;

#[test]
fn parallel_grasps_planned_on_aligned_depth_succeed_on_ground_truth() {
    let Some(aligned) = std::env::var_os("MOMA_GRASP_ALIGNED_DIR").map(PathBuf::from) else {
        eprintln!("SKIPPED: MOMA_GRASP_ALIGNED_DIR not set");
        return;
    };
    let shared = std::env::var_os("MOMA_SHARED_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/work/shared"));
    let name = std::env::var("MOMA_GRASP_ALIGNED_SET").unwrap_or("graspnet6dof-table".into());
    let set = MomaSet::open(shared.join("data").join(&name)).unwrap();
    let cfg = SceneConfig::default();
    let jaw = ParallelJaw::default();
    let (mut trials, mut ok) = (0usize, 0usize);
    for frame in &set.frames {
        let gt_depth = frame.load_depth().unwrap();
        let path = aligned.join(format!("{}.depth.npy", frame.id));
        let pred = moma_core::MetricDepth::new(moma_io::read_npy_f32(&path).unwrap());
        let masks: Vec<Option<moma_core::Mask>> = match frame.load_mask().unwrap() {
            Some(m) => mask_components(&m, MIN_TRIAL_COMPONENT_PX)
                .into_iter()
                .map(Some)
                .collect(),
            None => vec![None],
        };
        for (k, mask) in masks.iter().enumerate() {
            trials += 1;
            let gt = Scene::build(&gt_depth, &set.camera, mask.as_ref(), &cfg).unwrap();
            let planned = Scene::build(&pred, &set.camera, mask.as_ref(), &cfg).unwrap();
            let out = plan_parallel(&planned, &jaw, &ParallelConfig::default()).unwrap();
            let Some(g) = out.grasps.first() else {
                eprintln!("{}#{k}: no grasp: {:?}", frame.id, out.no_grasp_reason);
                continue;
            };
            let s = score_grasp(&gt, g, &Gripper::Parallel(jaw), &ScoreConfig::default()).unwrap();
            eprintln!("{}#{k}: {s:?} {g:?}", frame.id);
            ok += usize::from(s.success);
        }
    }
    eprintln!("{name} parallel on aligned depth: {ok}/{trials} (proxy)");
    assert!(trials > 0);
    let min_rate: f64 = std::env::var("MOMA_GRASP_ALIGNED_MIN_RATE")
        .ok()
        .and_then(|r| r.parse().ok())
        .unwrap_or(0.6);
    assert!(ok as f64 >= min_rate * trials as f64, "{ok}/{trials}");
}
