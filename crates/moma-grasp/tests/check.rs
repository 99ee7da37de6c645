//! `grasp_check`: grasps planned on one depth, executed on the truth of the same frame. Scenes
//! are rendered by exact ray casting (tests/common); the expectations are the planner's rules
//! on exact depth and negative controls with a known error.

mod common;

use common::{BoxSpec, Scene as Synth, intrinsics};
use moma_core::{DepthErrorModel, MetricDepth};
use moma_grasp::{
    GraspRequest, Gripper, GripperKind, ParallelJaw, Scene, SuctionCup, grasp_check, grasp_check_on,
};

const DIST_M: f64 = 0.7;

/// Two boxes, 40 and 50 mm tall, on a table seen from above.
fn two_boxes() -> MetricDepth {
    let b = |y: f64, h: f64| BoxSpec {
        y_m: y,
        height_m: h,
        ..BoxSpec::standard()
    };
    let mut s = Synth::top_down(DIST_M, Some(b(0.15, 0.04)));
    s.boxes[1] = Some(b(-0.15, 0.05));
    s.render()
}

fn grippers() -> [Gripper; 2] {
    [
        Gripper::Parallel(ParallelJaw::default()),
        Gripper::Suction(SuctionCup::default()),
    ]
}

#[test]
fn gripper_kinds_name_their_default_grippers() {
    for (kind, gripper) in GripperKind::ALL.into_iter().zip(grippers()) {
        assert_eq!(kind.default_gripper(), gripper);
        assert_eq!(gripper.kind(), kind);
        assert_eq!(kind.name().parse::<GripperKind>().unwrap(), kind);
        assert_eq!(
            serde_json::to_string(&kind).unwrap(),
            format!("\"{}\"", gripper.kind_name())
        );
    }
    let err = "vacuum".parse::<GripperKind>().unwrap_err().to_string();
    assert_eq!(
        err,
        "unknown gripper 'vacuum' (expected 'parallel' or 'suction')"
    );
}

/// The check on a truth scene built once is the check that builds it: what `moma grasp-eval`
/// reuses for every calibration of a set is what `moma calibrate --grasp-check` computes.
#[test]
fn a_check_on_a_prebuilt_truth_scene_is_the_same_check() {
    let truth = two_boxes();
    let k = intrinsics();
    let near = MetricDepth::new(truth.depth_m.mapv(|z| if z > 0.0 { z - 0.01 } else { z }));
    for gripper in grippers() {
        let request = GraspRequest::new(gripper)
            .with_error_model(Some(DepthErrorModel::uniform(0.004).unwrap()));
        let scene = Scene::build(&truth, &k, None, &request.scene).unwrap();
        let built = grasp_check(&near, &truth, &k, None, &request).unwrap();
        assert!(built.grasps > 0, "{built:?}");
        assert_eq!(
            grasp_check_on(&near, &scene, &k, None, &request).unwrap(),
            built
        );
    }
}

#[test]
fn grasps_planned_on_the_truth_hold_and_on_a_shifted_depth_fail() {
    let truth = two_boxes();
    let k = intrinsics();
    // the same depth 30 mm farther: a cup stops 30 mm behind the surface (compliance 15 mm),
    // fingers close 30 mm lower (into the table or under the boxes' reach)
    let far = MetricDepth::new(truth.depth_m.mapv(|z| if z > 0.0 { z + 0.03 } else { z }));
    for gripper in grippers() {
        for seed in 0..3 {
            let mut request = GraspRequest::new(gripper);
            request.seed = seed;
            let exact = grasp_check(&truth, &truth, &k, None, &request).unwrap();
            assert!(exact.grasps > 0, "{gripper:?} seed {seed}: {exact:?}");
            // every grasp the planner returns passed its execution on this very depth with the
            // scorer's rules, so on the truth they all hold
            assert_eq!(
                exact.successes, exact.grasps,
                "{gripper:?} seed {seed}: {exact:?}"
            );
            assert_eq!(exact.success_rate, Some(1.0));
            assert_eq!(
                (exact.gripper.as_str(), exact.scores.as_str()),
                (gripper.kind_name(), "proxy")
            );
            // no error model: no probabilities
            assert_eq!(exact.mean_success_prob, None);

            let shifted = grasp_check(&far, &truth, &k, None, &request).unwrap();
            let failed: usize = shifted.failures.values().sum();
            assert_eq!(shifted.successes + failed, shifted.grasps, "{shifted:?}");
            assert!(
                3 * shifted.successes <= shifted.grasps,
                "{gripper:?} seed {seed}: planned 30 mm off, {} of {} grasps still hold",
                shifted.successes,
                shifted.grasps
            );
            // and they fail mostly the way a surface 30 mm nearer than planned makes them
            // fail: a cup pushed past its compliance into it, fingers closed into the table
            let commonest = shifted
                .failures
                .iter()
                .max_by_key(|(_, n)| **n)
                .map(|(w, _)| w.as_str());
            let expected = match gripper {
                Gripper::Suction(_) => "cup_crash",
                Gripper::Parallel(_) => "collision",
            };
            assert_eq!(
                commonest,
                Some(expected),
                "{gripper:?} seed {seed}: {:?}",
                shifted.failures
            );
        }
    }
}

#[test]
fn an_error_model_gives_the_grasps_probabilities() {
    let truth = two_boxes();
    let request = GraspRequest::new(Gripper::Suction(SuctionCup::default()))
        .with_error_model(Some(DepthErrorModel::uniform(0.003).unwrap()));
    let c = grasp_check(&truth, &truth, &intrinsics(), None, &request).unwrap();
    let p = c.mean_success_prob.unwrap();
    assert!(c.grasps > 0 && p > 0.0 && p < 1.0, "{c:?}");
    // a wider σ makes the same grasps less likely to hold: the mean probability falls with it
    let mean_p = |sigma_m: f64| {
        let mut r = request
            .clone()
            .with_error_model(Some(DepthErrorModel::uniform(sigma_m).unwrap()));
        r.draws = 16;
        grasp_check(&truth, &truth, &intrinsics(), None, &r)
            .unwrap()
            .mean_success_prob
            .unwrap()
    };
    let (p1, p10, p40) = (mean_p(0.001), mean_p(0.01), mean_p(0.04));
    assert!(
        p1 > p10 && p10 > p40,
        "σ 1 / 10 / 40 mm: {p1} / {p10} / {p40}"
    );
}

#[test]
fn a_bare_table_gives_no_grasp_and_says_why() {
    let table = Synth::top_down(DIST_M, None).render();
    for gripper in grippers() {
        let c = grasp_check(
            &table,
            &table,
            &intrinsics(),
            None,
            &GraspRequest::new(gripper),
        )
        .unwrap();
        assert_eq!((c.grasps, c.successes, c.success_rate), (0, 0, None));
        assert!(c.failures.is_empty());
        let why = c.no_grasp_reason.as_deref().unwrap_or_default();
        assert!(
            why.contains("nothing stands more than the object height"),
            "{c:?}"
        );
    }
}

/// Without a mask the check counts the grasps on the objects the planner keeps: a region that
/// touches the image border (here the first 24 rows, 12–18 mm nearer, as real sensors' depth
/// curls along a frame's edge) is not tried, and the check says so in `notes`, with the text
/// `moma grasp` prints; a frame without one has none.
#[test]
fn the_check_names_the_regions_the_planner_left_out() {
    let k = intrinsics();
    let clean = two_boxes();
    let mut curled = clean.clone();
    for v in 0..24 {
        let lift_m = 0.018 - 0.006 * v as f32 / 24.0;
        for z in curled.depth_m.row_mut(v) {
            *z -= lift_m;
        }
    }
    for gripper in grippers() {
        let request = GraspRequest::new(gripper);
        let c = grasp_check(&clean, &clean, &k, None, &request).unwrap();
        assert!(c.grasps > 0 && c.notes.is_empty(), "{c:?}");
        let c = grasp_check(&curled, &curled, &k, None, &request).unwrap();
        let scene = Scene::build(&curled, &k, None, &request.scene).unwrap();
        assert_eq!(scene.border_regions_dropped(), 1);
        assert_eq!(c.notes, vec![scene.border_note().unwrap()], "{c:?}");
        assert!(c.notes[0].contains("touch the image border"), "{c:?}");
        // the field reaches the JSON that `moma calibrate --grasp-check --json` writes
        let json = serde_json::to_value(&c).unwrap();
        assert_eq!(json["notes"][0], serde_json::json!(c.notes[0]));
    }
}

#[test]
fn a_truth_of_another_size_is_an_error() {
    let truth = two_boxes();
    let small = MetricDepth::new(ndarray::Array2::from_elem((240, 320), 0.7f32));
    let request = GraspRequest::new(Gripper::Suction(SuctionCup::default()));
    let e = grasp_check(&truth, &small, &intrinsics(), None, &request).unwrap_err();
    assert!(e.to_string().contains("320"), "{e}");
}

/// The calibration frame's check (`calibration_frame_check`, what `moma calibrate --grasp-check`
/// and Python's `grasp_check` run) is `grasp_check` of the calibration's one-shot alignment
/// with the frame's error model and the seed: a prediction that is an affine map of the truth,
/// which GSSA calibrates exactly, for both grippers and two seeds; every grasp holds. A
/// prediction of another size is an alignment error.
#[test]
fn the_calibration_frames_check_is_the_check_of_its_one_shot_alignment() {
    use moma_core::align::Method;
    use moma_core::normalise::{AlignSpace, Normalisation, NormalisationConfig};
    use moma_core::pipeline::{AlignOptions, CalibrationConfig, CalibrationFrame, calibrate};
    use moma_core::{Prediction, PredictionKind};
    let truth = two_boxes();
    let k = intrinsics();
    let pred = Prediction::new(
        truth
            .depth_m
            .mapv(|z| if z > 0.0 { 2.0 * z + 0.1 } else { f32::NAN }),
        PredictionKind::RelativeDepth,
    );
    let config = CalibrationConfig {
        method: Method::Gssa,
        normalisation: NormalisationConfig {
            method: Normalisation::None,
            space: AlignSpace::Depth,
        },
        sampling: Default::default(),
        robust: None,
        workspace: None,
    };
    let cal = calibrate(&[CalibrationFrame::new(&pred, &truth)], &config).unwrap();
    let aligned = cal.aligned(&pred, &AlignOptions::default()).unwrap();
    assert!(aligned.error_model.is_some());
    for gripper in grippers() {
        for seed in [0, 5] {
            let check =
                moma_grasp::calibration_frame_check(&cal, &pred, &truth, &k, None, gripper, seed)
                    .unwrap();
            let mut request =
                GraspRequest::new(gripper).with_error_model(aligned.error_model.clone());
            request.seed = seed;
            assert_eq!(
                check,
                grasp_check(&aligned.depth, &truth, &k, None, &request).unwrap()
            );
            assert!(
                check.grasps > 0 && check.successes == check.grasps,
                "{check:?}"
            );
            assert!(check.mean_success_prob.is_some());
        }
    }
    let small = Prediction::new(
        ndarray::Array2::from_elem((10, 10), 1.0f32),
        PredictionKind::RelativeDepth,
    );
    let e = moma_grasp::calibration_frame_check(&cal, &small, &truth, &k, None, grippers()[1], 0)
        .unwrap_err();
    assert!(matches!(e, moma_grasp::GraspError::Align(_)), "{e}: {e:?}");
    assert!(
        e.to_string().starts_with("aligning the calibration frame"),
        "{e}"
    );
}
