from ._errors import BackendError as BackendError
from ._errors import InvalidInputError as InvalidInputError
from ._errors import MomaError as MomaError
from ._errors import MomaFileError as MomaFileError
from ._moma import Calibration as Calibration
from ._moma import DepthModel as DepthModel
from ._moma import Intrinsics as Intrinsics
from ._moma import __version__ as __version__
from ._moma import calibrate as calibrate
from ._moma import depth_to_points as depth_to_points
from ._moma import finetune as finetune
from ._moma import plan_grasps as plan_grasps
from ._moma import grasp_check as grasp_check
from ._moma import has_onnx as has_onnx
from ._moma import lora_fingerprint as lora_fingerprint
from ._moma import metrics as metrics
from ._moma import read_depth as read_depth
from ._moma import read_prediction as read_prediction
from ._moma import read_rgb as read_rgb
from ._moma import read_mask as read_mask
from ._moma import write_depth as write_depth
from ._moma import write_prediction as write_prediction

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
