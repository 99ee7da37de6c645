//! The simulator components one at a time (docs/method.md §6).
#![allow(clippy::needless_range_loop)]

mod common;

use common::*;
use moma_core::{Mask, MetricDepth, PredictionKind};
use moma_eval::simulate::{Simulator, SimulatorConfig};
use ndarray::Array2;

fn off() -> SimulatorConfig {
    SimulatorConfig::identity()
}

/// Scene without holes: plane plus a box.
fn dense_gt() -> MetricDepth {
    let g = gt(0);
    MetricDepth::new(g.depth_m.mapv(|z| if z > 0.0 { z } else { 0.7 }))
}

/// Least-squares residual RMS of z on the given features (normal equations, f64, centred).
fn ls_residual(z: &Array2<f32>, feats: &dyn Fn(usize, usize) -> Vec<f64>) -> f64 {
    let (h, w) = z.dim();
    let k = feats(0, 0).len();
    let mut ata = vec![vec![0.0; k]; k];
    let mut atb = vec![0.0; k];
    for v in 0..h {
        for u in 0..w {
            let f = feats(u, v);
            for i in 0..k {
                atb[i] += f[i] * z[[v, u]] as f64;
                for j in 0..k {
                    ata[i][j] += f[i] * f[j];
                }
            }
        }
    }
    // Gaussian elimination with partial pivoting
    let mut a = ata;
    let mut b = atb;
    for c in 0..k {
        let p = (c..k)
            .max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))
            .unwrap();
        a.swap(c, p);
        b.swap(c, p);
        for r in 0..k {
            if r != c {
                let f = a[r][c] / a[c][c];
                for j in c..k {
                    a[r][j] -= f * a[c][j];
                }
                b[r] -= f * b[c];
            }
        }
    }
    let x: Vec<f64> = (0..k).map(|i| b[i] / a[i][i]).collect();
    let mut ss = 0.0;
    for v in 0..h {
        for u in 0..w {
            let f = feats(u, v);
            let p: f64 = f.iter().zip(&x).map(|(a, b)| a * b).sum();
            ss += (z[[v, u]] as f64 - p).powi(2);
        }
    }
    (ss / (h * w) as f64).sqrt()
}

#[test]
fn all_strengths_zero_is_identity_up_to_the_kind_conversion() {
    let g = dense_gt();
    let sim = Simulator::new(off(), 5, PredictionKind::MetricDepth, intrinsics()).unwrap();
    let p = sim.predict(&g, None, "f0").unwrap();
    assert_eq!(p.values, g.depth_m);
    let sim = Simulator::new(off(), 5, PredictionKind::RelativeDisparity, intrinsics()).unwrap();
    let p = sim.predict(&g, None, "f0").unwrap();
    for (a, b) in p.values.iter().zip(g.depth_m.iter()) {
        assert!((a * b - 1.0).abs() < 1e-6);
    }
}

#[test]
fn holes_are_filled_with_the_nearest_valid_pixel() {
    let g = gt(0); // hole in the top-left 3×3 corner
    let sim = Simulator::new(off(), 0, PredictionKind::MetricDepth, intrinsics()).unwrap();
    let p = sim.predict(&g, None, "f0").unwrap();
    assert!(p.values.iter().all(|&x| x > 0.0 && x.is_finite()));
    let v = p.values[[0, 0]];
    assert!(v == g.depth_m[[0, 3]] || v == g.depth_m[[3, 0]], "{v}");
}

#[test]
fn viewpoint_component_alone_is_exactly_ssra() {
    let g = dense_gt();
    let cfg = SimulatorConfig {
        view_angle_deg: 3.0,
        focal_error: 0.1,
        principal_point_error: 0.05,
        depth_scale_error: 0.25,
        ..off()
    };
    let sim = Simulator::new(cfg, 11, PredictionKind::MetricDepth, intrinsics()).unwrap();
    assert!(sim.draws.theta_rad != 0.0 && sim.draws.phi_rad != 0.0);
    let p = sim.predict(&g, None, "f0").unwrap().values;
    // SSRA: z = ẑ(αu + βv + γ) + T3 — features [ẑu, ẑv, ẑ, 1]
    let ssra = ls_residual(&g.depth_m, &|u, v| {
        let zh = p[[v, u]] as f64;
        vec![zh * u as f64 / W as f64, zh * v as f64 / H as f64, zh, 1.0]
    });
    let gssa = ls_residual(&g.depth_m, &|u, v| vec![p[[v, u]] as f64, 1.0]);
    assert!(ssra < 2e-6, "SSRA residual {ssra} m");
    assert!(
        gssa > 50.0 * ssra.max(1e-7),
        "GSSA residual {gssa} should not vanish"
    );
}

#[test]
fn bumps_alone_stay_within_the_amplitude() {
    let g = dense_gt();
    let cfg = SimulatorConfig {
        bump_amplitude: 0.02,
        bump_count: 4,
        ..off()
    };
    let sim = Simulator::new(cfg, 3, PredictionKind::MetricDepth, intrinsics()).unwrap();
    let p = sim.predict(&g, None, "f0").unwrap().values;
    let mut max_dev = 0.0f64;
    for (a, b) in p.iter().zip(g.depth_m.iter()) {
        let r = (*a as f64 / *b as f64) - 1.0;
        max_dev = max_dev.max(r.abs());
    }
    assert!(max_dev <= 0.02 + 1e-6 && max_dev > 0.005, "{max_dev}");
}

#[test]
fn relief_compression_shrinks_small_objects() {
    // wide image so that σ = 30 px (at 640) is much larger than the object
    let (w, h) = (200usize, 150usize);
    let k = moma_core::Intrinsics {
        width: w,
        height: h,
        fx: 200.0,
        fy: 200.0,
        cx: 99.5,
        cy: 74.5,
    };
    let g = MetricDepth::new(Array2::from_shape_fn((h, w), |(v, u)| {
        if u.abs_diff(100) < 4 && v.abs_diff(75) < 4 {
            0.6
        } else {
            0.7
        }
    }));
    let cfg = SimulatorConfig {
        relief_compression: 0.2,
        relief_sigma_px: 60.0,
        ..off()
    };
    let sim = Simulator::new(cfg, 0, PredictionKind::MetricDepth, k).unwrap();
    let p = sim.predict(&g, None, "f0").unwrap().values;
    let relief = p[[10, 10]] as f64 - p[[75, 100]] as f64;
    assert!(
        (relief / 0.1 - 0.8).abs() < 0.03,
        "relief ratio {}",
        relief / 0.1
    );
}

fn minmax_unit(a: &Array2<f32>) -> Array2<f64> {
    let lo = a.iter().cloned().fold(f32::INFINITY, f32::min) as f64;
    let hi = a.iter().cloned().fold(f32::NEG_INFINITY, f32::max) as f64;
    a.mapv(|x| (x as f64 - lo) / (hi - lo))
}

#[test]
fn frame_fluctuation_alone_is_absorbed_by_normalisation() {
    let g = dense_gt();
    let cfg = SimulatorConfig {
        frame_fluctuation: 0.03,
        ..off()
    };
    let sim = Simulator::new(cfg, 2, PredictionKind::RelativeDisparity, intrinsics()).unwrap();
    let a = sim.predict(&g, None, "frame-a").unwrap().values;
    let b = sim.predict(&g, None, "frame-b").unwrap().values;
    let diff = a
        .iter()
        .zip(b.iter())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    assert!(
        diff > 1e-3,
        "frames must differ before normalisation ({diff})"
    );
    let (na, nb) = (minmax_unit(&a), minmax_unit(&b));
    let ndiff = na
        .iter()
        .zip(nb.iter())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f64, f64::max);
    assert!(ndiff < 1e-4, "after min-max in inverse space: {ndiff}");
}

#[test]
fn noise_is_small_and_edges_are_smoothed() {
    let g = dense_gt();
    let cfg = SimulatorConfig {
        noise_std: 0.005,
        ..off()
    };
    let sim = Simulator::new(cfg, 9, PredictionKind::MetricDepth, intrinsics()).unwrap();
    let p = sim.predict(&g, None, "f0").unwrap().values;
    let rel: Vec<f64> = p
        .iter()
        .zip(g.depth_m.iter())
        .map(|(a, b)| *a as f64 / *b as f64 - 1.0)
        .collect();
    let sd = (rel.iter().map(|x| x * x).sum::<f64>() / rel.len() as f64).sqrt();
    assert!((sd - 0.005).abs() < 0.0015, "{sd}");
    // pixel sizes are given at 640 px width: 20 px at 640 = 1.5 px at this 48-px test image
    let cfg = SimulatorConfig {
        edge_sigma_px: 20.0,
        ..off()
    };
    let sim = Simulator::new(cfg, 9, PredictionKind::MetricDepth, intrinsics()).unwrap();
    let p = sim.predict(&g, None, "f0").unwrap().values;
    // the box edge (step of 5 cm at u = 5/6 around row 12) becomes a ramp
    let step = (g.depth_m[[12, 5]] - g.depth_m[[12, 6]]).abs();
    let smoothed = (p[[12, 5]] - p[[12, 6]]).abs();
    assert!(smoothed < 0.8 * step, "{smoothed} vs {step}");
}

#[test]
fn transparency_pulls_towards_the_surface_behind() {
    let g = dense_gt();
    let m = mask(0); // covers the box of frame 0 and a margin
    let cfg = SimulatorConfig {
        transparency_pull: 0.5,
        ..off()
    };
    let sim = Simulator::new(cfg, 1, PredictionKind::MetricDepth, intrinsics()).unwrap();
    let p = sim.predict(&g, Some(&m), "f0").unwrap().values;
    let (obj, plane) = (
        g.depth_m[[12, 10]] as f64,
        0.7 + 0.002 * 10.0 - 0.001 * 12.0,
    );
    let got = p[[12, 10]] as f64;
    assert!(
        (got - (obj + 0.5 * (plane - obj))).abs() < 0.004,
        "{got} vs {}",
        obj + 0.5 * (plane - obj)
    );
    // outside the mask nothing changes
    assert_eq!(p[[30, 40]], g.depth_m[[30, 40]]);
    // a mask covering everything is an error
    let all = Mask::full(moma_core::ImageSize::new(W, H));
    assert!(sim.predict(&g, Some(&all), "f0").is_err());
}

#[test]
fn deterministic_per_seed_and_frame() {
    let g = dense_gt();
    let sim = Simulator::new(
        SimulatorConfig::default(),
        42,
        PredictionKind::RelativeDisparity,
        intrinsics(),
    )
    .unwrap();
    let a = sim.predict(&g, None, "x").unwrap();
    let b = sim.predict(&g, None, "x").unwrap();
    assert_eq!(a, b);
    let c = sim.predict(&g, None, "y").unwrap();
    assert_ne!(a, c);
    let sim2 = Simulator::new(
        SimulatorConfig::default(),
        43,
        PredictionKind::RelativeDisparity,
        intrinsics(),
    )
    .unwrap();
    assert_ne!(a, sim2.predict(&g, None, "x").unwrap());
    let sim3 = Simulator::new(
        SimulatorConfig::default(),
        42,
        PredictionKind::RelativeDisparity,
        intrinsics(),
    )
    .unwrap();
    assert_eq!(a, sim3.predict(&g, None, "x").unwrap());
}

#[test]
fn simulate_set_writes_npy_and_the_simulated_label() {
    let dir = tempfile::tempdir().unwrap();
    let s = set(2);
    let sim = Simulator::new(
        SimulatorConfig::default(),
        0,
        PredictionKind::MetricDepth,
        intrinsics(),
    )
    .unwrap();
    moma_eval::simulate::simulate_set(
        &s,
        &sim,
        moma_eval::simulate::TransparencySource::Auto,
        dir.path(),
    )
    .unwrap();
    for f in &s.frames {
        let a = moma_io::read_npy_f32(dir.path().join(format!("{}.npy", f.id))).unwrap();
        assert_eq!(a.dim(), (H, W));
    }
    let index = moma_io::read_prediction_index(dir.path()).unwrap().unwrap();
    assert!(index.simulated && index.source.contains("SIMULATED"));
    assert_eq!(index.kind, PredictionKind::MetricDepth);
    // the kind comes from predictions.json; --pred-kind may repeat it but not contradict it
    let p = moma_eval::protocol::PredictionSet::read(&s, dir.path(), None).unwrap();
    assert!(p.simulated && p.label.contains("SIMULATED"));
    assert_eq!(p.kind().unwrap(), PredictionKind::MetricDepth);
    assert!(
        moma_eval::protocol::PredictionSet::read(&s, dir.path(), Some(PredictionKind::MetricDepth))
            .is_ok()
    );
    let e = moma_eval::protocol::PredictionSet::read(
        &s,
        dir.path(),
        Some(PredictionKind::RelativeDisparity),
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("mismatch") && e.contains("predictions.json"),
        "{e}"
    );
    // without an index the kind must be given
    std::fs::remove_file(dir.path().join("predictions.json")).unwrap();
    let e = moma_eval::protocol::PredictionSet::read(&s, dir.path(), None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("prediction kind is unknown"), "{e}");
}

/// Strengths beyond what any depth model does are refused naming the field (a typo in a
/// --sim-config file used to hang on a huge blur or write maps of inf or 0); the defaults, the
/// identity and the bounds themselves pass.
#[test]
fn strengths_out_of_range_are_refused_by_name() {
    SimulatorConfig::default().validate().unwrap();
    SimulatorConfig::identity().validate().unwrap();
    let with = |f: &dyn Fn(&mut SimulatorConfig)| {
        let mut c = SimulatorConfig::default();
        f(&mut c);
        c.validate()
    };
    with(&|c| c.bump_count = 1000).unwrap();
    with(&|c| c.edge_sigma_px = 640.0).unwrap();
    type Edit = fn(&mut SimulatorConfig);
    let cases: [(&str, Edit); 8] = [
        ("bump_count", |c| c.bump_count = 100_000),
        ("relief_sigma_px", |c| c.relief_sigma_px = 1e9),
        ("edge_sigma_px", |c| c.edge_sigma_px = 641.0),
        ("noise_corr_sigma_px", |c| c.noise_corr_sigma_px = 1e6),
        ("principal_point_error", |c| c.principal_point_error = 1e6),
        ("inverse_log_scale", |c| c.inverse_log_scale = 1e6),
        ("noise_std", |c| c.noise_std = 1e30),
        ("focal_error", |c| c.focal_error = 1.0),
    ];
    for (name, edit) in cases {
        let e = with(&edit).unwrap_err().to_string();
        assert!(
            e.contains(name) && e.contains("largest sensible"),
            "{name}: {e}"
        );
    }
}
