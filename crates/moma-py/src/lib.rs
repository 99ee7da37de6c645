//! # moma-py — the Python extension `moma._moma`
//!
//! Thin bindings over moma-core (calibration, alignment, metrics, back-projection), moma-io
//! (depth files, camera.json, calibration files in the CLI's format) and moma-depth (Depth
//! Anything V2, candle backend; ONNX Runtime with the `onnx` feature). The Python package
//! (`python/moma`) re-exports everything and holds the exception classes and type stubs.
//!
//! Conventions: arrays are NumPy `(height, width)`; depth in metres (`float32`, NaN = no depth);
//! pixel coordinates u right, v down; camera frame x right, y down, z forward. The GIL is released
//! while aligning, calibrating and running the depth model.

mod arrays;
mod errors;

use std::path::PathBuf;
use std::sync::Mutex;

use moma_core::align::Method;
use moma_core::align::robust::{Robust, RobustKind};
use moma_core::metrics::DepthMetrics;
use moma_core::normalise::{AlignSpace, Normalisation};
use moma_core::pipeline::{
    AlignOptions, Calibration as CoreCalibration, CalibrationConfig, CalibrationFrame,
    PredictionInput,
};
use moma_core::realign::{AnchorTarget, CorrectionModel, RealignConfig};
use moma_core::sampling::{SamplingConfig, SamplingStrategy};
use moma_core::{
    CoreError, ImageSize, Intrinsics as CoreIntrinsics, Mask, MetricDepth, Prediction,
    PredictionKind,
};
use moma_depth::{Backbone, DepthModel as DepthModelTrait, Head, ModelSpec};
use moma_io::{CalibrationFile, CreationInfo};
use ndarray::Array2;
use numpy::{IntoPyArray, PyArray2};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};

use crate::arrays::{f32_2d, f32_owned, metres_2d, metres_owned, opt_mask, rgb_image};
use crate::errors::{IntoPyErr, Kind, ResultExt, err, unsigned, value_err};

// ---------------------------------------------------------------------------------------------
// names → moma-core enums (each name is defined once, in moma-core, with FromStr / Display)

fn parse_kind(s: &str) -> PyResult<PredictionKind> {
    s.parse::<PredictionKind>().py()
}

fn parse_norm(s: &str) -> PyResult<Normalisation> {
    s.parse::<Normalisation>().py()
}

fn parse_sampling(s: &str) -> PyResult<SamplingStrategy> {
    s.parse::<SamplingStrategy>().py()
}

/// The alignment method with its settings ([`moma_core::policy::method`], as `moma calibrate`).
fn parse_method(s: &str, options: &moma_core::policy::MethodOptions) -> PyResult<Method> {
    let method: Method = s.parse().py()?;
    moma_core::policy::method(method, options).map_err(|e| value_err(e.to_string()))
}

/// One frame's re-alignment into `out` (the zero-copy view path of `Calibration::align`):
/// its report, and the frame's normalisation note.
fn realign_view_into(
    cal: &CoreCalibration,
    pred: ndarray::ArrayView2<'_, f32>,
    kind: moma_core::PredictionKind,
    rgb: ndarray::ArrayView3<'_, u8>,
    config: &RealignConfig,
    mut out: ndarray::ArrayViewMut2<'_, f32>,
) -> Result<(moma_core::realign::RealignReport, Option<String>), CoreError> {
    let grey = moma_io::grey_half(rgb)?;
    let report = cal.align(
        PredictionInput::view(pred, kind),
        &AlignOptions::realigned(&grey, config),
        &mut out,
    )?;
    let note = report.normalisation_note;
    report.realign.map(|r| (r, note)).ok_or_else(|| {
        CoreError::InvalidParameter("re-alignment was asked for but gave no report".into())
    })
}

/// The re-alignment settings: [`RealignConfig::default`] (what `moma align --realign anchors`
/// uses) with the given keyword options replacing fields.
fn realign_config(options: Option<&Bound<'_, PyDict>>) -> PyResult<RealignConfig> {
    const NAMES: &str = "correction, target, ridge, max_anchors, min_anchors, \
                         min_anchor_fraction, holdout_fraction, acceptance_se, seed, abs_grey, \
                         rel_grey";
    let mut c = RealignConfig::default();
    let Some(options) = options else {
        return Ok(c);
    };
    for (key, value) in options.iter() {
        let key: String = key.extract()?;
        let bad = |e: PyErr| value_err(format!("re-alignment option {key}: {e}"));
        match key.as_str() {
            "correction" => {
                c.model = value
                    .extract::<String>()
                    .map_err(bad)?
                    .parse::<CorrectionModel>()
                    .py()?;
            }
            "target" => {
                c.target = value
                    .extract::<String>()
                    .map_err(bad)?
                    .parse::<AnchorTarget>()
                    .py()?;
            }
            "ridge" => c.ridge = value.extract().map_err(bad)?,
            "max_anchors" => c.max_anchors = value.extract().map_err(bad)?,
            "min_anchors" => c.min_anchors = value.extract().map_err(bad)?,
            "min_anchor_fraction" => c.min_anchor_fraction = value.extract().map_err(bad)?,
            "holdout_fraction" => c.holdout_fraction = value.extract().map_err(bad)?,
            "acceptance_se" => c.acceptance_se = value.extract().map_err(bad)?,
            "seed" => c.seed = value.extract().map_err(bad)?,
            "abs_grey" => c.thresholds.abs_grey = value.extract().map_err(bad)?,
            "rel_grey" => c.thresholds.rel = value.extract().map_err(bad)?,
            other => {
                return Err(value_err(format!(
                    "unknown re-alignment option '{other}' (expected one of: {NAMES})"
                )));
            }
        }
    }
    c.validate().py()?;
    Ok(c)
}

/// A serde value as a Python object (through `json.loads`).
fn to_py_json<'py>(py: Python<'py>, value: &impl serde::Serialize) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(value)
        .map_err(|e| err(Kind::Backend, format!("cannot encode as JSON: {e}")))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// A Python object (dict, list, …) decoded through JSON into `T`.
fn from_py_json<T: serde::de::DeserializeOwned>(
    value: &Bound<'_, PyAny>,
    what: &str,
) -> PyResult<T> {
    let text: String = value
        .py()
        .import("json")?
        .call_method1("dumps", (value,))?
        .extract()?;
    serde_json::from_str(&text).map_err(|e| value_err(format!("{what}: {e}")))
}

// ---------------------------------------------------------------------------------------------
// Intrinsics

/// `Intrinsics(fx, fy, cx, cy, width, height)`'s arguments.
type IntrinsicsArgs = (f64, f64, f64, f64, usize, usize);

/// Pinhole camera intrinsics in pixels, for an image of `width × height` pixels.
#[pyclass(module = "moma", frozen, eq)]
#[derive(Debug, Clone, PartialEq)]
struct Intrinsics {
    inner: CoreIntrinsics,
}

#[pymethods]
impl Intrinsics {
    #[new]
    #[pyo3(signature = (fx, fy, cx, cy, width, height))]
    fn new(fx: f64, fy: f64, cx: f64, cy: f64, width: i128, height: i128) -> PyResult<Self> {
        let inner = CoreIntrinsics {
            width: unsigned("width", width)?,
            height: unsigned("height", height)?,
            fx,
            fy,
            cx,
            cy,
        };
        inner.validate().py()?;
        Ok(Self { inner })
    }

    /// Reads a `camera.json` (`{"width","height","fx","fy","cx","cy"}`, pixels).
    #[staticmethod]
    fn load(path: PathBuf) -> PyResult<Self> {
        Ok(Self {
            inner: moma_io::read_camera(&path).py()?,
        })
    }

    /// Writes a `camera.json` (atomically).
    fn save(&self, path: PathBuf) -> PyResult<()> {
        moma_io::write_camera(&path, &self.inner).py()
    }

    /// Pickling (multiprocessing, `copy.deepcopy`): the constructor's arguments.
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> (Bound<'py, PyAny>, IntrinsicsArgs) {
        let k = slf.get().inner;
        (
            slf.get_type().into_any(),
            (k.fx, k.fy, k.cx, k.cy, k.width, k.height),
        )
    }

    /// Focal length along u (columns), pixels.
    #[getter]
    fn fx(&self) -> f64 {
        self.inner.fx
    }
    /// Focal length along v (rows), pixels.
    #[getter]
    fn fy(&self) -> f64 {
        self.inner.fy
    }
    /// Principal point column, pixels.
    #[getter]
    fn cx(&self) -> f64 {
        self.inner.cx
    }
    /// Principal point row, pixels.
    #[getter]
    fn cy(&self) -> f64 {
        self.inner.cy
    }
    /// Image width, pixels.
    #[getter]
    fn width(&self) -> usize {
        self.inner.width
    }
    /// Image height, pixels.
    #[getter]
    fn height(&self) -> usize {
        self.inner.height
    }

    /// The fields as a dict (the `camera.json` keys).
    fn to_dict<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py_json(py, &self.inner)
    }

    fn __repr__(&self) -> String {
        let k = &self.inner;
        format!(
            "Intrinsics(fx={}, fy={}, cx={}, cy={}, width={}, height={})",
            k.fx, k.fy, k.cx, k.cy, k.width, k.height
        )
    }
}

// ---------------------------------------------------------------------------------------------
// Calibration

/// A fitted calibration (alignment + normalisation), as written by `moma calibrate`.
#[pyclass(module = "moma", frozen)]
struct Calibration {
    /// The calibration; it owns its workspace mask (embedded in the file).
    inner: CoreCalibration,
    intrinsics: Option<CoreIntrinsics>,
    created: Option<CreationInfo>,
}

impl Calibration {
    fn of_file(file: CalibrationFile) -> Self {
        Self {
            inner: file.calibration,
            intrinsics: file.intrinsics,
            created: Some(file.created),
        }
    }

    fn file(&self) -> CalibrationFile {
        let created = self
            .created
            .clone()
            .unwrap_or_else(|| CreationInfo::now().with_source("python", "moma.calibrate"));
        CalibrationFile::new(self.inner.clone(), self.intrinsics, created)
    }

    /// The camera to plan with: `cam` where given, else the intrinsics the calibration records.
    fn camera(&self, cam: Option<&Intrinsics>) -> PyResult<CoreIntrinsics> {
        match (cam, self.intrinsics) {
            (Some(c), _) => Ok(c.inner),
            (None, Some(k)) => Ok(k),
            (None, None) => Err(value_err(
                "cam= is needed: the calibration records no intrinsics",
            )),
        }
    }
}

#[pymethods]
impl Calibration {
    /// Aligns a prediction of the calibrated kind and size: metric depth, float32 metres, NaN where
    /// no depth can be inferred. The GIL is released during the computation.
    fn align<'py>(
        &self,
        py: Python<'py>,
        pred: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let ro = f32_2d(pred, "pred")?;
        // Borrowed, not copied: NumPy's buffer is read in place (any strides).
        let view = ro.as_array();
        let kind = self.inner.prediction_kind;
        let input = PredictionInput::view(view, kind);
        let aligned = py
            .detach(|| self.inner.aligned(input, &AlignOptions::default()))
            .py()?;
        normalisation_warning(
            py,
            "Calibration.align",
            aligned.normalisation_note.as_deref(),
        )?;
        Ok(aligned.depth.depth_m.into_pyarray(py))
    }

    /// Like `align`, writing metres into `out` (float32, same shape as `pred`, writable) instead
    /// of allocating the result.
    fn align_into(
        &self,
        py: Python<'_>,
        pred: &Bound<'_, PyAny>,
        out: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let mut rw = arrays::f32_2d_out(out)?;
        let ro = f32_2d(pred, "pred")?;
        let view = ro.as_array();
        let mut out_view = rw.as_array_mut();
        let kind = self.inner.prediction_kind;
        let input = PredictionInput::view(view, kind);
        let report = py
            .detach(|| {
                self.inner
                    .align(input, &AlignOptions::default(), &mut out_view)
            })
            .py()?;
        normalisation_warning(
            py,
            "Calibration.align_into",
            report.normalisation_note.as_deref(),
        )
    }

    /// Writes the calibration in the CLI's file format (`moma-calibration` JSON, the current
    /// version, atomic), the workspace mask and anchor store (if any) embedded: the file is
    /// self-contained.
    fn save(&self, path: PathBuf) -> PyResult<()> {
        moma_io::write_calibration(&path, &self.file()).py()
    }

    /// Reads a calibration file written by `moma calibrate` or `Calibration.save` (any version
    /// this moma reads; version 1 is migrated).
    #[staticmethod]
    fn load(path: PathBuf) -> PyResult<Self> {
        Ok(Self::of_file(moma_io::read_calibration(&path).py()?))
    }

    /// A calibration from the JSON text of a calibration file (`to_json`'s inverse; checked as
    /// `load` checks a file).
    #[staticmethod]
    fn from_json(text: &str) -> PyResult<Self> {
        let file = moma_io::parse_calibration(std::path::Path::new("<json text>"), text).py()?;
        Ok(Self::of_file(file))
    }

    /// Pickling (multiprocessing, `copy.deepcopy`) goes through the file's JSON text.
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<(Bound<'py, PyAny>, (String,))> {
        let from_json = slf.get_type().getattr("from_json")?;
        Ok((from_json, (slf.borrow().to_json()?,)))
    }

    /// The fit summary, as `moma calibrate --json` prints it: `method`, `n_used`,
    /// `rms_residual_m` (metres), `fit_time_s` (seconds), `model` (the fitted parameters) and,
    /// for a robust fit only, `robust` (`kind`, `threshold_m`, `inliers`, `iterations`,
    /// `inlier_rms_residual_m`, …: the file's robust block).
    #[getter]
    fn report<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let r = &self.inner.report;
        let d = PyDict::new(py);
        d.set_item("method", r.method.as_str())?;
        d.set_item("n_used", r.n_used)?;
        d.set_item("rms_residual_m", r.rms_residual_m)?;
        d.set_item("fit_time_s", r.fit_time_s)?;
        d.set_item("model", to_py_json(py, &self.inner.model)?)?;
        if let Some(robust) = &r.robust {
            d.set_item("robust", to_py_json(py, robust)?)?;
        }
        Ok(d)
    }

    /// The error this calibration is expected to make away from its samples, by
    /// cross-validation on them (`moma calibrate`'s `predicted_error`): `{"protocol", "abs_rel",
    /// "rms_m"}` (metres), or None for a robust fit. `protocol`: "fixed-camera" (spatially
    /// buffered folds) or "per-frame" (plain leave-one-out) for gssa, ssra and lwlr; auto and the
    /// local variants report their own cross-validation.
    #[pyo3(signature = (protocol="fixed-camera"))]
    fn predicted_error<'py>(&self, py: Python<'py>, protocol: &str) -> PyResult<Bound<'py, PyAny>> {
        let protocol: moma_core::policy::Protocol = protocol.parse().py()?;
        let cv = self.inner.predicted_error(protocol).py()?;
        to_py_json(
            py,
            &cv.map(|cv| {
                serde_json::json!({
                    "protocol": self.inner.predicted_error_protocol(protocol),
                    "abs_rel": cv.abs_rel, "rms_m": cv.rms_m,
                })
            }),
        )
    }

    /// Whether the calibration holds the anchor store that `align_realigned` needs (made with
    /// `calibrate(..., anchors_rgb=...)` or `moma calibrate --anchors`).
    #[getter]
    fn has_anchors(&self) -> bool {
        self.inner.anchor_store().is_ok()
    }

    /// The calibration's error model of its aligned depth (a dict: `sigma_flat_m`,
    /// `sigma_dense_m` (absent in files before version 7), `depth_ref_m`, `depth_exponent`,
    /// `variance_shares`, `scales_px`, `relief_bias`, `relief_sigma`, `relief_radius_px`,
    /// `relief_max_m`, `edge_gain`, `edge_radius_px`, and `height_sigma` where the calibration
    /// has a height part: absent otherwise and in files before version 8, and
    /// `sample_distance_gain` where its samples reach only part of the image: absent otherwise
    /// and in files before version 9), None in files written before error models existed.
    #[getter]
    fn error_model<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py_json(py, &self.inner.error_model)
    }

    /// The per-pixel σ of the error of `depth_m` (this calibration's aligned depth of a frame,
    /// float32 metres) as `moma align --sigma-map` writes it: float32 metres, NaN where there is
    /// no depth. `report`: the re-alignment report of the frame (`align_realigned`'s), whose
    /// held-out anchor RMSE sets the flat σ (added to the calibration's own error for the
    /// default anchor target, `Calibration::frame_error_model`). An error when the calibration
    /// has no error model.
    #[pyo3(signature = (depth_m, report=None))]
    fn sigma_map<'py>(
        &self,
        py: Python<'py>,
        depth_m: &Bound<'py, PyAny>,
        report: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let depth = MetricDepth::new(metres_owned(depth_m, "depth_m")?);
        self.inner
            .image_size()
            .expect_eq("depth_m", depth.size())
            .py()?;
        let report: Option<moma_core::realign::RealignReport> = match report {
            Some(r) if !r.is_none() => Some(from_py_json(r, "report")?),
            _ => None,
        };
        let model = self
            .inner
            .frame_error_model(report.as_ref())
            .ok_or_else(|| {
                value_err(
                    "this calibration holds no error model (written before error models existed): \
                 calibrate again",
                )
            })?;
        let sigma = py.detach(|| model.sigma_map(&depth));
        Ok(sigma.into_pyarray(py))
    }

    /// `align`, then per-frame re-alignment on static anchors found in this frame's RGB
    /// (`moma align --realign anchors`): returns `(depth_m, report)`, float32 metres and the
    /// per-frame report as `moma align --realign anchors --json` prints it (`anchors`,
    /// `anchors_used`, `brightness_gain`, `held_out_rmse_before_m`, `held_out_rmse_after_m`
    /// (metres, None when not measured), `accepted`, `reason`, `held_out_truth_rmse_m`: the
    /// frame's error against the calibration frame's ground truth at anchors no fit used). When
    /// the correction is rejected or too few anchors remain (a covered background), the
    /// one-shot result is returned and
    /// `report["accepted"]` is False with the reason. `rgb`: uint8 `height × width × 3`, read in
    /// place. Options (keywords, defaults as the CLI's): `correction` (`"scale-shift"`,
    /// `"planar"`), `target` (`"calibration-output"`, `"ground-truth"`), `ridge`, `max_anchors`,
    /// `min_anchors`, `min_anchor_fraction`, `holdout_fraction`, `seed`, `abs_grey` (grey levels
    /// 0–255), `rel_grey` (fraction). The GIL is released during the computation.
    #[pyo3(signature = (pred, rgb, **options))]
    fn align_realigned<'py>(
        &self,
        py: Python<'py>,
        pred: &Bound<'py, PyAny>,
        rgb: &Bound<'py, PyAny>,
        options: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<(Bound<'py, PyArray2<f32>>, Bound<'py, PyAny>)> {
        let config = realign_config(options)?;
        self.inner.anchor_store().py()?; // no store: fail before aligning
        let ro = f32_2d(pred, "pred")?;
        let rgb_ro = arrays::rgb_ro(rgb, "rgb")?;
        let (view, rgb_view) = (ro.as_array(), rgb_ro.as_array());
        let kind = self.inner.prediction_kind;
        let (depth, report) = py
            .detach(|| {
                let (h, w) = view.dim();
                let mut depth = Array2::<f32>::zeros((h, w));
                let report = realign_view_into(
                    &self.inner,
                    view,
                    kind,
                    rgb_view,
                    &config,
                    depth.view_mut(),
                )?;
                Ok::<_, CoreError>((depth, report))
            })
            .py()?;
        let (report, note) = report;
        normalisation_warning(py, "Calibration.align_realigned", note.as_deref())?;
        Ok((depth.into_pyarray(py), to_py_json(py, &report)?))
    }

    /// Like `align_realigned`, writing metres into `out` (float32, same shape as `pred`,
    /// writable) instead of allocating; returns the report.
    #[pyo3(signature = (pred, rgb, out, **options))]
    fn align_realigned_into<'py>(
        &self,
        py: Python<'py>,
        pred: &Bound<'py, PyAny>,
        rgb: &Bound<'py, PyAny>,
        out: &Bound<'py, PyAny>,
        options: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let config = realign_config(options)?;
        self.inner.anchor_store().py()?;
        let mut rw = arrays::f32_2d_out(out)?;
        let ro = f32_2d(pred, "pred")?;
        let rgb_ro = arrays::rgb_ro(rgb, "rgb")?;
        let (view, rgb_view) = (ro.as_array(), rgb_ro.as_array());
        let mut out_view = rw.as_array_mut();
        let kind = self.inner.prediction_kind;
        let (report, note) = py
            .detach(|| {
                realign_view_into(
                    &self.inner,
                    view,
                    kind,
                    rgb_view,
                    &config,
                    out_view.view_mut(),
                )
            })
            .py()?;
        normalisation_warning(py, "Calibration.align_realigned_into", note.as_deref())?;
        to_py_json(py, &report)
    }

    /// `"metric-depth"`, `"relative-depth"` or `"relative-disparity"`: the prediction kind this
    /// calibration accepts (a `"relative-depth"` calibration also accepts `"metric-depth"`).
    #[getter]
    fn kind(&self) -> String {
        self.inner.prediction_kind.to_string()
    }

    /// Alignment method name, as in files: `raw`, `gssa`, `ssra`, `lwlr`, `lwlr-exact`, `lwlr-bare`,
    /// `ssra-local` or `gssa-local` (`auto` records the method it chose).
    #[getter]
    fn method(&self) -> &'static str {
        self.inner.model.name()
    }

    /// Normalisation name (`minmax`, `minmax-unit`, `median`, `none`).
    #[getter]
    fn norm(&self) -> &'static str {
        self.inner.normalisation.method.name()
    }

    /// Alignment space: `"inverse"` (disparity predictor, 1/z target) or `"depth"`.
    #[getter]
    fn space(&self) -> &'static str {
        self.inner.normalisation.space.name()
    }

    /// Calibration image size `(height, width)` in pixels (the NumPy shape predictions must have).
    #[getter]
    fn shape(&self) -> (usize, usize) {
        self.inner.samples.image_size.shape()
    }

    /// The camera intrinsics recorded with the calibration, if any.
    #[getter]
    fn intrinsics(&self) -> Option<Intrinsics> {
        self.intrinsics.map(|inner| Intrinsics { inner })
    }

    /// The workspace mask used for normalisation (bool, height × width), if any.
    #[getter]
    fn workspace<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray2<bool>>> {
        self.inner
            .workspace
            .as_ref()
            .map(|w| w.mask().data().clone().into_pyarray(py))
    }

    /// The calibration samples as an `n × 4` float64 array: u (px), v (px), normalised prediction, depth (m).
    #[getter]
    fn samples<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let s = &self.inner.samples.samples;
        Array2::from_shape_fn((s.len(), 4), |(i, j)| match j {
            0 => s[i].u,
            1 => s[i].v,
            2 => s[i].pred,
            _ => s[i].target,
        })
        .into_pyarray(py)
    }

    /// The calibration file's JSON text (what `save` writes).
    fn to_json(&self) -> PyResult<String> {
        serde_json::to_string_pretty(&self.file())
            .map_err(|e| err(Kind::Backend, format!("cannot encode calibration: {e}")))
    }

    fn __repr__(&self) -> String {
        let r = &self.inner.report;
        let (h, w) = self.inner.samples.image_size.shape();
        format!(
            "Calibration(method='{}', kind='{}', norm='{}', shape=({h}, {w}), n_used={}, rms_residual_m={:.6})",
            r.method,
            self.inner.prediction_kind,
            self.inner.normalisation.method.name(),
            r.n_used,
            r.rms_residual_m
        )
    }
}

/// `obj` as a list of frames when it is a list or tuple whose first item is 2-D (few-shot
/// calibration: one array per frame), else `None` (one frame's array, or a nested list of
/// numbers). An empty list or tuple is a list of no frames.
fn frame_list<'py>(
    obj: &Bound<'py, PyAny>,
    what: &str,
) -> PyResult<Option<Vec<Bound<'py, PyAny>>>> {
    if !(obj.is_instance_of::<PyList>() || obj.is_instance_of::<PyTuple>()) {
        return Ok(None);
    }
    let items = obj.try_iter()?.collect::<PyResult<Vec<_>>>()?;
    let Some(first) = items.first() else {
        return Ok(Some(items));
    };
    let ndim: usize = obj
        .py()
        .import("numpy")?
        .call_method1("ndim", (first,))
        .and_then(|n| n.extract())
        .map_err(|e| value_err(format!("{what}[0]: not an array: {e}")))?;
    Ok((ndim == 2).then_some(items))
}

/// The robust fit of `robust=` / `robust_threshold_m=` (RANSAC seeded with `seed`), as
/// `moma calibrate --robust KIND --robust-threshold-m M` builds it: `Robust`'s own defaults for
/// what is not given.
fn robust_from(
    robust: Option<&str>,
    threshold_m: Option<f64>,
    seed: u64,
    method: &Method,
) -> PyResult<Option<Robust>> {
    let Some(kind) = robust else {
        if let Some(t) = threshold_m {
            return Err(value_err(format!(
                "robust_threshold_m={t} needs robust= ('huber', 'tukey' or 'ransac')"
            )));
        }
        return Ok(None);
    };
    let kind: RobustKind = kind.parse().py()?;
    let mut r = Robust::new(kind).with_seed(seed);
    if let Some(t) = threshold_m {
        r = r.with_threshold_m(t);
    }
    r.validate()
        .map_err(|e| value_err(format!("robust_threshold_m: {e}")))?;
    r.check_method(method).py()?;
    Ok(Some(r))
}

/// Fits an alignment on one frame, or on several frames of the same camera (few-shot), as
/// `moma calibrate` does; with `anchors_rgb`, also stores the anchors for per-frame re-alignment
/// (`moma calibrate --anchors --anchors-rgb`).
#[pyfunction]
#[pyo3(signature = (pred, gt_m, cam=None, *, kind, method="ssra", norm=None, samples=100,
    sampling="random", seed=0, edge_margin_px=0, mask=None, workspace=None, space=None, bandwidth_px=None,
    robust=None, robust_threshold_m=None, anchors_rgb=None, protocol="fixed-camera", cv_loss=None,
    cv_margin_se=None))]
#[allow(clippy::too_many_arguments)]
fn calibrate(
    py: Python<'_>,
    pred: &Bound<'_, PyAny>,
    gt_m: &Bound<'_, PyAny>,
    cam: Option<&Intrinsics>,
    kind: &str,
    method: &str,
    norm: Option<&str>,
    samples: i128,
    sampling: &str,
    seed: i128,
    edge_margin_px: i128,
    mask: Option<&Bound<'_, PyAny>>,
    workspace: Option<&Bound<'_, PyAny>>,
    space: Option<&str>,
    bandwidth_px: Option<f64>,
    robust: Option<&str>,
    robust_threshold_m: Option<f64>,
    anchors_rgb: Option<&Bound<'_, PyAny>>,
    protocol: &str,
    cv_loss: Option<&str>,
    cv_margin_se: Option<f64>,
) -> PyResult<Calibration> {
    let (samples, seed, edge_margin_px): (usize, u64, u32) = (
        unsigned("samples", samples)?,
        unsigned("seed", seed)?,
        unsigned("edge_margin_px", edge_margin_px)?,
    );
    let kind = parse_kind(kind)?;
    let intrinsics = cam.map(|c| c.inner);
    let space = space.map(|s| s.parse::<AlignSpace>()).transpose().py()?;
    let method = parse_method(
        method,
        &moma_core::policy::MethodOptions {
            bandwidth_px,
            intrinsics,
            protocol: protocol.parse().py()?,
            cv_loss: cv_loss.map(str::parse).transpose().py()?,
            cv_margin_se,
        },
    )?;
    let norm = norm.map(parse_norm).transpose()?;
    let normalisation = moma_core::policy::normalisation(&method, norm, space, kind);
    let config = CalibrationConfig {
        robust: robust_from(robust, robust_threshold_m, seed, &method)?,
        method,
        normalisation,
        sampling: SamplingConfig {
            strategy: parse_sampling(sampling)?,
            n: samples,
            seed,
            edge_margin_px,
        },
        workspace: None,
    };

    // One frame (arrays) or several (lists of arrays, one per frame).
    let (pred_items, gt_items, few_shot) = match (
        frame_list(pred, "pred")?,
        frame_list(gt_m, "gt_m")?,
    ) {
        (None, None) => (vec![pred.clone()], vec![gt_m.clone()], false),
        (Some(p), Some(g)) => {
            if p.len() != g.len() {
                return Err(value_err(format!(
                    "calibrate takes one ground truth per prediction (the calibration frames, in \
                     order): got {} predictions and {} ground truths",
                    p.len(),
                    g.len()
                )));
            }
            if p.is_empty() {
                return Err(value_err(
                    "calibrate needs at least one frame: pred and gt_m are empty lists",
                ));
            }
            (p, g, true)
        }
        (p, _) => {
            let (list, one) = if p.is_some() {
                ("pred", "gt_m")
            } else {
                ("gt_m", "pred")
            };
            return Err(value_err(format!(
                "pred and gt_m must both be arrays (one frame) or both lists of arrays (several \
                 frames, one ground truth per prediction): {list} is a list, {one} one array"
            )));
        }
    };
    let n_frames = pred_items.len();
    let preds_ro = pred_items
        .iter()
        .enumerate()
        .map(|(i, p)| f32_2d(p, &frame_name("pred", i, few_shot)))
        .collect::<PyResult<Vec<_>>>()?;
    let gts_ro = gt_items
        .iter()
        .enumerate()
        .map(|(i, g)| metres_2d(g, &frame_name("gt_m", i, few_shot)))
        .collect::<PyResult<Vec<_>>>()?;
    // Sample masks: none, one for all frames, or one per frame.
    let sample_masks: Vec<Mask> = match mask.filter(|m| !m.is_none()) {
        None => Vec::new(),
        Some(m) => match frame_list(m, "mask")? {
            None => vec![arrays::mask(m, "mask")?],
            Some(list) => {
                if list.len() != 1 && list.len() != n_frames {
                    return Err(value_err(format!(
                        "give one mask for all frames or one per frame: got {} masks for {n_frames} \
                         frame(s)",
                        list.len()
                    )));
                }
                list.iter()
                    .enumerate()
                    .map(|(i, m)| arrays::mask(m, &format!("mask[{i}]")))
                    .collect::<PyResult<Vec<_>>>()?
            }
        },
    };
    let workspace = opt_mask(workspace, "workspace")?;
    let anchors = match anchors_rgb.filter(|a| !a.is_none()) {
        None => None,
        // A path (str or os.PathLike) is read as `moma calibrate --anchors-rgb` reads it.
        Some(a) => Some(match a.extract::<PathBuf>() {
            Ok(path) => AnchorRgb::File(path),
            Err(_)
                if a.cast::<numpy::PyUntypedArray>().is_ok()
                    || a.is_instance_of::<PyList>()
                    || a.is_instance_of::<PyTuple>() =>
            {
                AnchorRgb::Array(arrays::rgb_ro(a, "anchors_rgb")?)
            }
            Err(_) => {
                return Err(value_err(format!(
                    "anchors_rgb must be an image path (str or os.PathLike) or a uint8 \
                     height × width × 3 array, got {}",
                    a.get_type().name()?
                )));
            }
        }),
    };

    let pred_views: Vec<_> = preds_ro.iter().map(|r| r.as_array()).collect();
    let gt_views: Vec<_> = gts_ro.iter().map(|r| r.as_array()).collect();
    let anchor_view = match &anchors {
        Some(AnchorRgb::Array(ro)) => Some(ro.as_array()),
        _ => None,
    };
    let anchor_path = match &anchors {
        Some(AnchorRgb::File(p)) => Some(p.as_path()),
        _ => None,
    };
    let (inner, reach) = py
        .detach(|| -> Result<_, PyCalibrateError> {
            let preds: Vec<PredictionInput<'_>> = pred_views
                .iter()
                .map(|v| PredictionInput::view(v.view(), kind))
                .collect();
            let gts: Vec<MetricDepth> = gt_views
                .iter()
                .map(|v| MetricDepth::new(v.to_owned()))
                .collect();
            let size = ImageSize::of(&pred_views[0]);
            if let Some(k) = &intrinsics {
                k.size()
                    .expect_eq("prediction (vs camera intrinsics)", size)?;
            }
            let frames: Vec<CalibrationFrame<'_>> = preds
                .iter()
                .zip(&gts)
                .enumerate()
                .map(|(i, (&pred, gt))| {
                    CalibrationFrame::new(pred, gt)
                        .sampled_in(sample_masks.get(i).or(sample_masks.first()))
                })
                .collect();
            let config = config.clone().with_workspace(workspace.as_ref())?;
            let calibration = moma_core::calibrate(&frames, &config)?;
            let reach = moma_core::sampling::sample_reach_over(
                &calibration.samples,
                &gts.iter().collect::<Vec<_>>(),
            );
            // Anchors for per-frame re-alignment come from the first (calibration) frame.
            let calibration = match (anchor_view, anchor_path) {
                (Some(view), _) => {
                    size.expect_eq("anchors_rgb", ImageSize::new(view.dim().1, view.dim().0))?;
                    calibration.with_anchors(&moma_io::grey_half(view)?, &gts[0], preds[0])?
                }
                (None, Some(path)) => {
                    let img = moma_io::read_rgb_sized(path, size)?;
                    let view = ndarray::ArrayView3::from_shape(
                        (img.height() as usize, img.width() as usize, 3),
                        img.as_raw().as_slice(),
                    )
                    .map_err(|e| CoreError::InvalidParameter(format!("{}: {e}", path.display())))?;
                    calibration.with_anchors(&moma_io::grey_half(view)?, &gts[0], preds[0])?
                }
                (None, None) => calibration,
            };
            Ok((calibration, reach))
        })
        .map_err(|e| match e {
            PyCalibrateError::Core(e) => e.into_py_err(),
            PyCalibrateError::Io(e) => e.into_py_err(),
        })?;
    if let Some(w) = reach.and_then(|r| r.warning("mask=", inner.error_model.as_ref())) {
        user_warning(py, &w)?;
    }
    if inner.error_model.is_none() {
        user_warning(py, moma_core::pipeline::NO_ERROR_MODEL_WARNING)?;
    }
    for note in &inner.normalisation_notes {
        user_warning(py, &format!("moma.calibrate: {note}"))?;
    }
    if let Some(w) = inner
        .anchor_store()
        .ok()
        .and_then(|s| s.saturation_warning())
    {
        user_warning(py, &format!("moma.calibrate: {w} (anchors_rgb=)"))?;
    }
    // stamped when made (not each time it is written): `to_json`, `save` and pickling then
    // give the same text
    Ok(Calibration {
        inner,
        intrinsics,
        created: Some(CreationInfo::now().with_source("python", "moma.calibrate")),
    })
}

/// `anchors_rgb=`: a file or an array borrowed from NumPy.
enum AnchorRgb<'py> {
    File(PathBuf),
    Array(numpy::PyReadonlyArray3<'py, u8>),
}

/// The errors of the calibration step run without the GIL.
enum PyCalibrateError {
    Core(CoreError),
    Io(moma_io::IoError),
}

impl From<CoreError> for PyCalibrateError {
    fn from(e: CoreError) -> Self {
        Self::Core(e)
    }
}

impl From<moma_io::IoError> for PyCalibrateError {
    fn from(e: moma_io::IoError) -> Self {
        Self::Io(e)
    }
}

/// `what` for one frame, `what[i]` for frame `i` of several.
fn frame_name(what: &str, i: usize, few_shot: bool) -> String {
    if few_shot {
        format!("{what}[{i}]")
    } else {
        what.to_string()
    }
}

// ---------------------------------------------------------------------------------------------
// metrics, points, files

/// Depth metrics of `depth_m` against `gt_m` over pixels valid in both (and inside `mask`).
#[pyfunction]
#[pyo3(signature = (depth_m, gt_m, mask=None))]
fn metrics<'py>(
    py: Python<'py>,
    depth_m: &Bound<'py, PyAny>,
    gt_m: &Bound<'py, PyAny>,
    mask: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let pred = MetricDepth::new(metres_owned(depth_m, "depth_m")?);
    let gt = MetricDepth::new(metres_owned(gt_m, "gt_m")?);
    let mask = opt_mask(mask, "mask")?;
    let m = py
        .detach(|| DepthMetrics::compute(&pred, &gt, mask.as_ref()))
        .py()?;
    let d = PyDict::new(py);
    d.set_item("d105", m.d105)?;
    d.set_item("d110", m.d110)?;
    d.set_item("d125", m.d125)?;
    d.set_item("rel", m.rel)?;
    d.set_item("rmse", m.rmse)?;
    d.set_item("mae", m.mae)?;
    d.set_item("n", m.n)?;
    Ok(d)
}

/// Back-projects the valid pixels of `depth_m` (row-major order): `N × 3` float32 points in
/// metres, camera frame; with `rgb`, also their `N × 3` uint8 colours.
#[pyfunction]
#[pyo3(signature = (depth_m, cam, rgb=None))]
fn depth_to_points<'py>(
    py: Python<'py>,
    depth_m: &Bound<'py, PyAny>,
    cam: &Intrinsics,
    rgb: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyAny>> {
    let depth = MetricDepth::new(metres_owned(depth_m, "depth_m")?);
    let image = rgb
        .filter(|o| !o.is_none())
        .map(|o| rgb_image(o, "rgb"))
        .transpose()?;
    if let Some(img) = &image {
        let got = moma_core::ImageSize::new(img.width() as usize, img.height() as usize);
        depth.size().expect_eq("rgb", got).py()?;
    }
    let k = cam.inner;
    let points = py.detach(|| moma_core::depth_to_points(&depth, &k)).py()?;
    let xyz =
        Array2::from_shape_fn((points.len(), 3), |(i, j)| points[i].xyz_m[j]).into_pyarray(py);
    match image {
        None => Ok(xyz.into_any()),
        Some(img) => {
            let colours = Array2::from_shape_fn((points.len(), 3), |(i, j)| {
                img.get_pixel(points[i].u, points[i].v).0[j]
            })
            .into_pyarray(py);
            Ok((xyz, colours).into_pyobject(py)?.into_any())
        }
    }
}

// `grasp_draws=4` is written out in plan_grasps' signature (a path there shows as `...` in
// `help()`); it is the library's default.
const _: () = assert!(moma_grasp::DEFAULT_GRASP_DRAWS == 4);

/// Plans grasps on one frame, best first, as a list of dicts (`moma grasp --json`'s array).
///
/// `source` is a metric depth map (float32 metres, NaN or ≤ 0 = no depth; `cam` required) or a
/// `Calibration` with `pred=` (the frame's prediction; `cam` defaults to the calibration's
/// intrinsics): the depth is then aligned as `moma grasp --calib` does, re-aligned on static
/// anchors when `rgb=` (uint8 `height × width × 3`) is given (with `realign=`, a dict of
/// `Calibration.align_realigned`'s options, e.g. `{"correction": "planar"}`, as `moma grasp`'s
/// `--realign-*` flags; a frame that keeps the one-shot depth says why in a `UserWarning`),
/// and the calibration's error model
/// gives every grasp a `success_prob` (from the depth maps drawn from it on which the grasp
/// succeeds: `(successes + 1) / (draws + 2)`). With a depth map, `sigma_m=` (a uniform σ,
/// metres) does the same. `grasp_quality` is `"robust"` (the default where there is an error
/// model: by the share of successful draws) or `"nominal"` (by the planner's score);
/// `grasp_draws` depth draws (seeded by `seed`); `min_success_prob` drops grasps below it.
/// Other keywords: `gripper` (`"parallel"` or `"suction"`), `gripper_config` (the gripper's
/// geometry, as `moma grasp --gripper-config` reads it: a path to its JSON file, or a dict of
/// the same fields), `tie_tolerance` (the robust ranking's, as `--grasp-tie-tolerance`),
/// `extrinsics` (camera → robot base: a 4 × 4 array of rows, or a path to the JSON file of
/// `--extrinsics`; adds each grasp's `"base"` pose), `mask` (`height × width`, bool or integer
/// labels, nonzero = object: one value per object keeps touching objects apart), `top`,
/// `seed`, `keep_border_objects` (without a mask, a region touching the image border is no
/// object unless kept), `keep_containers` (nor is a region enclosing an opening of a
/// container's size, a bin's walls, nor background beside neither the support plane nor a
/// container; a `UserWarning` says when any was dropped). No grasp found is an empty
/// list, not an error, with the reason as a `UserWarning` (e.g. every grasp below
/// `min_success_prob`, which with N draws cannot exceed `(N + 1) / (N + 2)`). The GIL is
/// released while planning.
#[pyfunction]
#[pyo3(signature = (source, cam=None, gripper="parallel", mask=None, top=10, seed=0, keep_border_objects=false, *, pred=None, rgb=None, sigma_m=None, grasp_quality=None, grasp_draws=4, min_success_prob=None, gripper_config=None, tie_tolerance=None, extrinsics=None, keep_containers=false, realign=None))]
#[allow(clippy::too_many_arguments)] // Python keyword arguments, not a Rust API
fn plan_grasps<'py>(
    py: Python<'py>,
    source: &Bound<'py, PyAny>,
    cam: Option<&Intrinsics>,
    gripper: &str,
    mask: Option<&Bound<'py, PyAny>>,
    top: i128,
    seed: i128,
    keep_border_objects: bool,
    pred: Option<&Bound<'py, PyAny>>,
    rgb: Option<&Bound<'py, PyAny>>,
    sigma_m: Option<f64>,
    grasp_quality: Option<&str>,
    grasp_draws: i128,
    min_success_prob: Option<f64>,
    gripper_config: Option<&Bound<'py, PyAny>>,
    tie_tolerance: Option<f32>,
    extrinsics: Option<&Bound<'py, PyAny>>,
    keep_containers: bool,
    realign: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyAny>> {
    use moma_grasp::{GraspRequest, SceneConfig};
    let (top, seed, grasp_draws): (usize, u64, usize) = (
        unsigned("top", top)?,
        unsigned("seed", seed)?,
        unsigned("grasp_draws", grasp_draws)?,
    );
    let gripper = match gripper_config {
        None => default_gripper(gripper)?,
        Some(config) => gripper_from_config(gripper, config)?,
    };
    gripper
        .validate()
        .map_err(|e| value_err(format!("gripper_config: {e}")))?;
    let extrinsics = extrinsics.map(extrinsics_from_py).transpose()?;
    let (depth, error_model, k) = match source.cast::<Calibration>() {
        Ok(cal) => {
            let cal = cal.borrow();
            let pred = pred.ok_or_else(|| {
                value_err("planning from a Calibration needs the frame's prediction: pred=")
            })?;
            let prediction = Prediction::new(f32_owned(pred, "pred")?, cal.inner.prediction_kind);
            let k = cal.camera(cam)?;
            let rgb_ro = rgb.map(|r| arrays::rgb_ro(r, "rgb")).transpose()?;
            if realign.is_some() && rgb_ro.is_none() {
                return Err(value_err(
                    "realign= sets the re-alignment on static anchors, which needs the frame's \
                     rgb=",
                ));
            }
            let config = realign_config(realign)?;
            let rgb_view = rgb_ro.as_ref().map(|r| r.as_array());
            let inner = &cal.inner;
            let aligned = py
                .detach(|| {
                    let grey = rgb_view.map(moma_io::grey_half).transpose()?;
                    let options = moma_core::AlignOptions {
                        realign: grey.as_ref().map(|g| (g, &config)),
                        sigma_map: false,
                    };
                    inner.aligned(&prediction, &options)
                })
                .py()?;
            normalisation_warning(py, "plan_grasps", aligned.normalisation_note.as_deref())?;
            // as `moma grasp` prints it: a frame that kept the one-shot depth is said so
            if let Some(report) = aligned.realign.as_ref().filter(|r| !r.accepted) {
                user_warning(
                    py,
                    &format!("moma.plan_grasps: re-alignment (rgb=): {}", report.reason),
                )?;
            }
            (aligned.depth, aligned.error_model, k)
        }
        Err(_) => {
            if pred.is_some() || rgb.is_some() || realign.is_some() {
                return Err(value_err(
                    "pred=, rgb= and realign= go with a Calibration as the first argument, not \
                     a depth map",
                ));
            }
            let k = cam
                .ok_or_else(|| value_err("cam= is needed with a depth map"))?
                .inner;
            (MetricDepth::new(metres_owned(source, "depth_m")?), None, k)
        }
    };
    let error_model = match sigma_m {
        Some(s) => Some(
            moma_core::DepthErrorModel::uniform_for_width(s, depth.size().width)
                .map_err(|e| value_err(format!("sigma_m: {e}")))?,
        ),
        None => error_model,
    };
    let mask = arrays::opt_object_mask(mask, "mask")?;
    let mut request = GraspRequest::new(gripper).with_error_model(error_model);
    request.top_k = top;
    request.seed = seed;
    request.draws = grasp_draws;
    request.min_success_prob = min_success_prob;
    if let Some(t) = tie_tolerance {
        request.tie_tolerance = t;
    }
    request.scene = SceneConfig::keeping(keep_border_objects, keep_containers);
    if let Some(q) = grasp_quality {
        request.quality = q.parse().py()?;
    }
    request.validate().map_err(|e| value_err(e.to_string()))?;
    let (scene, mut outcome) = py
        .detach(|| moma_grasp::plan_grasps(&depth, &k, mask.as_ref(), &request))
        .map_err(|e| value_err(e.to_string()))?;
    if let Some(note) = scene.border_note() {
        user_warning(
            py,
            &format!(
                "moma.plan_grasps: {note} (keep_border_objects=True keeps them, mask= chooses \
                 objects)"
            ),
        )?;
    }
    if let Some(note) = scene.container_note() {
        user_warning(py, &format!("moma.plan_grasps: {note} (mask=)"))?;
    }
    if let Some(note) = scene.floating_note() {
        user_warning(
            py,
            &format!("moma.plan_grasps: {note} (mask= chooses objects)"),
        )?;
    }
    if let Some(e) = &extrinsics {
        outcome.set_base(e);
    }
    // no grasp is an empty list, not an error; the reason (`moma grasp` prints it on stderr)
    // comes as a UserWarning
    if outcome.grasps.is_empty()
        && let Some(reason) = &outcome.no_grasp_reason
    {
        user_warning(py, &format!("moma.plan_grasps: no grasp: {reason}"))?;
    }
    to_py_json(py, &outcome.grasps)
}

/// The frame's normalisation note ([`moma_core::FrameReport::normalisation_note`]) as a
/// `UserWarning` of `what`, as the CLI prints it.
fn normalisation_warning(py: Python<'_>, what: &str, note: Option<&str>) -> PyResult<()> {
    match note {
        Some(note) => user_warning(py, &format!("moma.{what}: {note}")),
        None => Ok(()),
    }
}

/// Issues a Python `UserWarning` (filtered and caught as Python's warnings are).
fn user_warning(py: Python<'_>, message: &str) -> PyResult<()> {
    PyErr::warn(
        py,
        &py.get_type::<pyo3::exceptions::PyUserWarning>(),
        &std::ffi::CString::new(message).map_err(|e| value_err(e.to_string()))?,
        1,
    )
}

/// The default geometry of gripper `name` (`parallel` or `suction`).
fn default_gripper(name: &str) -> PyResult<moma_grasp::Gripper> {
    name.parse::<moma_grasp::GripperKind>()
        .map(moma_grasp::GripperKind::default_gripper)
        .map_err(|e| value_err(e.to_string()))
}

/// The `gripper` of geometry `config`: a path to the JSON file `moma grasp --gripper-config`
/// reads, or a dict of its fields.
fn gripper_from_config(kind: &str, config: &Bound<'_, PyAny>) -> PyResult<moma_grasp::Gripper> {
    use moma_grasp::{Gripper, GripperKind};
    let kind = kind
        .parse::<GripperKind>()
        .map_err(|e| value_err(e.to_string()))?;
    let what = "gripper_config";
    let from_file = config.extract::<std::path::PathBuf>().ok();
    Ok(match (kind, from_file) {
        (GripperKind::Parallel, Some(p)) => Gripper::Parallel(moma_io::read_json(p, what).py()?),
        (GripperKind::Suction, Some(p)) => Gripper::Suction(moma_io::read_json(p, what).py()?),
        (GripperKind::Parallel, None) => Gripper::Parallel(from_py_json(config, what)?),
        (GripperKind::Suction, None) => Gripper::Suction(from_py_json(config, what)?),
    })
}

/// Camera → robot base extrinsics: a 4 × 4 array-like of rows, or a path to the JSON file
/// `moma grasp --extrinsics` reads; checked as the CLI checks them.
fn extrinsics_from_py(value: &Bound<'_, PyAny>) -> PyResult<moma_grasp::Extrinsics> {
    let rows: [[f64; 4]; 4] = match value.extract::<std::path::PathBuf>() {
        Ok(path) => moma_io::read_extrinsics(path).py()?,
        Err(_) => {
            let list = value
                .py()
                .import("numpy")?
                .call_method1("asarray", (value, "float64"))
                .map_err(|e| value_err(format!("extrinsics: not a 4 × 4 array: {e}")))?
                .call_method0("tolist")?;
            from_py_json(&list, "extrinsics (a 4 × 4 array of rows)")?
        }
    };
    moma_grasp::Extrinsics::new(rows).map_err(|e| value_err(format!("extrinsics: {e}")))
}

/// The grasp check of a frame whose ground truth is known, as `moma calibrate --grasp-check`
/// runs it on the calibration frame: `pred` (the frame's prediction) aligned one-shot by
/// `calibration` and planned on with its error model as `plan_grasps` plans (`gripper`,
/// default geometry; `mask`, `seed`), every grasp executed on `gt_m` (float32 metres, NaN or
/// ≤ 0 = no depth) by the proxy's rules. Returns a dict: `gripper`, `scores` (`"proxy"`),
/// `grasps`, `successes`, `success_rate`, `mean_success_prob`, `failures` (by reason),
/// `no_grasp_reason` and `notes` (regions the planner left out: at the image border, a
/// container's walls; each also a `UserWarning`, as `plan_grasps` gives it). PROXY scores, not robot trials; on the calibration frame it is a gauge
/// of the cell, not a forecast (docs/grasping.md). The GIL is released while planning.
#[pyfunction]
#[pyo3(signature = (calibration, pred, gt_m, cam=None, gripper="suction", mask=None, seed=0))]
#[allow(clippy::too_many_arguments)] // Python keyword arguments, not a Rust API
fn grasp_check<'py>(
    py: Python<'py>,
    calibration: &Calibration,
    pred: &Bound<'py, PyAny>,
    gt_m: &Bound<'py, PyAny>,
    cam: Option<&Intrinsics>,
    gripper: &str,
    mask: Option<&Bound<'py, PyAny>>,
    seed: i128,
) -> PyResult<Bound<'py, PyAny>> {
    let seed: u64 = unsigned("seed", seed)?;
    let gripper = default_gripper(gripper)?;
    let k = calibration.camera(cam)?;
    let prediction = Prediction::new(f32_owned(pred, "pred")?, calibration.inner.prediction_kind);
    let truth = MetricDepth::new(metres_owned(gt_m, "gt_m")?);
    let mask = arrays::opt_object_mask(mask, "mask")?;
    let inner = &calibration.inner;
    let check = py
        .detach(|| {
            moma_grasp::calibration_frame_check(
                inner,
                &prediction,
                &truth,
                &k,
                mask.as_ref(),
                gripper,
                seed,
            )
        })
        .py()?;
    for note in &check.notes {
        user_warning(py, &format!("moma.grasp_check: {note}"))?;
    }
    to_py_json(py, &check)
}

/// Reads metric depth: uint16 PNG (millimetres, 0 = none), `.npy` (metres) or `.pfm` (metres).
/// Returns float32 metres, NaN where there is no depth (in `.npy` and `.pfm` files too: 0,
/// negative and infinite values, which moma counts as no depth, read as NaN).
#[pyfunction]
fn read_depth(py: Python<'_>, path: PathBuf) -> PyResult<Bound<'_, PyArray2<f32>>> {
    let depth = py
        .detach(|| {
            moma_io::read_depth(&path).map(|d| {
                d.depth_m.mapv(|z| {
                    if moma_core::is_valid_depth(z) {
                        z
                    } else {
                        f32::NAN
                    }
                })
            })
        })
        .py()?;
    Ok(depth.into_pyarray(py))
}

/// Writes metric depth (metres) by extension: `.png` uint16 millimetres (NaN/≤0/out of range → 0),
/// `.npy` float32 metres, `.pfm` metres. Atomic. Returns `{"pixels", "invalid", "out_of_range"}`.
#[pyfunction]
fn write_depth<'py>(
    py: Python<'py>,
    path: PathBuf,
    depth_m: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyDict>> {
    let depth = MetricDepth::new(metres_owned(depth_m, "depth_m")?);
    let stats = py.detach(|| moma_io::write_depth(&path, &depth)).py()?;
    let d = PyDict::new(py);
    d.set_item("pixels", stats.pixels)?;
    d.set_item("invalid", stats.invalid)?;
    d.set_item("out_of_range", stats.out_of_range)?;
    Ok(d)
}

/// Reads a raw prediction (unitless): `.npy` (f32/f64), `.pfm`, or uint16 PNG raw values.
#[pyfunction]
fn read_prediction(py: Python<'_>, path: PathBuf) -> PyResult<Bound<'_, PyArray2<f32>>> {
    // The kind only labels the values; reading does not depend on it.
    let pred = py
        .detach(|| moma_io::read_prediction(&path, PredictionKind::RelativeDepth))
        .py()?;
    Ok(pred.values.into_pyarray(py))
}

/// Reads an 8-bit RGB image (PNG / JPEG) as a `height × width × 3` uint8 array.
#[pyfunction]
fn read_rgb(py: Python<'_>, path: PathBuf) -> PyResult<Bound<'_, numpy::PyArray3<u8>>> {
    let img = py.detach(|| moma_io::read_rgb(&path)).py()?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let arr = ndarray::Array3::from_shape_vec((h, w, 3), img.into_raw())
        .map_err(|e| err(Kind::File, format!("{}: {e}", path.display())))?;
    Ok(arr.into_pyarray(py))
}

/// Reads a mask PNG (8-bit grey, nonzero = inside; a set's `mask.png`) as a `height × width`
/// bool array: what `mask=` arguments take.
#[pyfunction]
fn read_mask(py: Python<'_>, path: PathBuf) -> PyResult<Bound<'_, numpy::PyArray2<bool>>> {
    let mask = py.detach(|| moma_io::read_mask(&path)).py()?;
    Ok(mask.data().clone().into_pyarray(py))
}

/// Writes a raw prediction (unitless): `.npy` or `.pfm` (atomic).
#[pyfunction]
fn write_prediction(py: Python<'_>, path: PathBuf, pred: &Bound<'_, PyAny>) -> PyResult<()> {
    // The kind only labels the values; writing does not depend on it.
    let pred = Prediction::new(f32_owned(pred, "pred")?, PredictionKind::RelativeDepth);
    py.detach(|| moma_io::write_prediction(&path, &pred)).py()
}

// ---------------------------------------------------------------------------------------------
// DepthModel

type BoxedModel = Box<dyn DepthModelTrait>;

/// Depth Anything V2 (candle backend; ONNX Runtime in builds with the `onnx` feature).
///
/// The network sits behind a mutex: one inference at a time per model object (the forward pass
/// takes `&mut self`), usable from any thread; the GIL is released while it runs (every
/// `DepthModel` is `Send`).
#[pyclass(module = "moma", frozen)]
struct DepthModel {
    model: Mutex<BoxedModel>,
    spec: ModelSpec,
    runtime: String,
}

fn parse_backbone(s: &str) -> PyResult<Backbone> {
    s.parse().map_err(value_err)
}

fn parse_head(s: &str, max_depth_m: f32) -> PyResult<Head> {
    Head::from_name(s, max_depth_m).map_err(value_err)
}

/// The preset network of `model`, `head` and `max_depth` (defaults vits, relative, 20 m).
fn preset_spec(
    model: Option<&str>,
    head: Option<&str>,
    max_depth: Option<f32>,
    input_size: usize,
) -> PyResult<ModelSpec> {
    Ok(ModelSpec {
        backbone: parse_backbone(model.unwrap_or("vits"))?,
        head: parse_head(head.unwrap_or("relative"), max_depth.unwrap_or(20.0))?,
        input_size,
    })
}

/// A `config` dict fixes the network and its head, as the CLI's `--model PATH.json` does:
/// `model=` beside it, or a `head=` / `max_depth=` that disagrees with it, is refused (they were
/// ignored, and a model meant to be metric ran as the dict's relative one).
fn check_config_agrees(
    (config, named): &(moma_depth::candle::DepthAnythingConfig, String),
    model: Option<&str>,
    head: Option<&str>,
    max_depth: Option<f32>,
) -> PyResult<()> {
    if let Some(m) = model.filter(|m| !is_config_file(m)) {
        return Err(value_err(format!(
            "model='{m}' and {named} both name the network: give one"
        )));
    }
    let own = match config.head {
        Head::Relative => ("relative", None),
        Head::Metric { max_depth_m } => ("metric", Some(max_depth_m)),
    };
    if let Some(h) = head {
        let asked = parse_head(h, max_depth.or(own.1).unwrap_or(20.0))?;
        if std::mem::discriminant(&asked) != std::mem::discriminant(&config.head) {
            return Err(value_err(format!(
                "head='{h}' disagrees with the {} head of {named}",
                own.0
            )));
        }
    }
    if let Some(m) = max_depth
        && Some(m) != own.1
    {
        return Err(value_err(format!(
            "max_depth={m} disagrees with {named} ({})",
            own.1
                .map_or("relative head, no max depth".to_string(), |f| format!(
                    "max_depth_m {f}"
                ))
        )));
    }
    Ok(())
}

fn parse_precision(s: &str) -> PyResult<moma_depth::Precision> {
    s.parse().map_err(value_err)
}

/// Loads the model: [`moma_depth::load`], or, for a custom architecture that a [`ModelSpec`]
/// cannot describe (`config`), the candle backend's constructor.
#[allow(clippy::too_many_arguments)]
fn load_depth_model(
    weights: &std::path::Path,
    spec: ModelSpec,
    config: Option<moma_depth::candle::DepthAnythingConfig>,
    backend: &str,
    device: moma_depth::DeviceRequest,
    precision: moma_depth::Precision,
    lora: Option<&std::path::Path>,
) -> Result<(BoxedModel, String), moma_depth::DepthError> {
    // (an adapter with ONNX is refused by `moma_depth::load`, naming the adapter, in every build)
    if backend == "onnx" && lora.is_none() && !cfg!(feature = "onnx") {
        return Err(moma_depth::DepthError::Unavailable(
            "this moma wheel was built without the ONNX Runtime backend: use backend=\"candle\", \
             or rebuild with `pip install . --config-settings=build-args=\"--features onnx\"`"
                .into(),
        ));
    }
    let model: BoxedModel = match config {
        Some(config) if backend != "onnx" => {
            if !weights.is_file() {
                return Err(moma_depth::DepthError::Weights {
                    path: weights.display().to_string(),
                    reason: "no such file".into(),
                });
            }
            let dev = moma_depth::candle::open_device(device)?;
            // The adapter is merged into the weights once, here: no per-frame cost.
            Box::new(moma_depth::candle::CandleDepthModel::load_with_precision(
                weights, config, &dev, precision, lora,
            )?)
        }
        _ => moma_depth::load(&moma_depth::LoadSpec {
            weights: weights.to_path_buf(),
            model: spec,
            options: moma_depth::LoadOptions {
                backend: if backend == "onnx" {
                    moma_depth::Backend::Onnx
                } else {
                    moma_depth::Backend::Candle
                },
                device,
                precision,
            },
            adapter: lora.map(std::path::Path::to_path_buf),
        })?,
    };
    let runtime = model.runtime();
    Ok((model, runtime))
}

/// `model=` as text: a preset's name, or the path (a `str` or an `os.PathLike`) of a
/// configuration file.
fn model_name(model: Option<PathBuf>) -> PyResult<Option<String>> {
    model
        .map(|m| {
            m.into_os_string()
                .into_string()
                .map_err(|m| value_err(format!("model={m:?}: not valid UTF-8")))
        })
        .transpose()
}

/// Whether `model=` names a configuration file (`PATH.json`, as the CLI's `--model`).
fn is_config_file(model: &str) -> bool {
    model.to_ascii_lowercase().ends_with(".json")
}

/// A custom architecture (e.g. small test networks), with the name errors give it: a `config`
/// dict (the `DepthAnythingConfig` fields, or the fields of a `--model PATH.json` file:
/// `embed_dim`, `depth`, `num_heads`, `intermediate_layers`, `features`, `out_channels`,
/// `head`, `max_depth`), or `model='PATH.json'`, the file the CLI's `--model` takes; `None` for
/// a preset by name.
fn parse_config(
    py: Python<'_>,
    model: Option<&str>,
    config: Option<&Bound<'_, PyDict>>,
) -> PyResult<Option<(moma_depth::candle::DepthAnythingConfig, String)>> {
    let custom = |file: moma_depth::ModelConfigFile| {
        moma_depth::candle::DepthAnythingConfig::custom(file.arch(), file.head())
    };
    let file = model.filter(|m| is_config_file(m));
    let Some(d) = config else {
        return file
            .map(|f| {
                moma_depth::ModelConfigFile::read(f)
                    .map(|c| (custom(c), format!("model='{f}'")))
                    .map_err(errors::IntoPyErr::into_py_err)
            })
            .transpose();
    };
    if let Some(f) = file {
        return Err(value_err(format!(
            "model='{f}' and config= both name the network: give one"
        )));
    }
    let text: String = py.import("json")?.call_method1("dumps", (d,))?.extract()?;
    let config = match serde_json::from_str(&text) {
        Ok(c) => c,
        Err(e) => custom(moma_depth::ModelConfigFile::from_json(&text).map_err(|f| {
            value_err(format!(
                "config: neither a DepthAnythingConfig ({e}) nor a configuration file's \
                 fields ({f})"
            ))
        })?),
    };
    Ok(Some((config, "config=".to_string())))
}

/// The fingerprint of base weights that a LoRA adapter for them must carry (its
/// `base_fingerprint` metadata, as `moma finetune` writes it): 16 hex digits of a 64-bit FNV-1a
/// hash of every base tensor (names, shapes, values in f32). For writing adapters trained
/// elsewhere in moma's `moma-lora-v1` layout.
#[pyfunction]
#[pyo3(signature = (weights, model=None, head=None, *, config=None))]
fn lora_fingerprint(
    py: Python<'_>,
    weights: PathBuf,
    model: Option<PathBuf>,
    head: Option<&str>,
    config: Option<&Bound<'_, PyDict>>,
) -> PyResult<String> {
    let model = model_name(model)?;
    let model = model.as_deref();
    let config = match parse_config(py, model, config)? {
        Some(c) => {
            check_config_agrees(&c, model, head, None)?;
            c.0
        }
        None => moma_depth::candle::DepthAnythingConfig::from_spec(&preset_spec(
            model, head, None, 518,
        )?),
    };
    py.detach(|| {
        if !weights.is_file() {
            return Err(moma_depth::DepthError::Weights {
                path: weights.display().to_string(),
                reason: "no such file".into(),
            });
        }
        let dev = moma_depth::candle::open_device(moma_depth::DeviceRequest::Cpu)?;
        let vb = moma_depth::candle::open_checkpoint(
            &weights,
            &config,
            &dev,
            moma_depth::candle::precision_dtype(moma_depth::Precision::F32, &dev)?,
        )?;
        moma_depth::candle::train::fingerprint(&vb, &config)
    })
    .py()
}

/// LoRA fine-tuning on moma sets: the options of `moma finetune` (same names, same defaults),
/// the same run (`moma_train::finetune`), the same report as `moma finetune --json` (a dict).
#[pyfunction]
#[pyo3(signature = (sets, weights, output, model=None, head=None, *, max_depth=None,
    input_size=518, config=None, device="auto", lora_rank=16, lora_alpha=None,
    lora_targets=vec!["q".to_string(), "v".to_string()], lora_dropout=0.0, train_head=false,
    head_lr_mult=1.0, loss=None, steps=None, epochs=None, batch=1, accumulate=1, lr=5e-4,
    weight_decay=0.01, schedule="one-cycle", warmup_frac=0.05, val_frac=0.2, val_every=0,
    save_every=0, min_depth=0.001, mask_loss=false, augment=true, seed=0, resume=None,
    stop_after=None, clip_grad_norm=1.0, crop=None))]
#[allow(clippy::too_many_arguments)]
fn finetune(
    py: Python<'_>,
    sets: Vec<PathBuf>,
    weights: PathBuf,
    output: PathBuf,
    model: Option<PathBuf>,
    head: Option<&str>,
    max_depth: Option<f32>,
    input_size: usize,
    config: Option<&Bound<'_, PyDict>>,
    device: &str,
    lora_rank: usize,
    lora_alpha: Option<f64>,
    lora_targets: Vec<String>,
    lora_dropout: f32,
    train_head: bool,
    head_lr_mult: f64,
    loss: Option<&str>,
    steps: Option<usize>,
    epochs: Option<usize>,
    batch: usize,
    accumulate: usize,
    lr: f64,
    weight_decay: f64,
    schedule: &str,
    warmup_frac: f64,
    val_frac: f64,
    val_every: usize,
    save_every: usize,
    min_depth: f32,
    mask_loss: bool,
    augment: bool,
    seed: u64,
    resume: Option<PathBuf>,
    stop_after: Option<usize>,
    clip_grad_norm: f64,
    crop: Option<(usize, usize)>,
) -> PyResult<Py<PyAny>> {
    let model = model_name(model)?;
    let model = model.as_deref();
    if sets.is_empty() {
        return Err(value_err("sets: give at least one moma set"));
    }
    moma_depth::preprocess::check_input_size(input_size)
        .map_err(|e| value_err(format!("input_size: {e}")))?;
    let spec = match parse_config(py, model, config)? {
        // Training builds its network from the spec: a custom architecture travels as
        // `Backbone::Custom` (as `moma finetune --model PATH.json`), and must be one.
        Some(named) => {
            check_config_agrees(&named, model, head, max_depth)?;
            let c = named.0;
            let arch = moma_depth::CustomArch {
                embed_dim: c.embed_dim,
                depth: c.depth,
                num_heads: c.num_heads,
                intermediate_layers: c.intermediate_layers,
                features: c.features,
                out_channels: c.out_channels,
            };
            let spec = ModelSpec {
                backbone: Backbone::Custom(arch),
                head: c.head,
                input_size,
            };
            let rebuilt = moma_depth::candle::DepthAnythingConfig {
                backbone: c.backbone,
                input_size: c.input_size,
                ..moma_depth::candle::DepthAnythingConfig::from_spec(&spec)
            };
            if rebuilt != c {
                return Err(value_err(
                    "config: fine-tuning takes the sizes of a `--model PATH.json` file (mlp_hidden_dim = 4 × embed_dim, the standard position grid and LayerNorm epsilon)",
                ));
            }
            spec
        }
        None => preset_spec(model, head, max_depth, input_size)?,
    };
    let mut opts = moma_train::FinetuneOptions::new(sets, weights, spec, output);
    opts.device = device.parse().map_err(value_err)?;
    opts.lora_rank = lora_rank;
    opts.lora_alpha = lora_alpha;
    opts.lora_targets = lora_targets
        .iter()
        .map(|t| t.parse())
        .collect::<Result<_, String>>()
        .map_err(value_err)?;
    opts.lora_dropout = lora_dropout;
    opts.train_head = train_head;
    opts.head_lr_mult = head_lr_mult;
    opts.loss = loss.map(str::parse).transpose().map_err(value_err)?;
    opts.steps = steps;
    opts.epochs = epochs;
    opts.batch = batch;
    opts.accumulate = accumulate;
    opts.lr = lr;
    opts.weight_decay = weight_decay;
    opts.schedule = schedule.parse().map_err(value_err)?;
    opts.warmup_frac = warmup_frac;
    opts.val_frac = val_frac;
    opts.val_every = val_every;
    opts.save_every = save_every;
    opts.min_depth_m = min_depth;
    opts.mask_loss = mask_loss;
    opts.augment = augment;
    opts.seed = seed;
    opts.resume = resume;
    opts.stop_after = stop_after;
    opts.clip_grad_norm = clip_grad_norm;
    opts.crop = crop;
    // Ctrl-C: Python's signal handlers run only when asked; each step asks (taking the GIL for
    // a moment), and a KeyboardInterrupt stops the run and is raised as itself.
    let mut interrupt: Option<PyErr> = None;
    let result = py.detach(|| {
        moma_train::finetune(
            &opts,
            &mut |_| match Python::attach(|py| py.check_signals()) {
                Ok(()) => std::ops::ControlFlow::Continue(()),
                Err(e) => {
                    interrupt = Some(e);
                    std::ops::ControlFlow::Break(())
                }
            },
        )
    });
    if let Some(e) = interrupt {
        return Err(e);
    }
    let report = result.py()?;
    let text = serde_json::to_string(&report).map_err(|e| value_err(format!("report: {e}")))?;
    Ok(py.import("json")?.call_method1("loads", (text,))?.unbind())
}

#[pymethods]
impl DepthModel {
    #[new]
    #[pyo3(signature = (weights, model=None, head=None, backend="candle", device="auto",
        lora=None, *, max_depth=None, input_size=None, dtype="f32", config=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        weights: PathBuf,
        model: Option<PathBuf>,
        head: Option<&str>,
        backend: &str,
        device: &str,
        lora: Option<PathBuf>,
        max_depth: Option<f32>,
        input_size: Option<i128>,
        dtype: &str,
        config: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        let model = model_name(model)?;
        let model = model.as_deref();
        let input_size: Option<usize> =
            input_size.map(|n| unsigned("input_size", n)).transpose()?;
        if !matches!(backend, "candle" | "onnx" | "auto") {
            return Err(value_err(format!(
                "unknown backend '{backend}' (expected 'candle' or 'onnx')"
            )));
        }
        let backend = match backend {
            "auto" if weights.extension().is_some_and(|e| e == "onnx") => "onnx",
            "auto" => "candle",
            b => b,
        };
        // A custom architecture (e.g. small test networks): the DepthAnythingConfig fields as a
        // dict, whose own input size applies unless `input_size=` is given (as the CLI's
        // `--model PATH.json --input-size` and `finetune(config=…, input_size=…)` take it: the
        // dict's used to win over an explicit `input_size=`)
        let config = parse_config(py, model, config)?;
        if let Some(c) = &config {
            check_config_agrees(c, model, head, max_depth)?;
        }
        let config = config.map(|(c, _)| c);
        let input_size = input_size
            .or(config.as_ref().map(|c| c.input_size))
            .unwrap_or(518);
        moma_depth::preprocess::check_input_size(input_size)
            .map_err(|e| value_err(format!("input_size: {e}")))?;
        let config = config.map(|c| moma_depth::candle::DepthAnythingConfig { input_size, ..c });
        let spec = match &config {
            Some(c) => c.spec(),
            None => preset_spec(model, head, max_depth, input_size)?,
        };
        let device: moma_depth::DeviceRequest = device.parse().map_err(value_err)?;
        let precision = parse_precision(dtype)?;
        let (model, runtime) = py
            .detach(|| {
                load_depth_model(
                    &weights,
                    spec,
                    config,
                    backend,
                    device,
                    precision,
                    lora.as_deref(),
                )
            })
            .py()?;
        Ok(Self {
            model: Mutex::new(model),
            spec,
            runtime,
        })
    }

    /// Runs the network on an 8-bit RGB image (`height × width × 3`, uint8) and returns the
    /// prediction at the image's size (float32): inverse depth (relative head, unitless) or
    /// depth in metres (metric head); see `kind`. The GIL is released during inference.
    fn predict<'py>(
        &self,
        py: Python<'py>,
        rgb: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let image = rgb_image(rgb, "rgb")?;
        let pred = py
            .detach(|| {
                let mut model = self.model.lock().map_err(|_| {
                    moma_depth::DepthError::Backend(
                        "the model is unusable: an earlier inference panicked".into(),
                    )
                })?;
                model.predict(&image)
            })
            .py()?;
        Ok(pred.values.into_pyarray(py))
    }

    /// `"relative-disparity"` (relative head) or `"metric-depth"` (metric head, metres): pass it to
    /// `calibrate`.
    #[getter]
    fn kind(&self) -> String {
        self.spec.head.prediction_kind().to_string()
    }

    /// Network input short-side lower bound, pixels.
    #[getter]
    fn input_size(&self) -> usize {
        self.spec.input_size
    }

    /// Backend, device and precision, e.g. for provenance records.
    #[getter]
    fn runtime(&self) -> &str {
        &self.runtime
    }

    fn __repr__(&self) -> String {
        format!(
            "DepthModel(kind='{}', input_size={}, runtime='{}')",
            self.spec.head.prediction_kind(),
            self.spec.input_size,
            self.runtime
        )
    }
}

// ---------------------------------------------------------------------------------------------

/// Whether this build has the ONNX Runtime backend.
#[pyfunction]
fn has_onnx() -> bool {
    cfg!(feature = "onnx")
}

#[pymodule]
fn _moma(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<Intrinsics>()?;
    m.add_class::<Calibration>()?;
    m.add_class::<DepthModel>()?;
    m.add_function(wrap_pyfunction!(calibrate, m)?)?;
    m.add_function(wrap_pyfunction!(finetune, m)?)?;
    m.add_function(wrap_pyfunction!(metrics, m)?)?;
    m.add_function(wrap_pyfunction!(depth_to_points, m)?)?;
    m.add_function(wrap_pyfunction!(plan_grasps, m)?)?;
    m.add_function(wrap_pyfunction!(grasp_check, m)?)?;
    m.add_function(wrap_pyfunction!(read_depth, m)?)?;
    m.add_function(wrap_pyfunction!(write_depth, m)?)?;
    m.add_function(wrap_pyfunction!(read_prediction, m)?)?;
    m.add_function(wrap_pyfunction!(write_prediction, m)?)?;
    m.add_function(wrap_pyfunction!(read_rgb, m)?)?;
    m.add_function(wrap_pyfunction!(read_mask, m)?)?;
    m.add_function(wrap_pyfunction!(has_onnx, m)?)?;
    m.add_function(wrap_pyfunction!(lora_fingerprint, m)?)?;
    Ok(())
}
