//! The defaults that every front end shares, decided once from typed inputs: the method's
//! settings, the normalisation and the alignment space by prediction kind. `moma calibrate`,
//! Python's `moma.calibrate` and the evaluation protocol call these functions instead of
//! deciding on their own.
//!
//! The rules:
//! - normalisation: `minmax` unless given (the paper's); RAW refuses any normalisation but
//!   `none` when it is fitted ([`crate::CalibrationConfig::check`]), so a user must say `none` to
//!   use a prediction as metres; an evaluation of RAW uses `none` in depth space whatever the
//!   other methods' normalisation ([`evaluation_normalisation`]);
//! - space: the prediction's own unless given ([`AlignSpace::native`]: inverse space for
//!   inverse-depth predictions, the only way to undo a relative model's disparity shift), depth
//!   space for RAW;
//! - method settings: SSRA gets the camera intrinsics (its canonical parameters are reported
//!   with them); an LWLR bandwidth is for the LWLR methods only.

use crate::align::{Method, lwlr};
use crate::camera::Intrinsics;
use crate::error::{CoreError, Result};
use crate::image::PredictionKind;
use crate::normalise::{AlignSpace, Normalisation, NormalisationConfig};

/// The normalisation used when none is given.
pub const DEFAULT_NORMALISATION: Normalisation = Normalisation::Minmax;

/// The alignment space used when none is given: depth space for RAW, else the prediction's own.
pub fn default_space(method: &Method, kind: PredictionKind) -> AlignSpace {
    if *method == Method::Raw {
        AlignSpace::Depth
    } else {
        AlignSpace::native(kind)
    }
}

/// The normalisation of a calibration: `norm` and `space` where given, else the defaults
/// ([`DEFAULT_NORMALISATION`], [`default_space`]).
pub fn normalisation(
    method: &Method,
    norm: Option<Normalisation>,
    space: Option<AlignSpace>,
    kind: PredictionKind,
) -> NormalisationConfig {
    NormalisationConfig {
        method: norm.unwrap_or(DEFAULT_NORMALISATION),
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

/// `method` with its settings: the intrinsics (SSRA's canonical parameters) and, for the LWLR
/// methods, a bandwidth in pixels replacing the default.
///
/// # Errors
/// [`CoreError::InvalidParameter`]: a bandwidth that is not a positive number of pixels, or a
/// bandwidth for a method that has none.
pub fn method(
    method: Method,
    bandwidth_px: Option<f64>,
    intrinsics: Option<Intrinsics>,
) -> Result<Method> {
    if let Some(b) = bandwidth_px
        && !(b.is_finite() && b > 0.0)
    {
        return Err(CoreError::InvalidParameter(format!(
            "bandwidth {b} must be a positive number of pixels"
        )));
    }
    Ok(match method.with_intrinsics(intrinsics) {
        Method::Lwlr(cfg) => Method::Lwlr(lwlr::LwlrConfig {
            bandwidth_px: bandwidth_px.or(cfg.bandwidth_px),
            ..cfg
        }),
        other if bandwidth_px.is_some() => {
            return Err(CoreError::InvalidParameter(format!(
                "a bandwidth applies to the LWLR methods only, not {other}"
            )));
        }
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
        let n = normalisation(&ssra, None, None, PredictionKind::InverseDepth);
        assert_eq!(
            (n.method, n.space),
            (Normalisation::Minmax, AlignSpace::Inverse)
        );
        let n = normalisation(&ssra, None, None, PredictionKind::Depth);
        assert_eq!(n.space, AlignSpace::Depth);
        let n = normalisation(&Method::Raw, None, None, PredictionKind::InverseDepth);
        assert_eq!(
            (n.method, n.space),
            (Normalisation::Minmax, AlignSpace::Depth)
        );
        let n = normalisation(
            &ssra,
            Some(Normalisation::Median),
            Some(AlignSpace::Depth),
            PredictionKind::InverseDepth,
        );
        assert_eq!(
            (n.method, n.space),
            (Normalisation::Median, AlignSpace::Depth)
        );
        let e = evaluation_normalisation(
            &Method::Raw,
            Normalisation::Median,
            None,
            PredictionKind::Depth,
        );
        assert_eq!(
            (e.method, e.space),
            (Normalisation::None, AlignSpace::Depth)
        );
        let e = evaluation_normalisation(
            &ssra,
            Normalisation::Median,
            None,
            PredictionKind::InverseDepth,
        );
        assert_eq!(
            (e.method, e.space),
            (Normalisation::Median, AlignSpace::Inverse)
        );
    }

    #[test]
    fn method_settings_and_their_errors() {
        let k = Intrinsics::nominal(ImageSize::new(64, 48));
        let m = method("lwlr".parse().unwrap(), Some(25.0), Some(k)).unwrap();
        assert!(matches!(m, Method::Lwlr(c) if c.bandwidth_px == Some(25.0)));
        let m = method("ssra".parse().unwrap(), None, Some(k)).unwrap();
        assert_eq!(
            m,
            "ssra".parse::<Method>().unwrap().with_intrinsics(Some(k))
        );
        assert!(
            method("gssa".parse().unwrap(), Some(25.0), None)
                .unwrap_err()
                .to_string()
                .contains("LWLR methods only")
        );
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(
                method("lwlr".parse().unwrap(), Some(bad), None).is_err(),
                "{bad}"
            );
        }
    }
}
