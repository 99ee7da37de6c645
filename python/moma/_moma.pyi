"""Type stubs of the Rust extension ``moma._moma`` (re-exported by ``moma``).

Units: depth in metres (``_m``), pixels (``_px``); arrays are ``(height, width)``.
Array arguments accept any real dtype and memory layout; a C-contiguous ``float32`` array is read
without conversion, anything else is converted to ``float32`` once. Bad arrays or parameters raise
``moma.InvalidInputError`` (a ``ValueError``); file problems ``moma.MomaFileError`` (an ``OSError``).
"""

from os import PathLike
from typing import (
    Any, Literal, NotRequired, Optional, Sequence, Tuple, TypedDict, Union, final, overload,
)

import numpy as np
import numpy.typing as npt

_Path = Union[str, "PathLike[str]"]
_Kind = Literal["metric-depth", "relative-depth", "relative-disparity"]
_Method = Literal[
    "ssra", "gssa", "lwlr", "lwlr-exact", "lwlr-bare", "ssra-local", "gssa-local", "auto", "raw"
]
_Robust = Literal["huber", "tukey", "ransac"]
_Norm = Literal["minmax", "minmax-unit", "median", "none"]
_Sampling = Literal["random", "grid"]
_F32 = npt.NDArray[np.float32]
_Mask = Union[npt.NDArray[np.bool_], npt.NDArray[np.uint8]]
# objects to grasp: a bool mask or integer instance labels (one value per object)
_Objects = Union[npt.NDArray[np.bool_], npt.NDArray[np.integer[Any]]]
_Rgb = npt.NDArray[np.uint8]

__all__ = [
    "Calibration",
    "DepthModel",
    "Intrinsics",
    "__version__",
    "calibrate",
    "depth_to_points",
    "plan_grasps",
    "has_onnx",
    "metrics",
    "read_depth",
    "read_prediction",
    "read_rgb",
    "read_mask",
    "write_depth",
    "write_prediction",
]

__version__: str

class _ReportFields(TypedDict):
    """``Calibration.report``: the fields ``moma calibrate --json`` prints."""

    method: str
    n_used: int
    rms_residual_m: float
    """RMS residual on the calibration samples, metres."""
    fit_time_s: float
    """Wall time of the fit, seconds."""
    model: dict[str, Any]
    """The fitted parameters (as in the calibration file)."""

class _Report(_ReportFields, total=False):
    robust: dict[str, Any]
    """Robust fits only: the file's robust block (``kind``, ``threshold_m`` (metres),
    ``inliers``, ``iterations``, ``inlier_rms_residual_m`` (metres), ``auto`` with
    ``scale_m`` when the threshold came from the data, …)."""

class _RealignReport(TypedDict):
    """``Calibration.align_realigned``: the per-frame report of ``moma align --realign anchors``."""

    anchors: int
    """Anchor pixels found (half resolution, before subsampling)."""
    anchors_used: int
    """Anchors used for the fit and the held-out test."""
    brightness_gain: Optional[float]
    """Global brightness gain of the frame against the calibration frame."""
    held_out_rmse_before_m: Optional[float]
    """RMSE of the one-shot result on the held-out anchors, metres."""
    held_out_rmse_after_m: Optional[float]
    """RMSE of the corrected result on the held-out anchors, metres."""
    held_out_gain_m: NotRequired[float]
    """Mean paired held-out gain (error before − after), metres; positive: the correction helps."""
    held_out_gain_se_m: NotRequired[float]
    """Standard error of ``held_out_gain_m``, metres."""
    correction: NotRequired[str]
    """The correction form that was tried."""
    target: str
    """What the correction was fitted to at the anchors (``"calibration-output"`` or
    ``"ground-truth"``), so what the held-out RMSEs measure: the frame's change since
    calibration, or its error against the calibration frame's truth."""
    prediction_affine: NotRequired[list[float]]
    """The accepted ``prediction-affine`` map ``[a, b]`` (absent otherwise)."""
    accepted: bool
    """Whether the correction was applied (else the one-shot result is returned)."""
    reason: str
    """Why (a warning when not accepted)."""

class _Metrics(TypedDict):
    """``moma.metrics``: depth accuracy over pixels valid in both maps."""

    d105: float
    """Fraction of pixels with max(z/z*, z*/z) < 1.05."""
    d110: float
    """Fraction with ratio < 1.10."""
    d125: float
    """Fraction with ratio < 1.25."""
    rel: float
    """Mean absolute relative error |z − z*| / z*."""
    rmse: float
    """Root-mean-square error, metres."""
    mae: float
    """Mean absolute error, metres."""
    n: int
    """Number of pixels evaluated."""

class _WriteStats(TypedDict):
    pixels: int
    invalid: int
    """Pixels that were NaN / ±inf / ≤ 0 m."""
    out_of_range: int
    """Valid depths the format cannot hold (PNG: < 0.5 mm or > 65.535 m), written as 0."""

@final
class Intrinsics:
    """Pinhole intrinsics in pixels for a ``width × height`` image (x right, y down, z forward)."""

    def __new__(
        cls, fx: float, fy: float, cx: float, cy: float, width: int, height: int
    ) -> "Intrinsics":
        """``fx``, ``fy``: focal lengths (px, > 0); ``cx``, ``cy``: principal point (px);
        ``width``, ``height``: image size (px). Raises ``InvalidInputError`` on invalid values."""
    @staticmethod
    def load(path: _Path) -> "Intrinsics":
        """Reads a ``camera.json`` (``{"width","height","fx","fy","cx","cy"}``, pixels)."""
    def save(self, path: _Path) -> None:
        """Writes a ``camera.json`` (atomically)."""
    @property
    def fx(self) -> float: ...
    @property
    def fy(self) -> float: ...
    @property
    def cx(self) -> float: ...
    @property
    def cy(self) -> float: ...
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    def to_dict(self) -> dict[str, Any]:
        """The ``camera.json`` fields."""

@final
class Calibration:
    """A fitted alignment (the content of a ``moma calibrate`` calibration file)."""

    def align(self, pred: npt.ArrayLike) -> _F32:
        """Metric depth (float32 metres, NaN where no depth can be inferred) from a prediction
        of the calibrated kind and shape. A float32 array (any strides) is read in place, not
        copied; other dtypes are converted once. Releases the GIL."""
    def align_into(self, pred: npt.ArrayLike, out: _F32) -> None:
        """Like ``align``, writing metres into ``out`` (writable float32, same shape; any
        strides) without allocating."""
    def align_realigned(
        self,
        pred: npt.ArrayLike,
        rgb: _Rgb,
        *,
        correction: Literal["scale-shift", "planar", "prediction-affine"] = "scale-shift",
        target: Literal["calibration-output", "ground-truth"] = "calibration-output",
        ridge: float = 100.0,
        max_anchors: int = 200,
        min_anchors: int = 50,
        min_anchor_fraction: float = 0.05,
        holdout_fraction: float = 0.3,
        acceptance_se: float = 1.0,
        seed: int = 0,
        abs_grey: float = 6.0,
        rel_grey: float = 0.08,
    ) -> Tuple[_F32, _RealignReport]:
        """``align``, then per-frame re-alignment on static anchors found in this frame's RGB
        (uint8 ``H×W×3``), as ``moma align --realign anchors``: ``(depth_m, report)``, float32
        metres. Needs a calibration with anchors (``has_anchors``; else ``InvalidInputError``).
        When the correction does not lower the held-out anchors' error, or too few anchors
        remain (a covered background), the one-shot result is returned and
        ``report["accepted"]`` is False with ``report["reason"]``. Options (defaults = the CLI's):
        ``correction`` form, ``target`` of the fit at the anchors, ``ridge`` towards the
        identity (anchor equivalents), ``max_anchors``, ``min_anchors``,
        ``min_anchor_fraction`` (of the stored valid pixels), ``holdout_fraction``,
        ``acceptance_se`` (the held-out gain must exceed this many standard errors), ``seed``
        (subsample and split), ``abs_grey`` (grey levels, 0–255) and ``rel_grey`` (fraction):
        the anchor rule's tolerances. Releases the GIL."""
    def align_realigned_into(
        self, pred: npt.ArrayLike, rgb: _Rgb, out: _F32, **options: Any
    ) -> _RealignReport:
        """Like ``align_realigned``, writing metres into ``out`` (writable float32, same shape)
        without allocating; returns the report. Same options."""
    @property
    def has_anchors(self) -> bool:
        """Whether the calibration holds the anchor store ``align_realigned`` needs."""
    @property
    def error_model(self) -> Optional[dict[str, Any]]:
        """The error model of the aligned depth (``sigma_flat_m``, ``depth_ref_m``, ...), None
        in files written before error models existed."""
    def sigma_map(
        self, depth_m: npt.ArrayLike, report: Optional[dict[str, Any]] = None
    ) -> _F32:
        """Per-pixel σ (float32 metres, NaN = no depth) of the error of this calibration's
        aligned depth ``depth_m``, as ``moma align --sigma-map`` writes it; ``report``: the
        frame's re-alignment report (widens the flat σ)."""
    def save(self, path: _Path) -> None:
        """Writes the CLI's calibration format (``moma-calibration`` JSON, the current version, atomic), the
        workspace mask and anchor store (if any) embedded: the file is self-contained."""
    @staticmethod
    def load(path: _Path) -> "Calibration":
        """Reads a file written by ``moma calibrate`` or ``Calibration.save``."""
    @property
    def report(self) -> _Report: ...
    @property
    def space(self) -> Literal["depth", "inverse"]:
        """Alignment space: ``"inverse"`` (disparity predictor, 1/z target) or ``"depth"``."""
    @property
    def kind(self) -> _Kind:
        """Prediction kind this calibration accepts."""
    @property
    def method(self) -> str: ...
    @property
    def norm(self) -> str: ...
    @property
    def shape(self) -> Tuple[int, int]:
        """``(height, width)`` in pixels that predictions must have."""
    @property
    def intrinsics(self) -> Optional[Intrinsics]: ...
    @property
    def workspace(self) -> Optional[npt.NDArray[np.bool_]]:
        """Normalisation workspace mask, if any."""
    @property
    def samples(self) -> npt.NDArray[np.float64]:
        """``n × 4``: u (px), v (px), normalised prediction, ground-truth depth (m)."""
    def predicted_error(
        self, protocol: Literal["fixed-camera", "per-frame"] = "fixed-camera"
    ) -> Optional[dict[str, Any]]:
        """The error expected away from the samples, by cross-validation on them (``moma
        calibrate``'s ``predicted_error``): ``{"protocol", "abs_rel", "rms_m"}`` (metres), None
        for a robust fit. ``auto`` and the local corrections report their own cross-validation
        whatever ``protocol`` asks, labelled with the folds they were calibrated with."""
    def to_json(self) -> str:
        """The calibration file's JSON text."""
    @staticmethod
    def from_json(text: str) -> "Calibration":
        """A calibration from a calibration file's JSON text (``to_json``'s inverse; checked as
        ``load`` checks a file). Calibrations pickle through it."""

def calibrate(
    pred: Union[npt.ArrayLike, Sequence[npt.ArrayLike]],
    gt_m: Union[npt.ArrayLike, Sequence[npt.ArrayLike]],
    cam: Optional[Intrinsics] = None,
    *,
    kind: _Kind,
    method: _Method = "ssra",
    norm: Optional[_Norm] = None,
    samples: int = 100,
    sampling: _Sampling = "random",
    seed: int = 0,
    edge_margin_px: int = 0,
    mask: Union[None, _Mask, Sequence[_Mask]] = None,
    workspace: Optional[_Mask] = None,
    space: Optional[Literal["depth", "inverse"]] = None,
    bandwidth_px: Optional[float] = None,
    robust: Optional[_Robust] = None,
    robust_threshold_m: Optional[float] = None,
    anchors_rgb: Union[None, _Rgb, _Path] = None,
    protocol: Literal["fixed-camera", "per-frame"] = "fixed-camera",
    cv_loss: Optional[Literal["target", "abs", "rel"]] = None,
    cv_margin_se: Optional[float] = None,
) -> Calibration:
    """Fits an alignment on one frame, or on several frames of one camera (few-shot), as
    ``moma calibrate`` does.

    ``pred``: the model's output (H×W, no NaN); ``gt_m``: ground-truth depth in metres (0/NaN =
    invalid). Few-shot: a list of predictions and a list of ground truths of the same length
    (one camera: all frames the same size); each frame is normalised on its own, ``samples``
    are drawn per frame (frame i > 0 with a seed derived from ``seed`` and i), one fit over
    all. ``cam``: intrinsics (SSRA's canonical parameters; recorded in the file); ``kind``:
    required, never guessed; ``norm``: default ``"minmax-unit"`` (``"none"`` for
    ``method="raw"``, as ``moma calibrate``);
    ``samples``: number of calibration pixels (per frame); ``seed``:
    of the random sampling (and RANSAC); ``edge_margin_px``: draw samples more than this many
    pixels away from depth discontinuities of the ground truth (object boundaries, where
    sensors return flying pixels and depth models blur; 0: anywhere valid); ``mask``: draw samples only inside (bool/uint8 H×W,
    nonzero = inside; few-shot: one for all frames or a list, one per frame); ``workspace``:
    normalise over this region (embedded in the calibration); ``space``: ``"inverse"``
    (disparity predictor, 1/z target) or ``"depth"``, default the prediction's own
    (relative-disparity → inverse, the depth kinds → depth); ``bandwidth_px``: LWLR bandwidth in pixels; ``robust``: robust
    fit against wrong ground truth (Huber or Tukey IRLS, RANSAC; for ssra, gssa, ssra-local,
    gssa-local), ``robust_threshold_m`` its residual scale in metres (None: the data-driven
    ``auto`` threshold, the CLI's default); ``anchors_rgb``: the (first) calibration frame's RGB (uint8 H×W×3 array or an image
    path) to store the anchors ``Calibration.align_realigned`` needs (``moma calibrate
    --anchors``); ``protocol``: what the calibration will align, which decides how ``auto``,
    ``ssra-local`` and ``gssa-local`` cross-validate: ``"fixed-camera"`` (other frames of a fixed
    camera) or ``"per-frame"`` (the frame it was calibrated on, sparse-to-dense);
    ``cv_loss`` (``"target"``, ``"abs"``, ``"rel"``) and ``cv_margin_se`` (standard errors; 1 is
    the one-standard-error rule, 0 the lowest CV loss) replace the protocol's loss and rule
    (``moma calibrate --protocol --cv-loss --cv-margin-se``). Bad input (lists of different lengths, frames of different sizes, an unknown
    robust kind, ...) raises ``InvalidInputError`` (a ``ValueError``) naming the problem."""

def metrics(
    depth_m: npt.ArrayLike, gt_m: npt.ArrayLike, mask: Optional[_Mask] = None
) -> _Metrics:
    """Accuracy of ``depth_m`` (metres) against ``gt_m`` (metres) over pixels valid in both."""

def plan_grasps(
    source: Union[npt.ArrayLike, Calibration],
    cam: Optional[Intrinsics] = None,
    gripper: Literal["parallel", "suction"] = "parallel",
    mask: Optional[_Objects] = None,
    top: int = 10,
    seed: int = 0,
    keep_border_objects: bool = False,
    *,
    pred: Optional[npt.ArrayLike] = None,
    rgb: Optional[_Rgb] = None,
    sigma_m: Optional[float] = None,
    grasp_quality: Optional[Literal["nominal", "robust"]] = None,
    grasp_draws: int = 4,
    min_success_prob: Optional[float] = None,
    gripper_config: Optional[Union[_Path, dict[str, float]]] = None,
    tie_tolerance: Optional[float] = None,
    extrinsics: Optional[Union[_Path, npt.ArrayLike]] = None,
    keep_containers: bool = False,
    realign: Optional[dict[str, Any]] = None,
) -> list[dict[str, Any]]:
    """Grasps, best first, as ``moma grasp --json`` prints them: parallel ``{"kind", "score",
    "success_prob", "center_m", "approach", "closing", "width_m"}``, suction ``{"kind",
    "score", "success_prob", "point_m", "approach"}``; camera frame x right, y down, z forward,
    metres. ``source``: metric depth (metres; ``cam`` required) or a ``Calibration`` with
    ``pred=`` the frame's prediction (``cam`` defaults to its intrinsics; ``rgb=`` re-aligns on
    static anchors, ``realign=`` a dict of ``Calibration.align_realigned``'s options, e.g.
    ``{"correction": "planar"}``; a frame that keeps the one-shot depth says why in a
    ``UserWarning``). ``success_prob`` is ``(k + 1) / (N + 2)`` for a grasp that succeeds on k
    of the N depth maps drawn from the error model (the calibration's, or a uniform
    ``sigma_m``), None without one; ``grasp_quality`` ``"robust"`` (the default with an error
    model) ranks by k / N, ``"nominal"`` by the planner's score. ``mask``: the objects (bool,
    or integer instance labels: one value per object keeps touching objects apart; nonzero =
    inside); without one, regions over 10 mm above the support plane that do not touch the
    image border (unless ``keep_border_objects``) and do not enclose an opening of a
    container's size (a bin's walls, unless ``keep_containers``; a ``UserWarning`` says when
    either is dropped). An empty list when nothing is graspable,
    with the reason as a ``UserWarning`` (e.g. every grasp below ``min_success_prob``, which
    with N draws cannot exceed ``(N + 1) / (N + 2)``). ``gripper_config`` (a dict, or the path
    of ``--gripper-config``'s JSON), ``tie_tolerance`` (``--grasp-tie-tolerance``) and
    ``extrinsics`` (a 4 × 4 camera → base array of rows, or the path of ``--extrinsics``'s JSON;
    each grasp gains ``"base"``) are taken as the CLI takes them."""

def grasp_check(
    calibration: Calibration,
    pred: npt.ArrayLike,
    gt_m: npt.ArrayLike,
    cam: Optional[Intrinsics] = None,
    gripper: Literal["parallel", "suction"] = "suction",
    mask: Optional[_Objects] = None,
    seed: int = 0,
) -> dict[str, Any]:
    """The grasp check of a frame whose ground truth is known (``moma calibrate
    --grasp-check``): ``pred`` aligned one-shot by ``calibration``, planned as ``plan_grasps``
    plans with its error model (``gripper``'s default geometry), every grasp executed on
    ``gt_m`` (metres) by the proxy's rules. Returns ``{"gripper", "scores": "proxy", "grasps",
    "successes", "success_rate", "mean_success_prob", "failures", "no_grasp_reason", "notes"}``
    (``notes``: regions the planner left out, at the image border or a container's walls, each
    also a ``UserWarning``). PROXY scores, not robot trials; a gauge of the cell, not a forecast
    (docs/grasping.md)."""

@overload
def depth_to_points(depth_m: npt.ArrayLike, cam: Intrinsics, rgb: None = None) -> _F32: ...
@overload
def depth_to_points(
    depth_m: npt.ArrayLike, cam: Intrinsics, rgb: npt.NDArray[np.uint8]
) -> Tuple[_F32, npt.NDArray[np.uint8]]: ...
def read_depth(path: _Path) -> _F32:
    """Metric depth from uint16 PNG (mm, 0 = none), ``.npy`` or ``.pfm`` (m): float32 metres, NaN = none.
    A ``.npy`` / ``.pfm`` whose median valid depth is above 200 m (millimetres given as metres)
    raises ``MomaFileError``."""

def write_depth(path: _Path, depth_m: npt.ArrayLike) -> _WriteStats:
    """Writes metric depth by extension: ``.png`` uint16 mm, ``.npy``/``.pfm`` float32 m (atomic)."""

def read_prediction(path: _Path) -> _F32:
    """A raw (unitless) prediction from ``.npy``, ``.pfm`` or uint16 PNG."""

def read_rgb(path: _Path) -> npt.NDArray[np.uint8]:
    """An 8-bit RGB image (PNG / JPEG) as ``height × width × 3`` uint8."""

def read_mask(path: _Path) -> npt.NDArray[np.bool_]:
    """A mask PNG (8-bit grey, nonzero = inside) as ``height × width`` bool, for ``mask=``."""

def write_prediction(path: _Path, pred: npt.ArrayLike) -> None:
    """Writes a raw prediction to ``.npy`` or ``.pfm`` (atomic)."""

def has_onnx() -> bool:
    """Whether this build has the ONNX Runtime backend."""

def lora_fingerprint(
    weights: _Path,
    model: Optional[Union[Literal["vits", "vitb", "vitl"], _Path]] = None,
    head: Optional[Literal["relative", "metric"]] = None,
    *,
    config: Optional[dict[str, Any]] = None,
) -> str:
    """The fingerprint (16 hex digits) of base weights that a LoRA adapter for them must carry
    in its ``base_fingerprint`` metadata, as ``moma finetune`` writes it: for adapters trained
    elsewhere and written in moma's ``moma-lora-v1`` layout. ``model`` (default ``vits``) and
    ``head`` (default ``relative``) name a preset network; ``config`` a custom one, which fixes
    its head (``model=`` beside it, or a ``head=`` that disagrees, raises ``InvalidInputError``).
    Raises ``MomaFileError`` for unreadable weights or ones that do not fit the architecture."""

def finetune(
    sets: Sequence[_Path],
    weights: _Path,
    output: _Path,
    model: Optional[Union[Literal["vits", "vitb", "vitl"], _Path]] = None,
    head: Optional[Literal["relative", "metric"]] = None,
    *,
    max_depth: Optional[float] = None,
    input_size: int = 518,
    config: Optional[dict[str, Any]] = None,
    device: str = "auto",
    lora_rank: int = 16,
    lora_alpha: Optional[float] = None,
    lora_targets: Sequence[Literal["q", "k", "v", "proj", "fc1", "fc2"]] = ("q", "v"),
    lora_dropout: float = 0.0,
    train_head: bool = False,
    head_lr_mult: float = 1.0,
    loss: Optional[Literal["silog", "silog-moma", "ssi"]] = None,
    steps: Optional[int] = None,
    epochs: Optional[int] = None,
    batch: int = 1,
    accumulate: int = 1,
    lr: float = 5e-4,
    weight_decay: float = 0.01,
    schedule: Literal["one-cycle", "poly"] = "one-cycle",
    warmup_frac: float = 0.05,
    val_frac: float = 0.2,
    val_every: int = 0,
    save_every: int = 0,
    min_depth: float = 0.001,
    mask_loss: bool = False,
    augment: bool = True,
    seed: int = 0,
    resume: Optional[_Path] = None,
    stop_after: Optional[int] = None,
    clip_grad_norm: float = 1.0,
    crop: Optional[tuple[int, int]] = None,
) -> dict[str, Any]:
    """LoRA fine-tuning of Depth Anything V2 on moma sets, as ``moma finetune`` (the same options
    under the same names, the same defaults, the same run) and returns the dict that
    ``moma finetune --json`` prints: ``steps``, ``train_loss_first``, ``train_loss_last``,
    ``val_loss_before``, ``val_loss_after``, ``val_loss_after_reload`` (the validation loss of
    the written adapter loaded through the inference path, as ``DepthModel(lora=output)`` loads
    it), ``adapter``, ``step_time_s``, ``loss``, ``train_frames``, ``val_frames``,
    ``validations`` (``[{"step", "loss"}]``, every ``val_every`` steps), ``note``.
    Writes ``output`` (the adapter, with the trained head when ``train_head``) and its optimiser
    state ``output`` with ``.optim.safetensors``. ``model``, ``head``, ``max_depth`` (defaults
    ``vits``, ``relative``, 20 m) or ``config``, a custom architecture, as ``DepthModel``. Give
    ``steps`` or ``epochs``. Releases the GIL while training; Ctrl-C stops the run at its next
    step and raises ``KeyboardInterrupt`` (only adapters of ``save_every`` are left). Bad
    options or data raise ``InvalidInputError``, unreadable files ``MomaFileError``, a step with a
    non-finite loss or gradient ``BackendError`` naming the step, frames and tensor. Random-weight
    models learn nothing meaningful: their losses only show that training runs."""

@final
class DepthModel:
    """Depth Anything V2. Thread-safe (one inference at a time per object); releases the GIL."""

    def __new__(
        cls,
        weights: _Path,
        model: Optional[Union[Literal["vits", "vitb", "vitl"], _Path]] = None,
        head: Optional[Literal["relative", "metric"]] = None,
        backend: Literal["candle", "onnx", "auto"] = "candle",
        device: str = "auto",
        lora: Optional[_Path] = None,
        *,
        max_depth: Optional[float] = None,
        input_size: Optional[int] = None,
        dtype: Literal["f32", "f16", "bf16", "int8"] = "f32",
        config: Optional[dict[str, Any]] = None,
    ) -> "DepthModel":
        """``weights``: official checkpoint (.pth / .safetensors; candle) or .onnx (onnx builds);
        ``model`` (default ``vits``) and ``head`` (default ``relative``): a preset network;
        ``device``: ``auto`` (the default, as the CLI's ``--device``: the first GPU this build
        supports, else the CPU), ``cpu``, ``cuda[:N]`` or ``metal[:N]``; ``max_depth``: metric head's
        largest depth, metres (default 20); ``input_size``: network input lower bound, px (multiple of 14;
        default 518, or the ``config`` dict's own; given, it applies to a ``config`` model too);
        ``model="PATH.json"``: a configuration file, as ``moma --model PATH.json`` takes it;
        ``config``: a custom architecture as a dict (the fields of such a file, or moma-depth
        ``DepthAnythingConfig`` fields), which fixes the network and its head as
        ``moma --model PATH.json`` does: ``model=`` beside it, or a ``head=`` / ``max_depth=``
        that disagrees with it, raises ``InvalidInputError``;
        ``lora``: a LoRA adapter file (``moma finetune`` output, ``moma-lora-v2`` safetensors with any
        trained head tensors; ``moma-lora-v1`` files still load)
        merged into the weights at load (candle backend; no per-frame cost). An adapter made for
        other base weights or another architecture raises ``MomaFileError``; with
        ``backend="onnx"``, ``BackendError``."""
    def predict(self, rgb: npt.NDArray[np.uint8]) -> _F32:
        """RGB uint8 ``H×W×3`` → float32 ``H×W`` prediction of kind ``self.kind``."""
    @property
    def kind(self) -> _Kind: ...
    @property
    def input_size(self) -> int: ...
    @property
    def runtime(self) -> str: ...
