//! A check on the shared real sets: grasps planned on the ground-truth depth of the opaque
//! sets, top-1 per trial (8-connected mask component ≥ 200 px, or the whole frame without a mask),
//! scored on the same ground truth (the planner's own ceiling), succeed in ≥ 90 % of trials.
//! Proxy scores, not robot results. Skipped when the shared data are absent.

use std::path::PathBuf;

use moma_grasp::{
    FailureReason, Grasp, Gripper, MIN_TRIAL_COMPONENT_PX, ParallelConfig, ParallelJaw, Scene,
    SceneConfig, ScoreConfig, SuctionConfig, SuctionCup, mask_components, plan_parallel,
    plan_suction, score_grasp,
};
use moma_io::MomaSet;

/// The shared data folder; a test that needs it fails naming where it looked (it runs only
/// with --include-ignored, as CI runs it).
fn shared() -> PathBuf {
    let dir = std::env::var_os("MOMA_SHARED_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"))
        .join("data");
    assert!(
        dir.is_dir(),
        "this test needs the shared data, not found at {} (set MOMA_SHARED_DIR)",
        dir.display()
    );
    dir
}

/// (trials, successes, failures) of top-1 grasps planned and scored on the ground truth.
fn run_set(set: &MomaSet, gripper: Gripper) -> (usize, usize, Vec<(String, FailureReason)>) {
    let (mut trials, mut ok, mut fails) = (0, 0, Vec::new());
    let cfg = SceneConfig::default();
    for frame in &set.frames {
        let depth = frame.load_depth().unwrap();
        let masks: Vec<Option<moma_core::Mask>> = match frame.load_mask().unwrap() {
            Some(m) => mask_components(&m, MIN_TRIAL_COMPONENT_PX)
                .into_iter()
                .map(Some)
                .collect(),
            None => vec![None],
        };
        for (k, mask) in masks.iter().enumerate() {
            trials += 1;
            let scene = match Scene::build(&depth, &set.camera, mask.as_ref(), &cfg) {
                Ok(s) => s,
                Err(e) => {
                    eprintln!("{} {k}: {e}", frame.id);
                    fails.push((format!("{}#{k}", frame.id), FailureReason::NoGrasp));
                    continue;
                }
            };
            let out = match gripper {
                Gripper::Parallel(j) => plan_parallel(&scene, &j, &ParallelConfig::default()),
                Gripper::Suction(c) => plan_suction(&scene, &c, &SuctionConfig::default()),
            }
            .unwrap();
            let Some(g): Option<&Grasp> = out.grasps.first() else {
                eprintln!("{} {k}: no grasp: {:?}", frame.id, out.no_grasp_reason);
                fails.push((format!("{}#{k}", frame.id), FailureReason::NoGrasp));
                continue;
            };
            let s = score_grasp(&scene, g, &gripper, &ScoreConfig::default()).unwrap();
            if s.success {
                ok += 1;
            } else {
                fails.push((format!("{}#{k}", frame.id), s.failure.unwrap()));
            }
        }
    }
    (trials, ok, fails)
}

#[test]
#[ignore = "needs ../shared (and a release build): run with --include-ignored (CI does)"]
fn ground_truth_grasps_on_opaque_sets_succeed_in_90_percent_of_trials() {
    let dir = shared();
    let mut per_gripper = [(0usize, 0usize); 2];
    for name in ["gqcnn-primesense", "graspnet6dof-table", "m2t2-table"] {
        let set = MomaSet::open(dir.join(name)).unwrap();
        for (gi, gripper) in [
            Gripper::Parallel(ParallelJaw::default()),
            Gripper::Suction(SuctionCup::default()),
        ]
        .into_iter()
        .enumerate()
        {
            let (t, s, f) = run_set(&set, gripper);
            let kind = match gripper {
                Gripper::Parallel(_) => "parallel",
                Gripper::Suction(_) => "suction",
            };
            eprintln!("{name} {kind}: {s}/{t} (proxy, ground-truth depth) failures {f:?}");
            per_gripper[gi].0 += t;
            per_gripper[gi].1 += s;
        }
    }
    for (kind, (trials, ok)) in ["parallel", "suction"].iter().zip(per_gripper) {
        let rate = ok as f64 / trials as f64;
        assert!(trials > 0);
        assert!(rate >= 0.9, "{kind}: success {ok}/{trials} = {rate:.2}");
    }
}
