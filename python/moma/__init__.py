"""moma — monocular one-shot metric-depth alignment (MOMA) for RGB-based robot grasping.

NumPy in, NumPy out. Depth maps are ``float32`` arrays of shape ``(height, width)`` in metres,
NaN where there is no depth; predictions are ``float32`` ``(height, width)`` arrays of a depth
model's raw output, of kind ``"metric-depth"`` (metres as a metric model predicts them),
``"relative-depth"`` (larger = farther, no unit) or ``"relative-disparity"`` (larger = nearer, no
unit). Pixel coordinates: u right, v down; camera frame: x right, y down, z forward.

Example::

    import moma
    cam = moma.Intrinsics(fx, fy, cx, cy, width, height)
    cal = moma.calibrate(pred, gt_m, cam, kind="relative-disparity", samples=100, seed=0)
    depth_m = cal.align(next_pred)
"""

from ._errors import BackendError, InvalidInputError, MomaError, MomaFileError
from ._moma import (
    Calibration,
    DepthModel,
    Intrinsics,
    __version__,
    calibrate,
    depth_to_points,
    finetune,
    plan_grasps,
    grasp_check,
    has_onnx,
    lora_fingerprint,
    metrics,
    read_depth,
    read_prediction,
    read_rgb,
    read_mask,
    write_depth,
    write_prediction,
)

__all__ = [
    "BackendError",
    "Calibration",
    "DepthModel",
    "Intrinsics",
    "InvalidInputError",
    "MomaError",
    "MomaFileError",
    "__version__",
    "calibrate",
    "depth_to_points",
    "finetune",
    "plan_grasps",
    "grasp_check",
    "has_onnx",
    "lora_fingerprint",
    "metrics",
    "read_depth",
    "read_prediction",
    "read_rgb",
    "read_mask",
    "write_depth",
    "write_prediction",
]
