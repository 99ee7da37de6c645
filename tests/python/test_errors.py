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
        (np.zeros((120, 160, 2), np.float32), "2-D"),
        (np.zeros((1, 120, 160, 1), np.float32), "2-D"),
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


def test_a_map_with_a_single_axis_is_one_map(cal):
    """A model's (1, H, W) output and a file's (H, W, 1) map align as the (H, W) map, as
    `moma.read_prediction` and the CLI take them."""
    pred, _ = scene()
    want = cal.align(pred)
    for same in (pred[None], pred[..., None], pred[None].astype(np.float64)):
        np.testing.assert_array_equal(cal.align(same), want)


def test_nan_in_prediction_is_named(cal):
    pred, _ = scene()
    pred[7, 9] = np.nan
    with pytest.raises(moma.InvalidInputError, match=r"non-finite.*u=9, v=7"):
        cal.align(pred)
    with pytest.raises(moma.InvalidInputError, match="non-finite"):
        moma.calibrate(pred, scene()[1], kind="relative-disparity")


def test_float64_beyond_float32_is_named(cal):
    """A finite float64 that float32 cannot hold is said to be one, not a NaN/inf of the
    input; the input's own inf stays "non-finite"."""
    pred, _ = scene()
    big = pred.astype(np.float64)
    big[3, 4] = 1e40
    # numpy warns of the overflow in its cast before moma says what it means
    with np.errstate(over="ignore"), pytest.raises(
        moma.InvalidInputError, match=r"1 value\(s\) beyond float32's range"
    ):
        cal.align(big)
    big[3, 4] = np.inf
    with pytest.raises(moma.InvalidInputError, match=r"non-finite.*u=4, v=3"):
        cal.align(big)


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
    # a negative pixel count is named (not a bare OverflowError from the binding)
    with pytest.raises(moma.InvalidInputError, match="width=-5: must be a non-negative integer"):
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


def test_negative_counts_and_seeds_name_the_argument():
    pred, gt = scene()
    for kw in ("samples", "seed", "edge_margin_px"):
        with pytest.raises(moma.InvalidInputError, match=f"{kw}=-1: must be a non-negative integer"):
            moma.calibrate(pred, gt, kind="relative-disparity", **{kw: -1})
    cam = moma.Intrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
    for kw in ("top", "seed", "grasp_draws"):
        with pytest.raises(moma.InvalidInputError, match=f"{kw}=-1"):
            moma.plan_grasps(gt, cam, **{kw: -1})
    with pytest.raises(moma.InvalidInputError, match="seed=18446744073709551616: too large"):
        moma.plan_grasps(gt, cam, seed=2**64)


def test_millimetres_are_refused_where_metres_are_expected(cal):
    pred, gt = scene()
    cam = moma.Intrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
    mm16 = np.nan_to_num(gt * 1000.0).astype(np.uint16)  # what a depth PNG holds
    mm32 = gt * 1000.0  # the same, cast to float without dividing
    for mm, says in ((mm16, "dtype uint16: depth in metres is floating point"), (mm32, "looks like millimetres")):
        with pytest.raises(moma.InvalidInputError, match=says):
            moma.calibrate(pred, mm, kind="relative-disparity")
        with pytest.raises(moma.InvalidInputError, match=says):
            moma.plan_grasps(mm, cam)
        with pytest.raises(moma.InvalidInputError, match=says):
            moma.metrics(mm, gt)
        with pytest.raises(moma.InvalidInputError, match=says):
            cal.sigma_map(mm)
    # the reverse: metres divided by 1000 once too often (a scene a millimetre away)
    km = gt / 1000.0
    for call in (
        lambda: moma.calibrate(pred, km, kind="relative-disparity"),
        lambda: moma.plan_grasps(km, cam),
        lambda: moma.metrics(km, gt),
        lambda: cal.sigma_map(km),
    ):
        with pytest.raises(moma.InvalidInputError, match="no scene a camera grasps in is that near"):
            call()
    with pytest.raises(moma.InvalidInputError, match="dtype bool"):
        moma.metrics(np.ones(gt.shape, bool), gt)
    # metres pass, in any float dtype
    assert moma.metrics(gt.astype(np.float64), gt)["mae"] == 0.0


def test_a_failed_realigned_align_into_leaves_out_as_it_was():
    pred, gt = scene(norm="minmax")  # a scene 0.32–0.69 m away (minmax-unit's: 0.12–0.49 m)
    rgb = np.random.default_rng(3).integers(0, 255, (*pred.shape, 3), dtype=np.uint8)
    cal = moma.calibrate(pred, gt, kind="relative-disparity", anchors_rgb=rgb, norm="minmax")
    out = np.full(pred.shape, 7.0, np.float32)
    with pytest.raises(moma.InvalidInputError, match="frame RGB is 160x60"):
        cal.align_realigned_into(pred, rgb[:60], out)
    assert (out == 7.0).all()
    # and the anchors' RGB of another size is named with the sizes the right way round
    with pytest.raises(moma.InvalidInputError, match=r"anchors_rgb is 160x60 \(WxH\), expected 160x120"):
        moma.calibrate(pred, gt, kind="relative-disparity", anchors_rgb=rgb[:60])


def test_read_depth_gives_nan_where_there_is_no_depth(tmp_path):
    p = tmp_path / "z.npy"
    np.save(p, np.array([[0.0, -1.0, np.inf, 0.5]], np.float32))
    z = moma.read_depth(str(p))
    assert np.isnan(z[0, :3]).all() and z[0, 3] == np.float32(0.5)
    # an empty map is not written (it could not be read back)
    for name in ("e.npy", "e.pfm", "e.png"):
        with pytest.raises(moma.MomaError):
            moma.write_depth(str(tmp_path / name), np.zeros((0, 3), np.float32))
        assert not (tmp_path / name).exists()


def test_calibrations_and_cameras_pickle_and_read_back_from_json(cal):
    import copy
    import pickle

    back = pickle.loads(pickle.dumps(cal))
    assert back.to_json() == cal.to_json()
    assert moma.Calibration.from_json(cal.to_json()).to_json() == cal.to_json()
    pred, _ = scene()
    assert np.array_equal(copy.deepcopy(cal).align(pred), cal.align(pred), equal_nan=True)
    cam = moma.Intrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
    assert pickle.loads(pickle.dumps(cam)) == cam and copy.deepcopy(cam) == cam
    with pytest.raises(moma.MomaFileError, match="json text"):
        moma.Calibration.from_json("{\"format\": \"moma-calibration\"")


def test_a_mask_given_as_a_list_is_read_as_numpy_reads_it():
    pred, gt = scene()
    inside = np.zeros(pred.shape, bool)
    inside[5:115, 5:155] = True
    inside[:, 80] = False  # a column without samples: the mask is used, not ignored
    a = moma.calibrate(pred, gt, kind="relative-disparity", mask=inside)
    b = moma.calibrate(pred, gt, kind="relative-disparity", mask=inside.tolist())
    assert np.array_equal(a.samples, b.samples)
    assert inside[a.samples[:, 1].astype(int), a.samples[:, 0].astype(int)].all()
