"""Few-shot calibration, robust fits, the alignment space and per-frame re-alignment on static
anchors from Python (issue 12), against independent expectations: a one-frame list is the
one-shot fit, a robust fit with 20 % gross outliers on a synthetic plane matches the clean fit,
a covered background keeps the one-shot result; and bad input raises ValueError naming the
problem. The same paths against the `moma` CLI are in test_cli_issue12.py."""

import numpy as np
import pytest

import moma
from conftest import scene, smooth_scene, textured_rgb, write_png

# ---------------------------------------------------------------------------------------------
# synthetic scenes


def frames(n, h=120, w=160, holes=True):
    """`n` frames of one camera: the conftest scene with different seeds (a different
    prediction and ground truth each, the same TRUE alignment)."""
    pairs = [scene(h=h, w=w, seed=10 + i, holes=holes) for i in range(n)]
    return [p for p, _ in pairs], [g for _, g in pairs]


def plane_scene(h=120, w=160, noise_m=0.0, outliers=0.0, seed=0):
    """A tilted table seen by a camera: depth z = 0.8 + 0.001·u − 0.0015·v metres (a plane in
    image coordinates), and a depth prediction that is an affine map of it (what GSSA and SSRA
    recover exactly). With `outliers`, that fraction of ground-truth pixels is replaced by gross
    errors of 0.2–0.6 m (either sign); `noise_m` adds Gaussian noise to the ground truth."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = 0.8 + 0.001 * u - 0.0015 * v
    pred = ((z - 0.3) * 2.5).astype(np.float32)
    gt = z + noise_m * rng.standard_normal(z.shape)
    if outliers:
        bad = rng.random(z.shape) < outliers
        gt[bad] += rng.choice([-1.0, 1.0], bad.sum()) * rng.uniform(0.2, 0.6, bad.sum())
    return pred, gt.astype(np.float32), z.astype(np.float32)


# ---------------------------------------------------------------------------------------------
# few-shot


@pytest.mark.parametrize("method", ["ssra", "gssa", "lwlr"])
def test_few_shot_with_one_frame_equals_one_shot(method, cam):
    pred, gt = scene()
    mask = np.ones(pred.shape, dtype=bool)
    mask[:, :20] = False
    one = moma.calibrate(pred, gt, cam, kind="relative-disparity", method=method, samples=60,
                         seed=4, mask=mask)
    few = moma.calibrate([pred], [gt], cam, kind="relative-disparity", method=method, samples=60,
                         seed=4, mask=[mask])
    assert few.report["model"] == one.report["model"]
    assert few.report["n_used"] == one.report["n_used"] == 60
    np.testing.assert_array_equal(few.samples, one.samples)
    other = (pred * 1.2 + 0.1).astype(np.float32)
    np.testing.assert_array_equal(few.align(other), one.align(other))


def test_few_shot_samples_per_frame_and_frame_zero_is_the_one_shot_draw(cam):
    preds, gts = frames(3)
    kw = dict(kind="relative-disparity", samples=40, seed=7, space="depth")
    few = moma.calibrate(preds, gts, cam, **kw)
    one = moma.calibrate(preds[0], gts[0], cam, **kw)
    s = few.samples
    assert s.shape == (120, 4) and few.report["n_used"] == 120
    # frame 0 keeps the one-shot seed: its samples come first, identical
    np.testing.assert_array_equal(s[:40], one.samples)
    # frames 1 and 2 draw other pixels (derived seeds), normalised on their own
    assert not np.array_equal(s[40:80, :2], s[:40, :2])
    assert not np.array_equal(s[80:, :2], s[40:80, :2])
    # every frame follows the same exact SSRA map (in depth space, each frame normalised on its
    # own), so the union is fitted exactly too
    assert few.report["rms_residual_m"] < 1e-4
    for p, g in zip(preds, gts):
        ok = np.isfinite(g) & (g > 0)
        np.testing.assert_allclose(few.align(p)[ok], g[ok], rtol=1e-4, atol=1e-5)


def test_few_shot_averages_a_per_frame_fluctuation():
    """Three frames whose predictions carry different disparity shifts (the per-frame
    fluctuation of a depth model): the 3-frame fit is not worse on average over the frames than
    the 1-frame fits (issue 12's check, here on a synthetic scene with a known answer)."""
    h, w = 120, 160
    rng = np.random.default_rng(3)
    v, u = np.mgrid[0:h, 0:w]
    z = (0.7 + 0.2 * np.sin(u / 19.0) * np.cos(v / 13.0) + 0.1 * rng.random((h, w))).astype(
        np.float32)
    shifts = [0.0, 0.15, -0.1]
    preds = [(1.0 / z + b).astype(np.float32) for b in shifts]
    gts = [z] * 3
    few = moma.calibrate(preds, gts, kind="relative-disparity", method="gssa", seed=1)
    mae_few = np.mean([moma.metrics(few.align(p), z)["mae"] for p in preds])
    mae_one = np.mean([
        np.mean([moma.metrics(moma.calibrate(pk, z, kind="relative-disparity", method="gssa",
                                             seed=1).align(p), z)["mae"] for p in preds])
        for pk in preds
    ])
    assert mae_few <= mae_one


# ---------------------------------------------------------------------------------------------
# robust fits


@pytest.mark.parametrize(
    "robust,threshold_m",
    [
        # 3 σ of the 1 mm sensor noise, for every kind
        ("huber", 0.003), ("tukey", 0.003), ("ransac", 0.003),
        # moma's default threshold: `auto`, from a robust estimate of the residual scale
        ("huber", None), ("tukey", None), ("ransac", None),
    ],
)
@pytest.mark.parametrize("method", ["ssra", "gssa"])
@pytest.mark.parametrize("seed", [1, 2])
def test_robust_fit_with_20_percent_gross_outliers_stays_close_to_the_clean_fit(
    robust, threshold_m, method, seed
):
    pred, gt_noisy, _ = plane_scene(noise_m=0.001, seed=seed)
    pred_o, gt_out, _ = plane_scene(noise_m=0.001, outliers=0.2, seed=seed)
    assert np.array_equal(pred, pred_o)
    kw = dict(kind="metric-depth", method=method, space="depth", samples=100, seed=5)
    clean = moma.calibrate(pred, gt_noisy, **kw).align(pred)
    plain = moma.calibrate(pred, gt_out, **kw).align(pred)
    cal = moma.calibrate(pred, gt_out, robust=robust, robust_threshold_m=threshold_m, **kw)
    rob = cal.align(pred)
    # least squares is dragged by the outliers (the test can fail) ...
    assert np.mean(np.abs(plain - clean)) > 0.01
    # ... the robust fit stays within 1 mm of the outlier-free fit on average (MAE between the
    # two depth maps), and within 3 mm everywhere (SSRA's corners extrapolate)
    assert np.mean(np.abs(rob - clean)) < 0.001
    assert np.max(np.abs(rob - clean)) < 0.003
    r = cal.report["robust"]
    assert r["kind"] == robust
    if threshold_m is not None:
        assert r["threshold_m"] == threshold_m
    else:
        # the scale is estimated from the 1 mm noise, not from the 0.1-0.5 m outliers
        assert 0.0005 < r["auto"]["scale_m"] < 0.002
    # about 80 % of the 100 samples are inliers (the outliers are 0.2 m or more away)
    assert 65 <= r["inliers"] <= 95
    assert r["inlier_rms_residual_m"] < 0.005


def test_robust_threshold_is_recorded_and_plain_fit_has_no_robust_block():
    pred, gt, _ = plane_scene(noise_m=0.001, outliers=0.2, seed=2)
    cal = moma.calibrate(pred, gt, kind="metric-depth", method="gssa", robust="huber",
                         robust_threshold_m=0.02, seed=3)
    assert cal.report["robust"]["threshold_m"] == 0.02
    plain = moma.calibrate(pred, gt, kind="metric-depth", method="gssa", seed=3)
    assert "robust" not in plain.report


def test_robust_ransac_is_seeded_and_few_shot_robust_works():
    pred, gt, _ = plane_scene(noise_m=0.001, outliers=0.2, seed=4)
    a = moma.calibrate(pred, gt, kind="metric-depth", method="gssa", robust="ransac", seed=8)
    b = moma.calibrate(pred, gt, kind="metric-depth", method="gssa", robust="ransac", seed=8)
    assert a.report["model"] == b.report["model"]
    few = moma.calibrate([pred, pred], [gt, gt], kind="metric-depth", method="gssa", robust="tukey",
                         seed=8)
    assert few.report["n_used"] == 200 and few.report["robust"]["kind"] == "tukey"


# ---------------------------------------------------------------------------------------------
# alignment space


def test_inverse_space_recovers_a_disparity_shift_exactly():
    """d = a/z + b with b = −0.5·mean(a/z): only a fit in inverse space can undo the shift
    (issue 12's check)."""
    h, w = 120, 160
    rng = np.random.default_rng(0)
    z = (0.6 + 0.5 * rng.random((h, w))).astype(np.float64)
    a = 2.0
    b = -0.5 * np.mean(a / z)
    pred = (a / z + b).astype(np.float32)
    gt = z.astype(np.float32)
    inv = moma.calibrate(pred, gt, kind="relative-disparity", method="gssa", space="inverse")
    dep = moma.calibrate(pred, gt, kind="relative-disparity", method="gssa", space="depth")
    assert inv.space == "inverse" and dep.space == "depth"
    assert moma.calibrate(pred, gt, kind="relative-disparity", method="gssa").space == "inverse"
    np.testing.assert_allclose(inv.align(pred), gt, rtol=2e-5)
    assert moma.metrics(dep.align(pred), gt)["rel"] > 0.01


# ---------------------------------------------------------------------------------------------
# re-alignment on static anchors


@pytest.fixture
def anchored():
    """A calibration with anchors on a textured static scene, and its inputs; the paper's
    minmax, so that a frame's disparity scale and shift reach the aligned depth and re-alignment
    has something to correct (the default, minmax-unit, absorbs them)."""
    pred, gt = smooth_scene()
    rgb = textured_rgb()
    cal = moma.calibrate(pred, gt, kind="relative-disparity", method="gssa", seed=2,
                         anchors_rgb=rgb, norm="minmax")
    return cal, pred, gt, rgb


def test_a_saturated_calibration_rgb_is_named_when_calibrating():
    """As `moma calibrate --anchors` warns: no anchor can lie where the image is blown out."""
    import warnings
    pred, gt = smooth_scene()
    rgb = textured_rgb()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a textured image: no warning at all
        moma.calibrate(pred, gt, kind="relative-disparity", method="gssa", seed=2,
                       anchors_rgb=rgb)
    blown = rgb.copy()
    h = blown.shape[0]
    blown[: h // 2] = 255  # the upper half saturated: 50 % of the image
    with pytest.warns(UserWarning, match=r"(4[5-9]|5[0-5]) % of the calibration frame's RGB "
                                         r"is saturated.*exposure.*\(anchors_rgb=\)"):
        cal = moma.calibrate(pred, gt, kind="relative-disparity", method="gssa", seed=2,
                             anchors_rgb=blown)
    assert cal.has_anchors


def test_plan_grasps_takes_the_realignment_settings_and_says_when_a_frame_kept_one_shot(anchored):
    """`plan_grasps(cal, pred=, rgb=, realign={...})` re-aligns with align_realigned's options,
    as `moma grasp --realign-*` does (it used the defaults whatever the user set)."""
    import warnings
    cal, pred, gt, rgb = anchored
    cam = moma.Intrinsics(100.0, 100.0, 79.5, 59.5, 160, 120)
    drifted = (pred * 1.15 + 0.1).astype(np.float32)
    # the default settings accept the frame: no re-alignment warning
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        moma.plan_grasps(cal, cam, pred=drifted, rgb=rgb, gripper="suction")
    assert not [w for w in caught if "re-alignment" in str(w.message)]
    # a setting no correction meets reaches the re-alignment: the frame keeps the one-shot depth
    with pytest.warns(UserWarning, match=r"re-alignment \(rgb=\): kept the one-shot result: .*needs > 1000000000 standard error"):
        moma.plan_grasps(cal, cam, pred=drifted, rgb=rgb, gripper="suction",
                         realign={"acceptance_se": 1e9})
    _, report = cal.align_realigned(drifted, rgb, acceptance_se=1e9)
    assert report["accepted"] is False
    with pytest.raises(ValueError, match="unknown re-alignment option 'ridges'"):
        moma.plan_grasps(cal, cam, pred=drifted, rgb=rgb, realign={"ridges": 1.0})
    with pytest.raises(ValueError, match="needs the frame's rgb="):
        moma.plan_grasps(cal, cam, pred=drifted, realign={"ridge": 1.0})
    with pytest.raises(ValueError, match="go with a Calibration"):
        moma.plan_grasps(gt, cam, realign={"ridge": 1.0})


def test_realign_on_a_covered_background_keeps_the_one_shot_result(anchored):
    cal, pred, gt, rgb = anchored
    assert cal.has_anchors
    other = (pred * 0.9 + 0.05).astype(np.float32)
    covered = textured_rgb(seed=99)  # every pixel changed: no static anchor left
    depth, report = cal.align_realigned(other, covered)
    assert report["accepted"] is False
    assert report["reason"]
    assert report["anchors"] < 50
    np.testing.assert_array_equal(depth, cal.align(other))


def test_realign_on_the_unchanged_background_corrects_a_fluctuation(anchored):
    cal, pred, gt, rgb = anchored
    # the depth model's output drifts (a disparity scale and shift) while the scene does not
    drifted = (pred * 1.15 + 0.1).astype(np.float32)
    depth, report = cal.align_realigned(drifted, rgb)
    assert set(report) == {"anchors", "anchors_used", "brightness_gain",
                           "held_out_rmse_before_m", "held_out_rmse_after_m",
                           "held_out_gain_m", "held_out_gain_se_m", "correction", "target",
                           "accepted", "reason", "held_out_truth_rmse_m",
                           "held_out_truth_inverse_rmse_per_m"}
    assert report["target"] == "calibration-output"
    assert report["correction"] == "scale-shift"
    assert report["held_out_gain_m"] > report["held_out_gain_se_m"] > 0
    assert report["anchors"] >= 50 and report["anchors_used"] > 0
    assert report["brightness_gain"] == pytest.approx(1.0)
    assert report["accepted"] is True, report["reason"]
    assert report["held_out_rmse_after_m"] < report["held_out_rmse_before_m"]
    plain = cal.align(drifted)
    assert moma.metrics(depth, gt)["mae"] < 0.5 * moma.metrics(plain, gt)["mae"]
    # the frame's own error against the calibration's truth (stored in whole millimetres) at
    # the held-out anchors: the whole scene is static background here, so it is the frame's
    # dense error against gt
    ok = np.isfinite(depth) & (gt > 0)
    rmse_m = float(np.sqrt(np.mean((depth[ok] - gt[ok]) ** 2)))
    inverse = float(np.sqrt(np.mean((1.0 / depth[ok] - 1.0 / gt[ok]) ** 2)))
    assert report["held_out_truth_rmse_m"] == pytest.approx(rmse_m, rel=0.5, abs=1e-3)
    assert report["held_out_truth_inverse_rmse_per_m"] == pytest.approx(inverse, rel=0.5,
                                                                        abs=2e-3)
    # a global brightness change of the frame does not remove the anchors
    brighter = np.clip(rgb.astype(np.float32) * 1.2, 0, 255).astype(np.uint8)
    _, rep2 = cal.align_realigned(drifted, brighter)
    assert rep2["brightness_gain"] == pytest.approx(1.2, abs=0.03)
    assert rep2["anchors"] >= 0.8 * report["anchors"]


def test_realign_into_options_and_file_round_trip(anchored, tmp_path):
    cal, pred, gt, rgb = anchored
    drifted = (pred * 1.15 + 0.1).astype(np.float32)
    depth, report = cal.align_realigned(drifted, rgb)
    out = np.full(pred.shape, -1.0, dtype=np.float32)
    ptr = out.ctypes.data
    rep = cal.align_realigned_into(drifted, rgb, out)
    assert out.ctypes.data == ptr and rep == report
    np.testing.assert_array_equal(out, depth)
    # strided (non-contiguous) RGB is read in place: the same result
    wide = np.zeros((120, 160, 4), dtype=np.uint8)
    wide[..., :3] = rgb
    d2, r2 = cal.align_realigned(drifted, wide[..., :3])
    np.testing.assert_array_equal(d2, depth)
    assert r2 == report
    # options reach the re-alignment: a ridge of 0 shrinks nothing, so the result changes
    d3, _ = cal.align_realigned(drifted, rgb, ridge=0.0, correction="planar",
                                target="ground-truth", seed=3)
    assert not np.array_equal(d3, depth)
    # too many anchors required: not accepted, with the reason
    d4, r4 = cal.align_realigned(drifted, rgb, min_anchors=100000, max_anchors=200000)
    assert r4["accepted"] is False and r4["reason"]
    np.testing.assert_array_equal(d4, cal.align(drifted))
    # the anchor store is embedded in the file
    cal.save(tmp_path / "c.json")
    back = moma.Calibration.load(tmp_path / "c.json")
    assert back.has_anchors
    d5, r5 = back.align_realigned(drifted, rgb)
    np.testing.assert_array_equal(d5, depth)
    assert r5 == report


def test_anchors_from_an_image_file_equal_anchors_from_the_array(anchored, tmp_path):
    cal, pred, gt, rgb = anchored
    write_png(tmp_path / "rgb.png", rgb)
    from_file = moma.calibrate(pred, gt, kind="relative-disparity", method="gssa", seed=2,
                               anchors_rgb=str(tmp_path / "rgb.png"), norm="minmax")
    assert from_file.has_anchors
    drifted = (pred * 1.15 + 0.1).astype(np.float32)
    a = cal.align_realigned(drifted, rgb)
    b = from_file.align_realigned(drifted, rgb)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[1] == b[1]


# ---------------------------------------------------------------------------------------------
# bad input


def test_bad_input_raises_value_error_naming_the_problem(anchored):
    cal, pred, gt, rgb = anchored
    small_p, small_g = scene(h=60, w=80)
    preds, gts = frames(2)
    cases = [
        (lambda: moma.calibrate([pred, small_p], [gt, small_g], kind="relative-disparity"),
         "same size"),
        (lambda: moma.calibrate([pred, pred], [gt], kind="relative-disparity"),
         "2 predictions and 1 ground truths"),
        (lambda: moma.calibrate([pred, pred], gt, kind="relative-disparity"), "both lists"),
        (lambda: moma.calibrate(pred, [gt, gt], kind="relative-disparity"), "both lists"),
        (lambda: moma.calibrate([], [], kind="relative-disparity"), "at least one frame"),
        (lambda: moma.calibrate(pred, gt, kind="relative-disparity", robust="l1"),
         "unknown robust fit 'l1'"),
        (lambda: moma.calibrate(pred, gt, kind="relative-disparity", robust_threshold_m=0.01),
         "needs robust="),
        (lambda: moma.calibrate(pred, gt, kind="relative-disparity", robust="huber",
                                robust_threshold_m=-1.0), "robust_threshold_m"),
        (lambda: moma.calibrate(pred, gt, kind="relative-disparity", robust="huber",
                                method="lwlr"), "lwlr"),
        (lambda: moma.calibrate(preds, gts, kind="relative-disparity",
                                mask=[np.ones(pred.shape, bool)] * 3), "3 masks for 2"),
        (lambda: moma.calibrate(pred, gt, kind="relative-disparity", space="disparity"),
         "disparity"),
        (lambda: moma.calibrate(pred, gt, kind="relative-disparity",
                                anchors_rgb=textured_rgb(60, 80)), "anchors_rgb"),
        (lambda: moma.calibrate(pred, gt, kind="relative-disparity",
                                anchors_rgb=rgb.astype(np.float32)), "uint8"),
        (lambda: moma.calibrate(pred, gt, kind="relative-disparity", anchors_rgb=5),
         "image path (str or os.PathLike) or a uint8"),
        (lambda: moma.calibrate(pred, gt, kind="relative-disparity", anchors_rgb=b"rgb.png"),
         "got bytes"),
        (lambda: cal.align_realigned(pred, rgb, ridge=-1.0), "ridge"),
        (lambda: cal.align_realigned(pred, rgb, ridg=1.0), "unknown re-alignment option"),
        (lambda: cal.align_realigned(pred, rgb, correction="cubic"), "cubic"),
        (lambda: cal.align_realigned(pred, textured_rgb(60, 80)), "RGB"),
        (lambda: cal.align_realigned(pred, rgb[..., 0]), "rgb"),
    ]
    for call, words in cases:
        with pytest.raises(ValueError, match=None) as e:
            call()
        assert isinstance(e.value, moma.InvalidInputError), e.value
        assert words.lower() in str(e.value).lower(), (words, str(e.value))
    plain = moma.calibrate(pred, gt, kind="relative-disparity")
    assert not plain.has_anchors
    with pytest.raises(moma.InvalidInputError, match="no anchor store"):
        plain.align_realigned(pred, rgb)
    with pytest.raises(moma.MomaFileError, match="nope.png"):
        moma.calibrate(pred, gt, kind="relative-disparity", anchors_rgb="nope.png")


def test_a_glitched_pixel_that_the_normalisation_follows_is_named():
    """One pixel far below the rest of a prediction moves a min-max normalised frame as a whole
    (no error, wrong metres): `align`, `align_into`, `align_realigned` and `plan_grasps` name it
    in a UserWarning, as `moma align` and `moma grasp` print it; a clean frame says nothing."""
    import warnings
    pred, gt = smooth_scene()
    rgb = textured_rgb()
    cal = moma.calibrate(pred, gt, kind="relative-disparity", method="gssa", seed=2,
                         anchors_rgb=rgb)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        clean = cal.align(pred)
    glitched = pred.copy()
    glitched[30, 40] = -5.0
    says = r"1 pixel\(s\) of the prediction lie far below the rest.*-5 at pixel \(u=40, v=30\)"
    with pytest.warns(UserWarning, match="moma.Calibration.align: " + says):
        moved = cal.align(glitched)
    # the warning is about something real: the frame moved by centimetres
    assert np.nanmedian(np.abs(moved - clean)) > 0.01
    out = np.empty_like(gt)
    with pytest.warns(UserWarning, match="moma.Calibration.align_into: " + says):
        cal.align_into(glitched, out)
    with pytest.warns(UserWarning, match="moma.Calibration.align_realigned: " + says):
        cal.align_realigned(glitched, rgb)
    cam = moma.Intrinsics(100.0, 100.0, 79.5, 59.5, 160, 120)
    with pytest.warns(UserWarning, match="moma.plan_grasps: " + says):
        moma.plan_grasps(cal, cam, pred=glitched, gripper="suction")
    # in the calibration frame the fit learns it: calibrate names it
    with pytest.warns(UserWarning, match="moma.calibrate: the calibration frame: " + says):
        moma.calibrate(glitched, gt, kind="relative-disparity", method="gssa", seed=2)
