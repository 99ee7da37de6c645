//! Calibration samples away from depth edges (`EvalConfig::edge_margin_px`) on real ground truth
//! with SIMULATED predictions: the case that motivated it.

mod common;

use common::*;
use moma_eval::protocol::{EvalConfig, evaluate};

/// graspnet6dof-table, simulator seed 1, sampling seed 2: three of SSRA's 100 calibration
/// samples fell on object boundaries (off by 0.11–0.27 m⁻¹ in disparity) and tilted its planar
/// scale field; the one-shot MAE over the other frames was about twice that of the other
/// sampling seeds. Samples kept 3 px from depth discontinuities avoid them.
#[test]
#[ignore = "needs ../shared: run with --include-ignored (CI does)"]
fn edge_margin_removes_the_boundary_samples_that_tilted_ssra() {
    let set = shared_set("graspnet6dof-table");
    let preds = simulated_inverse_depth(&set, 1);
    let mae = |edge_margin_px| {
        let config = EvalConfig {
            methods: vec!["ssra".parse().unwrap()],
            seeds: 1,
            seed_base: 2,
            edge_margin_px,
            ..Default::default()
        };
        let res = evaluate(&set, &preds, &config).unwrap();
        assert_eq!(res.len(), 1);
        res[0].per_image.mae.mean
    };
    // measured: 18.2 mm anywhere, 9.8 mm with the margin
    let (anywhere, away) = (mae(0), mae(3));
    assert!(
        away < 0.75 * anywhere,
        "margin 3: {away} m, margin 0: {anywhere} m"
    );
}
