//! The defaults that every front end shares, decided once from typed inputs: the method's
//! settings, the normalisation and the alignment space by prediction kind. `moma calibrate`,
//! Python's `moma.calibrate` and the evaluation protocol call these functions instead of
//! deciding on their own.
//!
//! The rules:
//! - normalisation: unless given, `minmax-unit` (the authors' code) for every prediction kind
//!   ([`default_normalisation`]; the paper's `minmax` on request), and `none` for RAW, which refuses any other when it is fitted
//!   ([`crate::CalibrationConfig::check`]); an evaluation of RAW uses `none` in depth space
//!   whatever the other methods' normalisation ([`evaluation_normalisation`]);
//! - space: the prediction's own unless given ([`AlignSpace::native`]: inverse space for
//!   relative-disparity predictions, the only way to undo a relative model's disparity shift), depth
//!   space for RAW;
//! - method settings: SSRA gets the camera intrinsics (its canonical parameters are reported
//!   with them); an LWLR bandwidth is for the LWLR methods only;
//! - the cross-validation of `auto` and of the local corrections follows the [`Protocol`], what
//!   the calibration will align ([`local_config`]): other frames of a fixed camera (spatially
//!   buffered, squared error in the fit's target units, the coarse bandwidths), or the frame it
//!   was calibrated on (plain leave-one-out, relative error, bandwidths down to ≈ 30 px).
//!   `--cv-loss` and `--cv-margin-se` override the loss and the rule, for these methods only.

use serde::{Deserialize, Serialize};

use crate::align::local::{CvLoss, LocalConfig};
use crate::align::{Method, lwlr};
use crate::camera::Intrinsics;
use crate::error::{CoreError, Result};
use crate::image::PredictionKind;
use crate::normalise::{AlignSpace, Normalisation, NormalisationConfig};

/// The normalisation used when none is given: `minmax-unit` (the authors' code) for every
/// prediction kind; the paper's `minmax` is there on request (`--norm minmax`).
///
/// A normalisation is computed on each frame, to absorb the frame's own scale and shift; what
/// else moves the frame's statistics between the calibration frame and a later one moves the
/// later frame's whole map. `minmax-unit`, (z − z_min) / (z_max − z_min), is invariant to the
/// frame's scale and shift. The paper's `minmax` adds z_min back, in the model's own output
/// units, so the calibration, which multiplies by about the range z_max − z_min, carries z_min's
/// change times that range into every pixel. For a *depth* z_min is the nearest surface, an
/// object that moves: on m2t2-table (nearest depth 0.76–0.79 m, far background 6.6–6.7 m), an
/// exact metric prediction aligned by SSRA has a masked MAE of 76.1 mm with `minmax`, 13.1 mm
/// with `minmax-unit`, 0.0 mm with `none` (SIMULATED, every error of the simulator off); with
/// the simulator's errors on, averaged over the four shared sets' SSRA, GSSA and LWLR one-shot
/// rows, 44.6, 17.1 and 24.0 mm; REAL Depth Anything 3 metric depth calibrated on one
/// zed-da3-office frame and scored on the others (a moving camera: a stress test, not a fixed
/// cell), 2 797, 947 and 1 061 mm (docs/evaluation.md, "The default normalisation follows the
/// prediction's kind"). For a *disparity* z_min is the far background, which stays, but a
/// relative model's per-frame scale drift moves it in proportion to the size of the model's raw
/// numbers, which no calibration sees: 1 % of drift moves a table by about 2 mm when the raw
/// disparities are about 1 and by about 6 cm when they are about 30
/// (`tests/default_normalisation.rs`); a held-out generator of relative predictions with raw
/// values of 13–50 gave one-shot suction 9 of 171 trials with `minmax` and 120 with
/// `minmax-unit`. On the shared sets (SIMULATED, raw values about 1) `minmax-unit` is as good or
/// better: masked MAE one-shot 8.6 → 6.8, 15.0 → 10.2, 27.4 → 26.6, 24.9 → 25.3 mm, re-aligned
/// 6.1 → 6.2, 11.2 → 10.0, 24.2 → 24.2, 18.1 → 19.0 mm (gqcnn-primesense, graspnet6dof-table,
/// m2t2-table, cleargrasp-transparent; SSRA, GSSA and LWLR, simulator seeds 0 and 1), and issue
/// 22's grasp figures rise (docs/grasping.md).
pub const fn default_normalisation(kind: PredictionKind) -> Normalisation {
    match kind {
        PredictionKind::RelativeDisparity
        | PredictionKind::MetricDepth
        | PredictionKind::RelativeDepth => Normalisation::MinmaxUnit,
    }
}

/// The alignment space used when none is given: depth space for RAW, else the prediction's own.
pub fn default_space(method: &Method, kind: PredictionKind) -> AlignSpace {
    if *method == Method::Raw {
        AlignSpace::Depth
    } else {
        AlignSpace::native(kind)
    }
}

/// The normalisation of a calibration: `norm` and `space` where given, else the defaults
/// ([`default_normalisation`], `none` for RAW, [`default_space`]).
pub fn normalisation(
    method: &Method,
    norm: Option<Normalisation>,
    space: Option<AlignSpace>,
    kind: PredictionKind,
) -> NormalisationConfig {
    NormalisationConfig {
        method: norm.unwrap_or(if *method == Method::Raw {
            Normalisation::None
        } else {
            default_normalisation(kind)
        }),
        space: space.unwrap_or_else(|| default_space(method, kind)),
    }
}

/// The normalisation a method is evaluated with: RAW always `none` in depth space (it is the
/// identity on a metric prediction), the others `norm` in `space` (default: the prediction's
/// own).
pub fn evaluation_normalisation(
    method: &Method,
    norm: Normalisation,
    space: Option<AlignSpace>,
    kind: PredictionKind,
) -> NormalisationConfig {
    if *method == Method::Raw {
        NormalisationConfig {
            method: Normalisation::None,
            space: AlignSpace::Depth,
        }
    } else {
        normalisation(method, Some(norm), space, kind)
    }
}

/// What a calibration will align, which decides what its cross-validation estimates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Protocol {
    /// A fixed camera (MOMA): calibrated once, then applied to other frames, where objects have
    /// moved. The cross-validation predicts each sample without its neighbours (spatially
    /// buffered), so that a correction is kept only where it carries over to content the
    /// calibration frame did not show.
    #[default]
    FixedCamera,
    /// Sparse-to-dense on one frame: the calibration aligns the frame its samples come from
    /// (a camera that moves, sparse depth on every frame). The cross-validation is plain
    /// leave-one-out: the error between samples of the same frame.
    PerFrame,
}

impl Protocol {
    /// Every protocol name, in documentation order.
    pub const NAMES: [&'static str; 2] = ["fixed-camera", "per-frame"];

    /// `fixed-camera` or `per-frame`.
    pub fn name(self) -> &'static str {
        match self {
            Self::FixedCamera => "fixed-camera",
            Self::PerFrame => "per-frame",
        }
    }
}

impl std::fmt::Display for Protocol {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Protocol {
    type Err = CoreError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "fixed-camera" => Ok(Self::FixedCamera),
            "per-frame" => Ok(Self::PerFrame),
            other => Err(CoreError::InvalidParameter(format!(
                "unknown protocol '{other}' (expected one of: {})",
                crate::names::join(Self::NAMES)
            ))),
        }
    }
}

/// The settings of `auto`'s and the local corrections' cross-validation for `protocol`, chosen
/// by measurement (docs/evaluation.md, "Choosing auto's cross-validation"):
/// - fixed camera: [`LocalConfig::default`] (buffer 0.1 × diagonal, squared error in target
///   units, one standard error, b ∈ {0.05, 0.1, 0.2, 0.4} × diagonal, ≥ 10 samples per node,
///   λ ∈ {0.1, 1, 10, 100}); finer bandwidths, other losses or no buffer cost up to 5–12 % MAE
///   on the simulated fixed-camera sets;
/// - per frame: plain leave-one-out, relative error `|ẑ − z|/z`, one standard error,
///   b ∈ {0.03, 0.04, 0.06, 0.1, 0.2, 0.4} × diagonal raised to ≥ 2 samples per node (≈ 31 px
///   for 100 samples at 640×480, 27 px at 640×360), λ ∈ {0.01, 0.1, 1, 10, 100}: 10–30 % lower
///   AbsRel than LWLR on the real Depth Anything 3 frames of zed-da3-office.
pub fn local_config(protocol: Protocol) -> LocalConfig {
    match protocol {
        Protocol::FixedCamera => LocalConfig::default(),
        Protocol::PerFrame => LocalConfig {
            bandwidth_fractions: vec![0.03, 0.04, 0.06, 0.1, 0.2, 0.4],
            ridges: vec![0.01, 0.1, 1.0, 10.0, 100.0],
            min_node_samples: 2.0,
            cv_buffer_fraction: 0.0,
            cv_loss: CvLoss::Rel,
            cv_margin_se: 1.0,
            ..LocalConfig::default()
        },
    }
}

/// The user's settings of a method besides its name ([`method`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MethodOptions {
    /// LWLR bandwidth, pixels (LWLR methods only).
    pub bandwidth_px: Option<f64>,
    /// Camera intrinsics (SSRA's canonical parameters).
    pub intrinsics: Option<Intrinsics>,
    /// What the calibration will align ([`local_config`]).
    pub protocol: Protocol,
    /// Cross-validation loss replacing the protocol's (ssra-local, gssa-local, auto only).
    pub cv_loss: Option<CvLoss>,
    /// Selection margin in standard errors replacing the protocol's (ssra-local, gssa-local,
    /// auto only).
    pub cv_margin_se: Option<f64>,
}

/// `method` with its settings: the intrinsics (SSRA's canonical parameters); for the LWLR
/// methods, a bandwidth in pixels replacing the default; for ssra-local, gssa-local and auto,
/// the cross-validation of `options.protocol` ([`local_config`]) with the loss and margin
/// given.
///
/// # Errors
/// [`CoreError::InvalidParameter`]: a bandwidth that is not a positive number of pixels, or a
/// bandwidth for a method that has none; a cross-validation setting for a method without
/// cross-validation; a negative or non-finite margin.
pub fn method(method: Method, options: &MethodOptions) -> Result<Method> {
    let MethodOptions {
        bandwidth_px,
        intrinsics,
        protocol,
        cv_loss,
        cv_margin_se,
    } = *options;
    if let Some(b) = bandwidth_px
        && !(b.is_finite() && b > 0.0)
    {
        return Err(CoreError::InvalidParameter(format!(
            "bandwidth {b} must be a positive number of pixels"
        )));
    }
    if let Some(k) = cv_margin_se
        && !(k.is_finite() && k >= 0.0)
    {
        return Err(CoreError::InvalidParameter(format!(
            "the selection margin {k} must be a finite number of standard errors ≥ 0"
        )));
    }
    let cv = |_: LocalConfig| LocalConfig {
        cv_loss: cv_loss.unwrap_or(local_config(protocol).cv_loss),
        cv_margin_se: cv_margin_se.unwrap_or(local_config(protocol).cv_margin_se),
        ..local_config(protocol)
    };
    let method = method.with_intrinsics(intrinsics);
    if bandwidth_px.is_some() && !matches!(method, Method::Lwlr(_)) {
        return Err(CoreError::InvalidParameter(format!(
            "a bandwidth applies to the LWLR methods only, not {method}"
        )));
    }
    if (cv_loss.is_some() || cv_margin_se.is_some())
        && !matches!(
            method,
            Method::SsraLocal(_) | Method::GssaLocal(_) | Method::Auto(_)
        )
    {
        // LWLR too: it has no selection to set (the settings were dropped without a word)
        return Err(CoreError::InvalidParameter(format!(
            "a cross-validation loss or margin applies to ssra-local, gssa-local and auto only, \
             not {method}"
        )));
    }
    Ok(match method {
        Method::Lwlr(cfg) => Method::Lwlr(lwlr::LwlrConfig {
            bandwidth_px: bandwidth_px.or(cfg.bandwidth_px),
            ..cfg
        }),
        Method::SsraLocal(c) => Method::SsraLocal(cv(c)),
        Method::GssaLocal(c) => Method::GssaLocal(cv(c)),
        Method::Auto(c) => Method::Auto(cv(c)),
        other => other,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::ImageSize;

    #[test]
    fn defaults_follow_the_method_and_the_kind() {
        let ssra: Method = "ssra".parse().unwrap();
        let n = normalisation(&ssra, None, None, PredictionKind::RelativeDisparity);
        assert_eq!(
            (n.method, n.space),
            (Normalisation::MinmaxUnit, AlignSpace::Inverse)
        );
        let n = normalisation(&ssra, None, None, PredictionKind::MetricDepth);
        assert_eq!(
            (n.method, n.space),
            (Normalisation::MinmaxUnit, AlignSpace::Depth)
        );
        let n = normalisation(&Method::Raw, None, None, PredictionKind::RelativeDisparity);
        assert_eq!(
            (n.method, n.space),
            (Normalisation::None, AlignSpace::Depth)
        );
        let n = normalisation(
            &ssra,
            Some(Normalisation::Median),
            Some(AlignSpace::Depth),
            PredictionKind::RelativeDisparity,
        );
        assert_eq!(
            (n.method, n.space),
            (Normalisation::Median, AlignSpace::Depth)
        );
        let e = evaluation_normalisation(
            &Method::Raw,
            Normalisation::Median,
            None,
            PredictionKind::MetricDepth,
        );
        assert_eq!(
            (e.method, e.space),
            (Normalisation::None, AlignSpace::Depth)
        );
        let e = evaluation_normalisation(
            &ssra,
            Normalisation::Median,
            None,
            PredictionKind::RelativeDisparity,
        );
        assert_eq!(
            (e.method, e.space),
            (Normalisation::Median, AlignSpace::Inverse)
        );
    }

    #[test]
    fn method_settings_and_their_errors() {
        let k = Intrinsics::nominal(ImageSize::new(64, 48));
        let opts = |bandwidth_px, intrinsics| MethodOptions {
            bandwidth_px,
            intrinsics,
            ..Default::default()
        };
        let m = method("lwlr".parse().unwrap(), &opts(Some(25.0), Some(k))).unwrap();
        assert!(matches!(m, Method::Lwlr(c) if c.bandwidth_px == Some(25.0)));
        let m = method("ssra".parse().unwrap(), &opts(None, Some(k))).unwrap();
        assert_eq!(
            m,
            "ssra".parse::<Method>().unwrap().with_intrinsics(Some(k))
        );
        assert!(
            method("gssa".parse().unwrap(), &opts(Some(25.0), None))
                .unwrap_err()
                .to_string()
                .contains("LWLR methods only")
        );
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(
                method("lwlr".parse().unwrap(), &opts(Some(bad), None)).is_err(),
                "{bad}"
            );
        }
    }

    #[test]
    fn cross_validation_follows_the_protocol_and_the_overrides() {
        let per_frame = MethodOptions {
            protocol: Protocol::PerFrame,
            ..Default::default()
        };
        for name in ["auto", "ssra-local", "gssa-local"] {
            let m = method(name.parse().unwrap(), &MethodOptions::default()).unwrap();
            assert_eq!(
                m,
                name.parse::<Method>().unwrap(),
                "{name}: fixed camera = default"
            );
            let m = method(name.parse().unwrap(), &per_frame).unwrap();
            let cfg = match m {
                Method::Auto(c) | Method::SsraLocal(c) | Method::GssaLocal(c) => c,
                other => panic!("{other}"),
            };
            assert_eq!(cfg, local_config(Protocol::PerFrame));
            assert_eq!((cfg.cv_buffer_fraction, cfg.cv_loss), (0.0, CvLoss::Rel));
        }
        let m = method(
            "auto".parse().unwrap(),
            &MethodOptions {
                cv_loss: Some(CvLoss::Abs),
                cv_margin_se: Some(0.0),
                ..per_frame
            },
        )
        .unwrap();
        assert!(matches!(&m, Method::Auto(c) if c.cv_loss == CvLoss::Abs
            && c.cv_margin_se == 0.0 && c.cv_buffer_fraction == 0.0));
        let loss = MethodOptions {
            cv_loss: Some(CvLoss::Rel),
            ..Default::default()
        };
        for name in ["ssra", "gssa", "lwlr", "lwlr-exact", "raw"] {
            let e = method(name.parse().unwrap(), &loss)
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("ssra-local, gssa-local and auto only"),
                "{name}: {e}"
            );
        }
        for bad in [-0.5, f64::NAN, f64::INFINITY] {
            let o = MethodOptions {
                cv_margin_se: Some(bad),
                ..Default::default()
            };
            assert!(method("auto".parse().unwrap(), &o).is_err(), "{bad}");
        }
        assert_eq!("per-frame".parse::<Protocol>().unwrap(), Protocol::PerFrame);
        assert!("sideways".parse::<Protocol>().is_err());
    }
}
