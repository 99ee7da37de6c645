"""Bad arrays and parameters raise moma's exception classes (never crash the interpreter)."""

import numpy as np
import pytest

import moma
from conftest import scene


@pytest.fixture(scope="module")
def cal():
    pred, gt = scene()
    return moma.calibrate(pred, gt, kind="relative-disparity")


def test_exception_hierarchy():
    assert issubclass(moma.InvalidInputError, moma.MomaError)
    assert issubclass(moma.InvalidInputError, ValueError)
    assert issubclass(moma.MomaFileError, moma.MomaError)
    assert issubclass(moma.MomaFileError, OSError)
    assert issubclass(moma.BackendError, moma.MomaError)
    assert issubclass(moma.BackendError, RuntimeError)


def test_kind_is_required():
    pred, gt = scene()
    with pytest.raises(TypeError, match="kind"):
        moma.calibrate(pred, gt)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(kind="disparity-ish"), "prediction kind"),
        (dict(kind="metric-depth", method="magic"), "unknown method"),
        (dict(kind="metric-depth", norm="zscore"), "unknown normalisation"),
        (dict(kind="metric-depth", sampling="sobol"), "unknown sampling"),
        (dict(kind="metric-depth", method="lwlr", bandwidth_px=-3.0), "bandwidth"),
        # As `moma calibrate --bandwidth-px` (one rule, moma_core::policy): not silently ignored.
        (dict(kind="metric-depth", method="ssra", bandwidth_px=30.0), "LWLR methods only"),
        (dict(kind="metric-depth", samples=2), "too few"),
        (dict(kind="metric-depth", edge_margin_px=500), "edge margin of 500 px"),
    ],
)
def test_bad_parameters(kwargs, match):
    pred, gt = scene()
    with pytest.raises(moma.InvalidInputError, match=match):
        moma.calibrate(pred, gt, **kwargs)


@pytest.mark.parametrize(
    "bad,match",
    [
        (np.zeros((120,), np.float32), "2-D"),
        (np.zeros((120, 160, 1), np.float32), "2-D"),
        (np.zeros((2, 120, 160), np.float64), "2-D"),
        (np.zeros((121, 160), np.float32), "size mismatch"),
        (np.zeros((120, 161), np.float64), "size mismatch"),
        (np.array([["a", "b"], ["c", "d"]]), "dtype"),
        (np.zeros((120, 160), np.complex64), "dtype"),
        (np.full((120, 160), None, dtype=object), "dtype"),
        ("not an array", "2-D"),
    ],
)
def test_bad_prediction_arrays(cal, bad, match):
    with pytest.raises(moma.InvalidInputError, match=match):
        cal.align(bad)


def test_nan_in_prediction_is_named(cal):
    pred, _ = scene()
    pred[7, 9] = np.nan
    with pytest.raises(moma.InvalidInputError, match=r"non-finite.*u=9, v=7"):
        cal.align(pred)
    with pytest.raises(moma.InvalidInputError, match="non-finite"):
        moma.calibrate(pred, scene()[1], kind="relative-disparity")


def test_bad_out_buffers(cal):
    pred, _ = scene()
    with pytest.raises(moma.InvalidInputError, match="float32"):
        cal.align_into(pred, np.zeros(pred.shape, np.float64))
    with pytest.raises(moma.InvalidInputError, match="size mismatch"):
        cal.align_into(pred, np.zeros((120, 10), np.float32))
    ro = np.zeros(pred.shape, np.float32)
    ro.flags.writeable = False
    with pytest.raises(moma.InvalidInputError, match="out"):
        cal.align_into(pred, ro)
    with pytest.raises(moma.InvalidInputError):
        cal.align_into(pred, [[0.0]])


def test_bad_ground_truth_and_masks():
    pred, gt = scene()
    with pytest.raises(moma.InvalidInputError, match="size mismatch"):
        moma.calibrate(pred, gt[:, :100], kind="relative-disparity")
    with pytest.raises(moma.InvalidInputError, match="no valid"):
        moma.calibrate(pred, np.zeros_like(gt), kind="relative-disparity")
    with pytest.raises(moma.InvalidInputError, match="bool or uint8"):
        moma.calibrate(pred, gt, kind="relative-disparity", mask=np.ones(pred.shape, np.float32))
    with pytest.raises(moma.InvalidInputError, match="2-D"):
        moma.calibrate(pred, gt, kind="relative-disparity", workspace=np.ones((3, 120, 160), bool))
    with pytest.raises(moma.InvalidInputError, match="size mismatch"):
        moma.calibrate(pred, gt, kind="relative-disparity", mask=np.ones((10, 10), bool))


def test_bad_intrinsics():
    with pytest.raises(moma.InvalidInputError, match="fx"):
        moma.Intrinsics(-1.0, 100.0, 10.0, 10.0, 20, 20)
    with pytest.raises(moma.InvalidInputError, match="empty"):
        moma.Intrinsics(1.0, 1.0, 0.0, 0.0, 0, 20)
    with pytest.raises(OverflowError):  # a negative pixel count is not an unsigned integer
        moma.Intrinsics(1.0, 1.0, 0.0, 0.0, -5, 20)


def test_camera_size_must_match_prediction():
    pred, gt = scene()
    cam = moma.Intrinsics(100.0, 100.0, 50.0, 40.0, 100, 80)
    with pytest.raises(moma.InvalidInputError, match="size mismatch"):
        moma.calibrate(pred, gt, cam, kind="relative-disparity")


def test_metrics_errors():
    gt = np.ones((4, 4), np.float32)
    with pytest.raises(moma.InvalidInputError, match="size mismatch"):
        moma.metrics(np.ones((4, 5), np.float32), gt)
    with pytest.raises(moma.InvalidInputError, match="no pixel"):
        moma.metrics(gt, np.zeros((4, 4), np.float32))


def test_bad_rgb_for_points():
    cam = moma.Intrinsics(10.0, 10.0, 1.5, 1.5, 4, 4)
    d = np.ones((4, 4), np.float32)
    with pytest.raises(moma.InvalidInputError, match="uint8"):
        moma.depth_to_points(d, cam, rgb=np.zeros((4, 4, 3), np.float32))
    with pytest.raises(moma.InvalidInputError, match="3"):
        moma.depth_to_points(d, cam, rgb=np.zeros((4, 4, 4), np.uint8))
    with pytest.raises(moma.InvalidInputError, match="size mismatch"):
        moma.depth_to_points(d, cam, rgb=np.zeros((5, 4, 3), np.uint8))
    with pytest.raises(moma.InvalidInputError, match="size mismatch"):
        moma.depth_to_points(np.ones((5, 4), np.float32), cam)
