//! Alignment methods: fit on sparse samples, apply to whole normalised maps (docs/method.md §2).
//!
//! A new method is one new module + one variant in [`Method`] and
//! [`AlignmentModel`].

mod grid;
pub mod gssa;
pub mod local;
pub mod lwlr;
pub mod robust;
pub mod ssra;

use std::time::Instant;

use ndarray::{Array2, ArrayView2, ArrayViewMut2};
use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};
use crate::image::{ImageSize, MetricDepth, is_valid_depth};
use crate::normalise::{AlignSpace, NormalisedMap};
use crate::sampling::Pixel;

/// One calibration sample.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sample {
    /// Column, pixels.
    pub u: f64,
    /// Row, pixels.
    pub v: f64,
    /// Normalised prediction ẑ (unitless).
    pub pred: f64,
    /// The ground truth as the fit's target, in the units of [`SampleSet::space`]
    /// ([`AlignSpace::target_unit`]): depth in metres in depth space (always, in files: the field
    /// is `depth_m` there), 1/depth in 1/m in inverse space ([`SampleSet::in_space`]).
    #[serde(rename = "depth_m")]
    pub target: f64,
}

/// The calibration samples of one frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SampleSet {
    /// Size of the image the samples come from.
    pub image_size: ImageSize,
    /// What [`Sample::target`] holds: depth in metres ([`AlignSpace::Depth`], the default and
    /// the only value in files) or the fit's target in inverse space, 1/m
    /// ([`AlignSpace::Inverse`], made by [`SampleSet::in_space`]).
    #[serde(default = "depth_space", skip_serializing_if = "is_depth_space")]
    pub space: AlignSpace,
    /// The samples.
    pub samples: Vec<Sample>,
}

fn depth_space() -> AlignSpace {
    AlignSpace::Depth
}

fn is_depth_space(space: &AlignSpace) -> bool {
    *space == AlignSpace::Depth
}

impl SampleSet {
    /// The same samples with their ground truth as the fit's target in `space`: depth (metres)
    /// in depth space, 1/z (1/m) in inverse space.
    pub fn in_space(&self, space: AlignSpace) -> Self {
        if space == self.space {
            return self.clone();
        }
        Self {
            image_size: self.image_size,
            space,
            samples: self
                .samples
                .iter()
                .map(|s| Sample {
                    target: space.target_from_depth(self.space.depth_from_target(s.target)),
                    ..*s
                })
                .collect(),
        }
    }

    /// The same set with other samples (same image size and space).
    pub fn with_samples(&self, samples: Vec<Sample>) -> Self {
        Self {
            image_size: self.image_size,
            space: self.space,
            samples,
        }
    }

    /// Reads ẑ and ground truth at `pixels`; pixels whose ẑ or ground truth is invalid are skipped.
    ///
    /// # Errors
    /// Size mismatch between `normalised` and `gt`; a pixel outside the image.
    pub fn gather(normalised: &NormalisedMap, gt: &MetricDepth, pixels: &[Pixel]) -> Result<Self> {
        let size = ImageSize::of(&normalised.values.view());
        size.expect_eq("ground truth", gt.size())?;
        let mut samples = Vec::with_capacity(pixels.len());
        for p in pixels {
            let (u, v) = (p.u as usize, p.v as usize);
            if u >= size.width || v >= size.height {
                return Err(CoreError::InvalidParameter(format!(
                    "sample pixel (u={u}, v={v}) lies outside the {size} image"
                )));
            }
            let pred = normalised.values[[v, u]];
            let depth = gt.depth_m[[v, u]];
            if pred.is_finite() && is_valid_depth(depth) {
                samples.push(Sample {
                    u: u as f64,
                    v: v as f64,
                    pred: f64::from(pred),
                    target: f64::from(depth),
                });
            }
        }
        Ok(Self {
            image_size: size,
            space: AlignSpace::Depth,
            samples,
        })
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// `true` when there is no sample.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// The samples' pixel positions `(u, v)` (column, row), in order.
    pub fn pixels_uv(&self) -> Vec<(f64, f64)> {
        self.samples.iter().map(|s| (s.u, s.v)).collect()
    }

    /// Checks every sample: finite pixel position inside the image, finite ẑ, valid depth (> 0 m).
    ///
    /// # Errors
    /// [`CoreError::InvalidSample`] naming the first bad sample.
    pub fn validate(&self) -> Result<()> {
        for (index, s) in self.samples.iter().enumerate() {
            let reason = if !s.pred.is_finite() {
                Some(format!("normalised prediction {} is not finite", s.pred))
            } else if !(s.target.is_finite() && s.target > 0.0) {
                Some(format!(
                    "ground-truth depth {} m is not a valid depth",
                    s.target
                ))
            } else if !(s.u.is_finite() && s.v.is_finite()) {
                Some(format!("pixel position ({}, {}) is not finite", s.u, s.v))
            } else if !(s.u >= 0.0
                && s.v >= 0.0
                && s.u < self.image_size.width as f64
                && s.v < self.image_size.height as f64)
            {
                Some(format!(
                    "pixel position ({}, {}) lies outside the {} image",
                    s.u, s.v, self.image_size
                ))
            } else {
                None
            };
            if let Some(reason) = reason {
                return Err(CoreError::InvalidSample { index, reason });
            }
        }
        Ok(())
    }

    /// Errors with [`CoreError::TooFewSamples`] unless there are at least `need` samples.
    fn require(&self, method: &'static str, need: usize) -> Result<()> {
        if self.samples.len() < need {
            Err(CoreError::TooFewSamples {
                method,
                got: self.samples.len(),
                need,
            })
        } else {
            Ok(())
        }
    }
}

/// Root-mean-square of `predict(sample) − depth` over the samples, metres (0 for no sample).
fn rms_residual(samples: &[Sample], predict: impl Fn(&Sample) -> f64) -> f64 {
    if samples.is_empty() {
        return 0.0;
    }
    let ss: f64 = samples
        .iter()
        .map(|s| {
            let r = predict(s) - s.target;
            r * r
        })
        .sum();
    (ss / samples.len() as f64).sqrt()
}

/// What a fit reports besides its parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FitReport {
    /// The method fitted (its settings are in the model).
    pub method: MethodName,
    /// Samples used.
    pub n_used: usize,
    /// Root-mean-square residual on the calibration samples, metres.
    pub rms_residual_m: f64,
    /// Wall time of the fit, seconds.
    pub fit_time_s: f64,
    /// The robust fit's summary (kind, threshold, inliers, iterations); absent for a plain
    /// least-squares fit (and in files written before robust fits existed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robust: Option<robust::RobustReport>,
}

/// Checks per-sample fit weights: one per sample, each finite and ≥ 0.
fn check_weights(n: usize, weights: &[f64]) -> Result<()> {
    if weights.len() != n {
        return Err(CoreError::InvalidParameter(format!(
            "{} weights for {n} samples",
            weights.len()
        )));
    }
    if let Some((k, w)) = weights
        .iter()
        .enumerate()
        .find(|(_, w)| !(w.is_finite() && **w >= 0.0))
    {
        return Err(CoreError::InvalidParameter(format!(
            "weight of sample #{k} is {w}, must be finite and ≥ 0"
        )));
    }
    Ok(())
}

/// An alignment method with its settings, not yet fitted.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "method", rename_all = "lowercase")]
pub enum Method {
    /// Identity: the prediction is used as metric depth.
    Raw,
    /// Global scale and shift.
    Gssa,
    /// Scale-shift-rotation (the paper's method).
    Ssra(ssra::SsraConfig),
    /// Locally weighted linear regression.
    Lwlr(lwlr::LwlrConfig),
    /// SSRA plus a cross-validated local scale/shift correction (docs/method.md §10).
    #[serde(rename = "ssra-local")]
    SsraLocal(local::LocalConfig),
    /// GSSA plus a cross-validated local scale/shift correction (docs/method.md §10).
    #[serde(rename = "gssa-local")]
    GssaLocal(local::LocalConfig),
    /// The simplest of gssa, ssra, gssa-local, ssra-local and lwlr whose cross-validated error
    /// on the calibration samples is within the rule's margin of the best's
    /// ([`local::fit_auto`]); the settings are those of the cross-validation and of the local
    /// candidates.
    Auto(local::LocalConfig),
}

/// A fitted alignment: everything needed to turn a normalised map into metres. Serialisable into a calibration file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "method", rename_all = "lowercase")]
pub enum AlignmentModel {
    /// Identity.
    Raw,
    /// Global scale and shift.
    Gssa(gssa::GssaModel),
    /// Scale-shift-rotation.
    Ssra(ssra::SsraModel),
    /// Locally weighted linear regression.
    Lwlr(lwlr::LwlrModel),
    /// Global fit plus local correction (`ssra-local`, `gssa-local`).
    Local(Box<local::LocalModel>),
    /// The method chosen by leave-one-out cross-validation.
    Auto(local::AutoModel),
}

impl Method {
    /// Every method name [`Method::from_str`](std::str::FromStr) accepts, in documentation order:
    /// the names of [`MethodName::ALL`].
    pub const NAMES: [&'static str; 9] = {
        let mut names = [""; 9];
        let mut i = 0;
        while i < names.len() {
            names[i] = MethodName::ALL[i].as_str();
            i += 1;
        }
        names
    };

    /// Method name as used on the command line and in files: `ssra`, `gssa`, `raw`, and for
    /// LWLR the preset its settings follow (`lwlr` grid solve, `lwlr-exact` exact solve with
    /// BoostingDepth's pre-fit and ridge, `lwlr-bare` the bare formula).
    pub fn name(&self) -> &'static str {
        MethodName::from(self).as_str()
    }

    /// The method with `intrinsics` used for reporting (SSRA's canonical parameters); other
    /// methods are returned unchanged.
    pub fn with_intrinsics(self, intrinsics: Option<crate::camera::Intrinsics>) -> Self {
        match self {
            Self::Ssra(_) => Self::Ssra(ssra::SsraConfig { intrinsics }),
            other => other,
        }
    }

    /// Minimum number of samples the method needs (RAW: 0, GSSA: 2, SSRA: 4, LWLR: 2,
    /// gssa-local: 4, ssra-local: 6, auto: 3).
    pub fn min_samples(&self) -> usize {
        match self {
            Self::Raw => 0,
            Self::Gssa => gssa::MIN_SAMPLES,
            Self::Ssra(_) => ssra::MIN_SAMPLES,
            Self::Lwlr(_) => lwlr::MIN_SAMPLES,
            Self::GssaLocal(_) => local::GSSA_LOCAL_MIN_SAMPLES,
            Self::SsraLocal(_) => local::SSRA_LOCAL_MIN_SAMPLES,
            Self::Auto(_) => local::AUTO_MIN_SAMPLES,
        }
    }

    /// Fits on `samples`. The report's `rms_residual_m` is the RMS of (fitted − ground truth) on
    /// the calibration samples, in metres (RAW with no sample reports 0).
    ///
    /// # Errors
    /// - [`CoreError::InvalidSample`]: a sample with non-finite ẑ or invalid depth;
    /// - [`CoreError::TooFewSamples`]: GSSA < 2, SSRA < 4, LWLR < 2 samples;
    /// - [`CoreError::Degenerate`]: constant ẑ (GSSA, LWLR), collinear sample pixels or otherwise
    ///   rank-deficient features (SSRA);
    /// - [`CoreError::SizeMismatch`]: SSRA intrinsics for another image size.
    ///
    /// # Example
    /// ```
    /// use moma_core::align::{Method, Sample, SampleSet};
    /// use moma_core::normalise::AlignSpace;
    /// use moma_core::ImageSize;
    /// let samples = (0..10)
    ///     .map(|k| Sample { u: k as f64, v: 0.0, pred: k as f64, target: 0.5 + 0.1 * k as f64 })
    ///     .collect();
    /// let set = SampleSet { image_size: ImageSize::new(10, 1), space: AlignSpace::Depth, samples };
    /// let (model, report) = Method::Gssa.fit(&set).unwrap();
    /// assert!(report.rms_residual_m < 1e-12);
    /// ```
    pub fn fit(&self, samples: &SampleSet) -> Result<(AlignmentModel, FitReport)> {
        let start = Instant::now();
        samples.validate()?;
        samples.require(self.name(), self.min_samples())?;
        let model = match self {
            Self::Raw => AlignmentModel::Raw,
            Self::Gssa => AlignmentModel::Gssa(gssa::fit(&samples.samples)?),
            Self::Ssra(cfg) => AlignmentModel::Ssra(ssra::fit(samples, cfg)?),
            Self::Lwlr(cfg) => AlignmentModel::Lwlr(lwlr::fit(samples, cfg)?),
            Self::SsraLocal(cfg) => {
                AlignmentModel::Local(Box::new(local::fit(samples, local::LocalBase::Ssra, cfg)?))
            }
            Self::GssaLocal(cfg) => {
                AlignmentModel::Local(Box::new(local::fit(samples, local::LocalBase::Gssa, cfg)?))
            }
            Self::Auto(cfg) => AlignmentModel::Auto(local::fit_auto(samples, cfg)?),
        };
        let rms_residual_m = match &model {
            AlignmentModel::Raw => rms_residual(&samples.samples, |s| s.pred),
            AlignmentModel::Gssa(m) => rms_residual(&samples.samples, |s| m.predict(s.pred)),
            AlignmentModel::Ssra(m) => {
                rms_residual(&samples.samples, |s| m.predict(s.u, s.v, s.pred))
            }
            AlignmentModel::Lwlr(m) => m.rms_residual_m(),
            m @ (AlignmentModel::Local(_) | AlignmentModel::Auto(_)) => {
                rms_residual(&samples.samples, |s| m.predict_at(s.u, s.v, s.pred))
            }
        };
        let report = FitReport {
            method: MethodName::from(self),
            n_used: samples.len(),
            rms_residual_m,
            fit_time_s: start.elapsed().as_secs_f64(),
            robust: None,
        };
        Ok((model, report))
    }
}

/// The name of an LWLR configuration: the preset its solve, pre-fit and ridge follow.
/// Which alignment method, without its settings: what a fit report, a calibration file's
/// summary and `auto`'s candidate list record. Named as [`Method::name`] and
/// [`AlignmentModel::name`] name them (serialised as that name, parsed with [`Method::NAMES`] in
/// the error). A [`Method`] is the method *with* its settings, a fitted [`AlignmentModel`] the
/// result; both give their `MethodName` with [`MethodName::from`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(try_from = "String", into = "&'static str")]
pub enum MethodName {
    /// `raw`.
    Raw,
    /// `gssa`.
    Gssa,
    /// `ssra`.
    Ssra,
    /// `lwlr` (grid solve, BoostingDepth's).
    Lwlr,
    /// `lwlr-exact`.
    LwlrExact,
    /// `lwlr-bare`.
    LwlrBare,
    /// `ssra-local`.
    SsraLocal,
    /// `gssa-local`.
    GssaLocal,
    /// `auto`.
    Auto,
}

impl MethodName {
    /// Every method, in documentation order ([`Method::NAMES`] are their names).
    pub const ALL: [MethodName; 9] = [
        Self::Ssra,
        Self::Gssa,
        Self::Lwlr,
        Self::LwlrExact,
        Self::LwlrBare,
        Self::SsraLocal,
        Self::GssaLocal,
        Self::Auto,
        Self::Raw,
    ];

    /// The name on the command line and in files.
    pub const fn as_str(self) -> &'static str {
        match self {
            Self::Raw => "raw",
            Self::Gssa => "gssa",
            Self::Ssra => "ssra",
            Self::Lwlr => "lwlr",
            Self::LwlrExact => "lwlr-exact",
            Self::LwlrBare => "lwlr-bare",
            Self::SsraLocal => "ssra-local",
            Self::GssaLocal => "gssa-local",
            Self::Auto => "auto",
        }
    }
}

impl std::fmt::Display for MethodName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for MethodName {
    type Err = CoreError;
    fn from_str(s: &str) -> Result<Self> {
        crate::names::parse(s, &Self::ALL, Self::as_str, "method")
    }
}

impl TryFrom<String> for MethodName {
    type Error = CoreError;
    fn try_from(s: String) -> Result<Self> {
        s.parse()
    }
}

impl From<MethodName> for &'static str {
    fn from(m: MethodName) -> Self {
        m.as_str()
    }
}

impl PartialEq<&str> for MethodName {
    fn eq(&self, other: &&str) -> bool {
        self.as_str() == *other
    }
}

impl From<&Method> for MethodName {
    fn from(m: &Method) -> Self {
        match m {
            Method::Raw => Self::Raw,
            Method::Gssa => Self::Gssa,
            Method::Ssra(_) => Self::Ssra,
            Method::Lwlr(cfg) => lwlr_name(cfg),
            Method::SsraLocal(_) => Self::SsraLocal,
            Method::GssaLocal(_) => Self::GssaLocal,
            Method::Auto(_) => Self::Auto,
        }
    }
}

impl From<&AlignmentModel> for MethodName {
    fn from(m: &AlignmentModel) -> Self {
        match m {
            AlignmentModel::Raw => Self::Raw,
            AlignmentModel::Gssa(_) => Self::Gssa,
            AlignmentModel::Ssra(_) => Self::Ssra,
            AlignmentModel::Lwlr(m) => lwlr_name(&m.config),
            AlignmentModel::Local(m) => m.method_name(),
            AlignmentModel::Auto(_) => Self::Auto,
        }
    }
}

fn lwlr_name(cfg: &lwlr::LwlrConfig) -> MethodName {
    match cfg.solve {
        lwlr::LwlrSolve::Grid => MethodName::Lwlr,
        lwlr::LwlrSolve::Exact if !cfg.global_prefit && cfg.ridge_shift == 0.0 => {
            MethodName::LwlrBare
        }
        lwlr::LwlrSolve::Exact => MethodName::LwlrExact,
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Method {
    type Err = CoreError;
    /// Parses a name of [`Method::NAMES`] ([`MethodName`]) into the method with its default
    /// settings (SSRA without intrinsics: see [`Method::with_intrinsics`]).
    fn from_str(s: &str) -> Result<Self> {
        Ok(Self::with_defaults(s.parse()?))
    }
}

impl Method {
    /// The method called `name` with its default settings.
    pub fn with_defaults(name: MethodName) -> Self {
        match name {
            MethodName::Ssra => Self::Ssra(ssra::SsraConfig::default()),
            MethodName::Gssa => Self::Gssa,
            MethodName::Lwlr => Self::Lwlr(lwlr::LwlrConfig::faithful()),
            MethodName::LwlrExact => Self::Lwlr(lwlr::LwlrConfig::exact()),
            MethodName::LwlrBare => Self::Lwlr(lwlr::LwlrConfig::bare_exact()),
            MethodName::SsraLocal => Self::SsraLocal(local::LocalConfig::default()),
            MethodName::GssaLocal => Self::GssaLocal(local::LocalConfig::default()),
            MethodName::Auto => Self::Auto(local::LocalConfig::default()),
            MethodName::Raw => Self::Raw,
        }
    }
}

impl AlignmentModel {
    /// Method name (`raw`, `gssa`, `ssra`, `lwlr`, `lwlr-exact`, `lwlr-bare`, `ssra-local`,
    /// `gssa-local`, `auto`).
    pub fn name(&self) -> &'static str {
        MethodName::from(self).as_str()
    }

    /// The fitted value at pixel `(u, v)` for normalised value ẑ = `pred`, in the fit's target
    /// space (metres in depth space), exactly as [`AlignmentModel::apply`] computes it there
    /// (LWLR: from its full-size maps at the nearest pixel), in f64.
    pub fn predict_at(&self, u: f64, v: f64, pred: f64) -> f64 {
        match self {
            Self::Raw => pred,
            Self::Gssa(m) => m.predict(pred),
            Self::Ssra(m) => m.predict(u, v, pred),
            Self::Lwlr(m) => m.predict_at_pixel(u, v, pred),
            Self::Local(m) => m.predict_at(u, v, pred),
            Self::Auto(m) => m.chosen.predict_at(u, v, pred),
        }
    }

    /// Checks a model read from a file: finite parameters, SSRA's linear and canonical
    /// parameters describing the same model (relative difference ≤ 1e-6), LWLR's settings and
    /// bandwidth (> 0) valid, image sizes non-empty.
    ///
    /// # Errors
    /// [`CoreError::InvalidParameter`] naming the bad value.
    pub fn validate(&self) -> Result<()> {
        let finite = |what: &str, x: f64| {
            if x.is_finite() {
                Ok(())
            } else {
                Err(CoreError::InvalidParameter(format!(
                    "{} parameter {what} is {x}, not a finite number",
                    self.name()
                )))
            }
        };
        if let Some(size) = self.image_size()
            && !size.is_within_limits()
        {
            return Err(CoreError::InvalidParameter(format!(
                "{} calibration image size {size} is empty or too large",
                self.name()
            )));
        }
        match self {
            Self::Raw => Ok(()),
            Self::Gssa(m) => {
                finite("scale", m.scale)?;
                finite("shift", m.shift)
            }
            Self::Ssra(m) => {
                finite("alpha_per_px", m.alpha_per_px)?;
                finite("beta_per_px", m.beta_per_px)?;
                finite("gamma", m.gamma)?;
                finite("t3", m.t3)?;
                for (name, x) in ["s", "theta_rad", "phi_rad", "t3", "cx_px", "cy_px", "f_px"]
                    .iter()
                    .zip(m.canonical.as_array())
                {
                    finite(name, x)?;
                }
                if m.canonical.f_px.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                    return Err(CoreError::InvalidParameter(format!(
                        "ssra canonical f_px is {}, must be > 0",
                        m.canonical.f_px
                    )));
                }
                // Compare the two parameterisations as models: predictions at the image corners
                // for ẑ = 1 and the shift.
                let (a, b, g, t) = m.canonical.to_linear();
                let (w, h) = (m.image_size.width as f64, m.image_size.height as f64);
                let corners = [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)];
                let scale = corners
                    .iter()
                    .map(|&(u, v)| (m.alpha_per_px * u + m.beta_per_px * v + m.gamma).abs())
                    .fold(m.t3.abs(), f64::max)
                    .max(1e-12);
                let worst = corners
                    .iter()
                    .map(|&(u, v)| {
                        ((a * u + b * v + g) - (m.alpha_per_px * u + m.beta_per_px * v + m.gamma))
                            .abs()
                    })
                    .fold((t - m.t3).abs(), f64::max);
                if worst > 1e-6 * scale {
                    return Err(CoreError::InvalidParameter(format!(
                        "ssra linear parameters (alpha, beta, gamma, t3) and canonical parameters \
                         describe different models (difference {worst:.3e} m per unit ẑ)"
                    )));
                }
                Ok(())
            }
            Self::Lwlr(m) => m.validate(),
            Self::Local(m) => m.validate(),
            Self::Auto(m) => m.validate(),
        }
    }

    /// The calibration image size when the model depends on pixel position (SSRA, LWLR).
    pub fn image_size(&self) -> Option<ImageSize> {
        match self {
            Self::Raw | Self::Gssa(_) => None,
            Self::Ssra(m) => Some(m.image_size),
            Self::Lwlr(m) => Some(m.image_size),
            Self::Local(m) => Some(m.image_size),
            Self::Auto(m) => m.chosen.image_size(),
        }
    }

    /// Applies the alignment to a whole normalised map; pixels with non-finite ẑ, and pixels
    /// where the model's output is not positive (no depth), are `NaN`.
    /// Output in metres. One fused pass; see [`AlignmentModel::apply_into`] to reuse a buffer.
    ///
    /// # Errors
    /// Size mismatch with the calibration image.
    pub fn apply(&self, normalised: ArrayView2<'_, f32>) -> Result<MetricDepth> {
        let mut out = Array2::<f32>::zeros(normalised.raw_dim());
        self.apply_into(normalised, &mut out.view_mut())?;
        Ok(MetricDepth::new(out))
    }

    /// Like [`AlignmentModel::apply`], writing metres into `out` (same shape as `normalised`)
    /// without allocating (LWLR computes and caches its maps on first use).
    ///
    /// # Errors
    /// Size mismatch between `normalised` and `out`, or with the calibration image.
    pub fn apply_into(
        &self,
        normalised: ArrayView2<'_, f32>,
        out: &mut ArrayViewMut2<'_, f32>,
    ) -> Result<()> {
        let size = ImageSize::of(&normalised);
        size.expect_eq("output buffer", ImageSize::new(out.ncols(), out.nrows()))?;
        if let Some(calib) = self.image_size() {
            calib.expect_eq("normalised map", size)?;
        }
        match self {
            Self::Raw => out.zip_mut_with(&normalised, |o, &z| {
                *o = crate::kernels::positive_or_nan(z);
            }),
            Self::Gssa(m) => {
                let (s, t) = (m.scale as f32, m.shift as f32);
                crate::kernels::map_rows(normalised, out, |_, zin, zout| {
                    crate::kernels::affine(zin, zout, s, t)
                });
            }
            Self::Ssra(m) => m.apply_into(normalised, out),
            Self::Lwlr(m) => m.apply_into(normalised, out),
            Self::Local(m) => m.apply_into(normalised, out),
            Self::Auto(m) => m.chosen.apply_into(normalised, out)?,
        }
        Ok(())
    }
}
