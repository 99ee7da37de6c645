//! The grasp JSON shapes (docs/grasping.md) and the camera→base transform.

use moma_grasp::{
    Extrinsics, Grasp, GraspError, ParallelGrasp, ParallelPose, SuctionGrasp, SuctionPose, Vec3,
};

fn parallel() -> Grasp {
    Grasp::Parallel(ParallelGrasp {
        success_prob: None,
        score: 0.5,
        pose: ParallelPose {
            center_m: [0.1, -0.2, 0.7],
            approach: [0.0, 0.0, 1.0],
            closing: [1.0, 0.0, 0.0],
            width_m: 0.06,
        },
        base: None,
    })
}

#[test]
fn parallel_json_has_exactly_the_issue_fields_in_order() {
    let s = serde_json::to_string(&parallel()).unwrap();
    assert_eq!(
        s,
        r#"{"kind":"parallel","score":0.5,"success_prob":null,"center_m":[0.1,-0.2,0.7],"approach":[0.0,0.0,1.0],"closing":[1.0,0.0,0.0],"width_m":0.06}"#
    );
    let back: Grasp = serde_json::from_str(&s).unwrap();
    assert_eq!(back, parallel());
}

#[test]
fn suction_json_and_base_frame() {
    let mut g = Grasp::Suction(SuctionGrasp {
        success_prob: None,
        score: 0.25,
        pose: SuctionPose {
            point_m: [0.0, 0.1, 0.5],
            approach: [0.0, 0.0, 1.0],
        },
        base: None,
    });
    assert_eq!(
        serde_json::to_string(&g).unwrap(),
        r#"{"kind":"suction","score":0.25,"success_prob":null,"point_m":[0.0,0.1,0.5],"approach":[0.0,0.0,1.0]}"#
    );
    // Camera looking down from 1 m above the base origin: x_b = x_c, y_b = −y_c, z_b = 1 − z_c.
    let e = Extrinsics::new([
        [1.0, 0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0, 0.0],
        [0.0, 0.0, -1.0, 1.0],
        [0.0, 0.0, 0.0, 1.0],
    ])
    .unwrap();
    g.set_base(&e);
    let v: serde_json::Value = serde_json::to_value(g).unwrap();
    let base = &v["base"];
    let p: Vec<f64> = serde_json::from_value(base["point_m"].clone()).unwrap();
    let a: Vec<f64> = serde_json::from_value(base["approach"].clone()).unwrap();
    assert!((p[0] - 0.0).abs() < 1e-6 && (p[1] + 0.1).abs() < 1e-6 && (p[2] - 0.5).abs() < 1e-6);
    assert_eq!(a, vec![0.0, 0.0, -1.0]);
    assert_eq!(base.as_object().unwrap().len(), 2, "{base}");
}

#[test]
fn parallel_base_frame_rotates_directions_and_keeps_width() {
    // 90° about z plus a translation.
    let e = Extrinsics::new([
        [0.0, -1.0, 0.0, 0.5],
        [1.0, 0.0, 0.0, -0.25],
        [0.0, 0.0, 1.0, 0.1],
        [0.0, 0.0, 0.0, 1.0],
    ])
    .unwrap();
    let mut g = parallel();
    g.set_base(&e);
    let Grasp::Parallel(p) = g else {
        unreachable!()
    };
    let b = p.base.unwrap();
    let c = Vec3::from(b.center_m);
    assert!(
        (c - Vec3::new(0.5 + 0.2, -0.25 + 0.1, 0.8)).norm() < 1e-6,
        "{c:?}"
    );
    assert_eq!(b.closing, [0.0, 1.0, 0.0]);
    assert_eq!(b.approach, [0.0, 0.0, 1.0]);
    assert_eq!(b.width_m, 0.06);
}

#[test]
fn non_rigid_extrinsics_are_rejected() {
    let scaled = [
        [2.0, 0.0, 0.0, 0.0],
        [0.0, 2.0, 0.0, 0.0],
        [0.0, 0.0, 2.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let reflection = [
        [-1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let bad_row = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0, 1.0],
    ];
    let nan = [
        [f64::NAN, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    // finite in f64, beyond f32 (poses are f32): the grasps' JSON had `null` coordinates
    let far = [
        [1.0, 0.0, 0.0, 1.0e39],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let mut gantry = far;
    gantry[0][3] = -20.0;
    Extrinsics::new(gantry).unwrap();
    // millimetres given as metres (a camera 0.1, 0.2, 0.5 m from the base)
    let mut millimetres = far;
    (millimetres[0][3], millimetres[1][3], millimetres[2][3]) = (100.0, 200.0, 500.0);
    for (m, word) in [
        (scaled, "orthonormal"),
        (reflection, "det"),
        (bad_row, "last row"),
        (nan, "finite"),
        (far, "beyond 20 m"),
        (millimetres, "millimetres?"),
    ] {
        let err = Extrinsics::new(m).unwrap_err();
        assert!(matches!(err, GraspError::NonRigidExtrinsics(_)));
        assert!(err.to_string().contains(word), "{err}");
    }
    // Through serde too (the CLI reads `{"camera_to_base": [...]}`).
    let r: Result<Extrinsics, _> =
        serde_json::from_str("[[2,0,0,0],[0,2,0,0],[0,0,2,0],[0,0,0,1]]");
    assert!(r.is_err());
    // A tiny numerical error is fine.
    let ok = Extrinsics::new([
        [1.0, 1e-5, 0.0, 0.0],
        [-1e-5, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]);
    assert!(ok.is_ok());
}

#[test]
fn mask_components_split_into_trials() {
    use moma_core::Mask;
    use ndarray::Array2;
    // Two 15x15 squares (225 px, diagonal-touching pixels join), one 10x10 speck (100 px).
    let mut m = Array2::from_elem((60, 80), false);
    m.slice_mut(ndarray::s![0..15, 0..15]).fill(true);
    m.slice_mut(ndarray::s![15..30, 15..30]).fill(true); // touches the first at a corner
    m.slice_mut(ndarray::s![40..55, 50..65]).fill(true);
    m.slice_mut(ndarray::s![45..55, 0..10]).fill(true);
    let comps = moma_grasp::mask_components(&Mask::new(m), moma_grasp::MIN_TRIAL_COMPONENT_PX);
    let counts: Vec<usize> = comps.iter().map(|c| c.count()).collect();
    assert_eq!(counts, vec![450, 225]);
}
