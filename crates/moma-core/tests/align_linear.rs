//! GSSA and SSRA: recovery of known parameters, LM cross-check, canonical parameters, bad input.

mod common;

use approx::assert_relative_eq;
use moma_core::align::ssra::{self, SsraCanonical, SsraConfig};
use moma_core::align::{AlignmentModel, Method, Sample, SampleSet};
use moma_core::{CoreError, ImageSize, Intrinsics};
use ndarray::Array2;
use proptest::prelude::*;

const SIZE: ImageSize = ImageSize::new(640, 480);

fn ssra_model(m: &AlignmentModel) -> ssra::SsraModel {
    match m {
        AlignmentModel::Ssra(s) => *s,
        other => panic!("expected SSRA, got {other:?}"),
    }
}

#[test]
fn gssa_recovers_exact_parameters_noise_free() {
    let set = common::samples(SIZE, 50, 1, 0.0, |_, _, p| 0.7 * p + 0.3);
    let (model, report) = Method::Gssa.fit(&set).unwrap();
    let AlignmentModel::Gssa(g) = model else {
        panic!("not gssa")
    };
    assert_relative_eq!(g.scale, 0.7, epsilon = 1e-12);
    assert_relative_eq!(g.shift, 0.3, epsilon = 1e-12);
    assert!(report.rms_residual_m < 1e-12);
    assert_eq!((report.method.as_str(), report.n_used), ("gssa", 50));
}

#[test]
fn gssa_recovers_parameters_with_noise() {
    // σ = 2 mm, n = 2000, ẑ spread ~0.35: σ_s ≈ 0.002/(0.35·√2000) ≈ 1.3e-4
    let set = common::samples(SIZE, 2000, 2, 0.002, |_, _, p| 0.7 * p + 0.3);
    let (model, report) = Method::Gssa.fit(&set).unwrap();
    let AlignmentModel::Gssa(g) = model else {
        panic!("not gssa")
    };
    assert!((g.scale - 0.7).abs() < 1e-3, "{g:?}");
    assert!((g.shift - 0.3).abs() < 1e-3, "{g:?}");
    assert!((report.rms_residual_m - 0.002).abs() < 2e-4, "{report:?}");
}

// z = ẑ(αu + βv + γ) + T3 with α, β in m/px
const ALPHA: f64 = 2.0e-4;
const BETA: f64 = -1.5e-4;
const GAMMA: f64 = 0.9;
const T3: f64 = 0.12;

fn linear_truth(u: f64, v: f64, p: f64) -> f64 {
    p * (ALPHA * u + BETA * v + GAMMA) + T3
}

#[test]
fn ssra_recovers_exact_parameters_noise_free() {
    let set = common::samples(SIZE, 100, 3, 0.0, linear_truth);
    let (model, report) = Method::Ssra(SsraConfig::default()).fit(&set).unwrap();
    let m = ssra_model(&model);
    assert_relative_eq!(m.alpha_per_px, ALPHA, epsilon = 1e-13);
    assert_relative_eq!(m.beta_per_px, BETA, epsilon = 1e-13);
    assert_relative_eq!(m.gamma, GAMMA, epsilon = 1e-10);
    assert_relative_eq!(m.t3, T3, epsilon = 1e-10);
    assert!(report.rms_residual_m < 1e-12, "{report:?}");
    assert_eq!(m.image_size, SIZE);
}

/// Files before version 5 named the parameters in metres (`alpha_m_per_px`, …, `t3_m`, `s_m`)
/// although an inverse-space fit holds 1/m: the same document with those names reads as the
/// same model, and a model is written with the unit-free names.
#[test]
fn ssra_parameters_named_before_version_5_read_as_the_same_model() {
    let set = common::samples(SIZE, 100, 3, 0.0, linear_truth);
    let (model, _) = Method::Ssra(SsraConfig::default()).fit(&set).unwrap();
    let text = serde_json::to_string(&model).unwrap();
    for name in [
        "\"alpha_per_px\"",
        "\"beta_per_px\"",
        "\"gamma\"",
        "\"t3\"",
        "\"s\"",
    ] {
        assert!(text.contains(name), "{name} missing in {text}");
    }
    let old = text
        .replace("\"alpha_per_px\"", "\"alpha_m_per_px\"")
        .replace("\"beta_per_px\"", "\"beta_m_per_px\"")
        .replace("\"gamma\"", "\"gamma_m\"")
        .replace("\"t3\"", "\"t3_m\"")
        .replace("\"s\"", "\"s_m\"");
    assert!(!old.contains("\"t3\""));
    let back: AlignmentModel = serde_json::from_str(&old).unwrap();
    assert_eq!(back, model);
}

#[test]
fn ssra_exactly_four_samples_interpolates() {
    let set = common::samples(SIZE, 4, 4, 0.0, linear_truth);
    let (model, _) = Method::Ssra(SsraConfig::default()).fit(&set).unwrap();
    let m = ssra_model(&model);
    assert_relative_eq!(m.alpha_per_px, ALPHA, epsilon = 1e-10);
    assert_relative_eq!(m.t3, T3, epsilon = 1e-8);
}

#[test]
fn ssra_recovers_parameters_with_noise() {
    let set = common::samples(SIZE, 3000, 5, 0.002, linear_truth);
    let (model, report) = Method::Ssra(SsraConfig::default()).fit(&set).unwrap();
    let m = ssra_model(&model);
    // compare the predicted scale field at the image corners rather than raw coefficients
    for (u, v) in [
        (0.0, 0.0),
        (639.0, 0.0),
        (0.0, 479.0),
        (639.0, 479.0),
        (320.0, 240.0),
    ] {
        let got = m.predict(u, v, 1.0);
        let want = linear_truth(u, v, 1.0);
        assert!((got - want).abs() < 3e-3, "({u},{v}): {got} vs {want}");
    }
    assert!((report.rms_residual_m - 0.002).abs() < 2e-4, "{report:?}");
}

#[test]
fn ssra_canonical_parameters_round_trip() {
    let k = Intrinsics {
        width: 640,
        height: 480,
        fx: 610.0,
        fy: 612.0,
        cx: 318.5,
        cy: 241.25,
    };
    let truth = SsraCanonical {
        s: 1.15,
        theta_rad: 0.07,
        phi_rad: -0.11,
        t3: 0.08,
        cx_px: k.cx,
        cy_px: k.cy,
        f_px: k.fx,
    };
    // data from the paper's formula, evaluated literally
    let set = common::samples(SIZE, 200, 6, 0.0, |u, v, p| {
        let x = p * (u - k.cx) / k.fx;
        let y = p * (v - k.cy) / k.fx;
        let (s, th, ph) = (1.15f64, 0.07f64, -0.11f64);
        s * (-x * ph.sin() + y * th.sin() * ph.cos() + p * th.cos() * ph.cos()) + 0.08
    });
    let cfg = SsraConfig {
        intrinsics: Some(k),
    };
    let (model, _) = Method::Ssra(cfg).fit(&set).unwrap();
    let c = ssra_model(&model).canonical;
    assert_relative_eq!(c.s, truth.s, epsilon = 1e-9);
    assert_relative_eq!(c.theta_rad, truth.theta_rad, epsilon = 1e-9);
    assert_relative_eq!(c.phi_rad, truth.phi_rad, epsilon = 1e-9);
    assert_relative_eq!(c.t3, truth.t3, epsilon = 1e-9);
    assert_eq!((c.cx_px, c.cy_px, c.f_px), (k.cx, k.cy, k.fx));
    // canonical → linear → canonical
    let (a, b, g, t) = c.to_linear();
    let back = SsraCanonical::from_linear(a, b, g, t, k.cx, k.cy, k.fx);
    assert_relative_eq!(back.theta_rad, c.theta_rad, epsilon = 1e-12);
    assert_relative_eq!(back.s, c.s, epsilon = 1e-12);
}

#[test]
fn ssra_canonical_sign_makes_r33_positive() {
    // negative overall scale: s must come out negative with R33 > 0 (|θ| < π/2)
    let c = SsraCanonical::from_linear(1e-5, 2e-5, -0.8, 0.1, 320.0, 240.0, 640.0);
    assert!(c.s < 0.0);
    assert!(c.theta_rad.abs() < std::f64::consts::FRAC_PI_2);
    let (a, b, g, t) = c.to_linear();
    assert_relative_eq!(a, 1e-5, epsilon = 1e-15);
    assert_relative_eq!(b, 2e-5, epsilon = 1e-15);
    assert_relative_eq!(g, -0.8, epsilon = 1e-12);
    assert_eq!(t, 0.1);
}

#[test]
fn ssra_nominal_intrinsics_when_none_given() {
    let set = common::samples(SIZE, 100, 7, 0.0, linear_truth);
    let (model, _) = Method::Ssra(SsraConfig::default()).fit(&set).unwrap();
    let c = ssra_model(&model).canonical;
    assert_eq!((c.cx_px, c.cy_px, c.f_px), (319.5, 239.5, 640.0));
    // the canonical parameters reproduce the model through the paper's formula
    for (u, v, p) in [(3.0, 7.0, 0.5), (600.0, 400.0, 1.3)] {
        assert_relative_eq!(c.predict(u, v, p), linear_truth(u, v, p), epsilon = 1e-12);
    }
}

#[test]
fn ssra_closed_form_matches_levenberg_marquardt_cost() {
    // a noisy problem that is not exactly of the model family
    let set = common::samples(SIZE, 300, 8, 0.004, |u, v, p| {
        linear_truth(u, v, p) + 0.01 * (u / 100.0).sin()
    });
    let (model, report) = Method::Ssra(SsraConfig::default()).fit(&set).unwrap();
    let m = ssra_model(&model);
    let mse_cf = report.rms_residual_m.powi(2);
    let lm = ssra::fit_lm(&set, 8, 42).unwrap();
    let rel = (lm.mse_m2 - mse_cf) / mse_cf;
    assert!(
        rel.abs() < 1e-9,
        "LM mse {} vs closed form {} (rel {rel:e})",
        lm.mse_m2,
        mse_cf
    );
    // the closed form is the global optimum: LM can only match it, never beat it
    assert!(rel > -1e-12, "{rel:e}");
    // LM's (non-identifiable) parameters describe the same function
    for s in set.samples.iter().take(20) {
        assert!((lm.params.predict(s.u, s.v, s.pred) - m.predict(s.u, s.v, s.pred)).abs() < 1e-6);
    }
}

#[test]
fn ssra_apply_matches_model_and_keeps_nan() {
    let set = common::samples(SIZE, 100, 9, 0.0, linear_truth);
    let (model, _) = Method::Ssra(SsraConfig::default()).fit(&set).unwrap();
    let m = ssra_model(&model);
    let mut zhat = Array2::from_shape_fn((480, 640), |(v, u)| {
        0.5 + ((u * 7 + v * 3) % 100) as f32 / 100.0
    });
    zhat[[10, 20]] = f32::NAN;
    let out = model.apply(zhat.view()).unwrap().depth_m;
    assert!(out[[10, 20]].is_nan());
    for (v, u) in [(0, 0), (479, 639), (100, 333), (240, 1)] {
        let want = m.predict(u as f64, v as f64, f64::from(zhat[[v, u]]));
        assert!((f64::from(out[[v, u]]) - want).abs() < 1e-5, "({u},{v})");
    }
    // a non-contiguous view gives the same result
    let t = zhat.t().to_owned();
    let out2 = model.apply(t.t()).unwrap().depth_m;
    assert_eq!(out.mapv(f32::to_bits), out2.mapv(f32::to_bits));
}

#[test]
fn gssa_apply_is_affine() {
    let model = AlignmentModel::Gssa(moma_core::align::gssa::GssaModel {
        scale: 2.0,
        shift: -0.5,
    });
    let z = ndarray::array![[1.0f32, f32::NAN], [0.25, 3.0]];
    let out = model.apply(z.view()).unwrap().depth_m;
    assert_eq!(out[[0, 0]], 1.5);
    assert!(out[[0, 1]].is_nan());
    // 2·0.25 − 0.5 = 0 m: at the camera, no depth
    assert!(out[[1, 0]].is_nan(), "{out}");
    assert_eq!(out[[1, 1]], 5.5);
    assert_eq!(
        AlignmentModel::Raw.apply(z.view()).unwrap().depth_m[[1, 1]],
        3.0
    );
}

#[test]
fn apply_size_mismatch_is_an_error() {
    let set = common::samples(SIZE, 100, 10, 0.0, linear_truth);
    let (model, _) = Method::Ssra(SsraConfig::default()).fit(&set).unwrap();
    let z = Array2::<f32>::ones((240, 320));
    assert!(matches!(
        model.apply(z.view()),
        Err(CoreError::SizeMismatch { .. })
    ));
    let mut out = Array2::<f32>::zeros((480, 641));
    let z = Array2::<f32>::ones((480, 640));
    assert!(matches!(
        model.apply_into(z.view(), &mut out.view_mut()),
        Err(CoreError::SizeMismatch { .. })
    ));
}

// ---- bad input -------------------------------------------------------------------------------

fn set_of(points: &[(f64, f64, f64, f64)]) -> SampleSet {
    SampleSet {
        space: moma_core::normalise::AlignSpace::Depth,
        image_size: SIZE,
        samples: points
            .iter()
            .map(|&(u, v, pred, target)| Sample { u, v, pred, target })
            .collect(),
    }
}

#[test]
fn too_few_samples() {
    let one = set_of(&[(1.0, 2.0, 0.5, 1.0)]);
    assert!(matches!(
        Method::Gssa.fit(&one),
        Err(CoreError::TooFewSamples {
            need: 2,
            got: 1,
            ..
        })
    ));
    let three = set_of(&[
        (1.0, 2.0, 0.5, 1.0),
        (5.0, 9.0, 0.7, 1.2),
        (30.0, 2.0, 0.9, 1.1),
    ]);
    assert!(matches!(
        Method::Ssra(SsraConfig::default()).fit(&three),
        Err(CoreError::TooFewSamples {
            need: 4,
            got: 3,
            ..
        })
    ));
    let lwlr = Method::Lwlr(Default::default());
    assert!(matches!(
        lwlr.fit(&one),
        Err(CoreError::TooFewSamples { need: 2, .. })
    ));
    assert!(matches!(
        lwlr.fit(&set_of(&[])),
        Err(CoreError::TooFewSamples { .. })
    ));
    // RAW needs none
    assert!(Method::Raw.fit(&set_of(&[])).is_ok());
}

#[test]
fn non_finite_or_invalid_samples() {
    let mut pts = vec![
        (1.0, 2.0, 0.5, 1.0),
        (5.0, 9.0, 0.7, 1.2),
        (30.0, 2.0, 0.9, 1.1),
        (3.0, 40.0, 1.0, 1.3),
    ];
    pts[2].2 = f64::NAN;
    for m in [
        Method::Raw,
        Method::Gssa,
        Method::Ssra(SsraConfig::default()),
        Method::Lwlr(Default::default()),
    ] {
        assert!(
            matches!(
                m.fit(&set_of(&pts)),
                Err(CoreError::InvalidSample { index: 2, .. })
            ),
            "{m:?}"
        );
    }
    pts[2].2 = 0.9;
    pts[1].3 = f64::INFINITY;
    assert!(matches!(
        Method::Gssa.fit(&set_of(&pts)),
        Err(CoreError::InvalidSample { index: 1, .. })
    ));
    pts[1].3 = 0.0;
    assert!(matches!(
        Method::Gssa.fit(&set_of(&pts)),
        Err(CoreError::InvalidSample { index: 1, .. })
    ));
}

#[test]
fn constant_prediction_is_degenerate() {
    let pts: Vec<_> = (0..20)
        .map(|k| {
            (
                k as f64 * 13.0 % 600.0,
                k as f64 * 7.0 % 400.0,
                0.8,
                1.0 + 0.01 * k as f64,
            )
        })
        .collect();
    for m in [
        Method::Gssa,
        Method::Ssra(SsraConfig::default()),
        Method::Lwlr(Default::default()),
    ] {
        assert!(
            matches!(m.fit(&set_of(&pts)), Err(CoreError::Degenerate(_))),
            "{m:?}"
        );
    }
}

#[test]
fn collinear_pixels_are_degenerate_for_ssra() {
    // all on the line v = 0.5 u + 10, varied ẑ: the ẑv feature is a combination of ẑu and ẑ
    let pts: Vec<_> = (0..50)
        .map(|k| {
            let u = 10.0 + 11.0 * k as f64;
            (
                u,
                0.5 * u + 10.0,
                0.5 + 0.01 * ((k * 7) % 13) as f64,
                1.0 + 0.001 * k as f64,
            )
        })
        .collect();
    assert!(matches!(
        Method::Ssra(SsraConfig::default()).fit(&set_of(&pts)),
        Err(CoreError::Degenerate(_))
    ));
    // a single row, too
    let row: Vec<_> = (0..50)
        .map(|k| (k as f64 * 12.0, 100.0, 0.5 + 0.02 * (k % 9) as f64, 1.0))
        .collect();
    assert!(matches!(
        Method::Ssra(SsraConfig::default()).fit(&set_of(&row)),
        Err(CoreError::Degenerate(_))
    ));
    // but GSSA is fine on them
    assert!(Method::Gssa.fit(&set_of(&pts)).is_ok());
}

#[test]
fn ssra_intrinsics_for_another_size_is_an_error() {
    let set = common::samples(SIZE, 100, 11, 0.0, linear_truth);
    let k = Intrinsics::nominal(ImageSize::new(1280, 720));
    let r = Method::Ssra(SsraConfig {
        intrinsics: Some(k),
    })
    .fit(&set);
    assert!(matches!(r, Err(CoreError::SizeMismatch { .. })), "{r:?}");
}

// ---- properties --------------------------------------------------------------------------

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    #[test]
    fn ssra_fit_is_invariant_to_sample_order(seed in 0u64..1000, rot in 1usize..99) {
        let set = common::samples(SIZE, 100, seed, 0.003, linear_truth);
        let mut perm = set.clone();
        perm.samples.rotate_left(rot);
        perm.samples.reverse();
        let (a, _) = Method::Ssra(SsraConfig::default()).fit(&set).unwrap();
        let (b, _) = Method::Ssra(SsraConfig::default()).fit(&perm).unwrap();
        let (a, b) = (ssra_model(&a), ssra_model(&b));
        for (u, v) in [(0.0, 0.0), (639.0, 479.0), (100.0, 400.0)] {
            prop_assert!((a.predict(u, v, 1.0) - b.predict(u, v, 1.0)).abs() < 1e-10);
        }
    }

    #[test]
    fn gssa_residuals_are_orthogonal_to_features(seed in 0u64..1000) {
        // normal equations: Σ r = 0 and Σ r ẑ = 0 at the optimum
        let set = common::samples(SIZE, 60, seed, 0.01, |_, _, p| 1.3 * p - 0.2 + 0.05 * p * p);
        let (m, _) = Method::Gssa.fit(&set).unwrap();
        let AlignmentModel::Gssa(g) = m else { unreachable!() };
        let r: Vec<f64> = set.samples.iter().map(|s| g.predict(s.pred) - s.target).collect();
        let s0: f64 = r.iter().sum();
        let s1: f64 = r.iter().zip(&set.samples).map(|(r, s)| r * s.pred).sum();
        prop_assert!(s0.abs() < 1e-10 && s1.abs() < 1e-10);
    }
}

/// A fit report names its method with a [`MethodName`]: the same names, in the same order, as
/// [`Method::NAMES`], each the name of the method it is parsed from, and serialised as that name.
#[test]
fn method_names_match_the_methods() {
    use moma_core::align::MethodName;
    assert_eq!(
        Method::NAMES,
        [
            "ssra",
            "gssa",
            "lwlr",
            "lwlr-exact",
            "lwlr-bare",
            "ssra-local",
            "gssa-local",
            "auto",
            "raw"
        ]
    );
    for name in Method::NAMES {
        let method: Method = name.parse().unwrap();
        let id = MethodName::from(&method);
        assert_eq!(id.as_str(), name);
        assert_eq!(name.parse::<MethodName>().unwrap(), id);
        assert_eq!(serde_json::to_string(&id).unwrap(), format!("\"{name}\""));
    }
    let e = "lwlr2".parse::<MethodName>().unwrap_err().to_string();
    assert!(e.contains("'lwlr2'") && e.contains("lwlr-exact"), "{e}");
    let set = common::samples(SIZE, 100, 3, 0.0, linear_truth);
    let (model, report) = Method::Ssra(SsraConfig::default()).fit(&set).unwrap();
    assert_eq!(report.method, MethodName::Ssra);
    assert_eq!(MethodName::from(&model), MethodName::Ssra);
}
