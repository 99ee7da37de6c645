"""`moma.plan_grasps`: a box of known size on a table, seen straight down by a pinhole camera;
the same dicts as `moma grasp --json` (compared with the CLI when its binary is found)."""

import json
import subprocess

import numpy as np
import pytest

import moma
from conftest import moma_bin

W, H, F = 320, 240, 300.0
TABLE_M, TOP_M = 0.70, 0.65  # camera looks straight down: table at 0.70 m, box top 50 mm above
BOX_HALF_M = (0.035, 0.020)  # 70 mm × 40 mm footprint, long side along x


def box_scene():
    cam = moma.Intrinsics(F, F, (W - 1) / 2, (H - 1) / 2, W, H)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    x_top = (u - cam.cx) / F * TOP_M
    y_top = (v - cam.cy) / F * TOP_M
    on_box = (np.abs(x_top) <= BOX_HALF_M[0]) & (np.abs(y_top) <= BOX_HALF_M[1])
    depth = np.where(on_box, TOP_M, TABLE_M).astype(np.float32)
    return cam, depth, on_box


def test_suction_on_the_top_face_and_parallel_across_the_narrow_side():
    cam, depth, box = box_scene()
    suction = moma.plan_grasps(depth, cam, gripper="suction", mask=box, top=3)
    assert suction and suction[0]["kind"] == "suction"
    assert set(suction[0]) == {"kind", "score", "success_prob", "point_m", "approach"}
    assert suction[0]["success_prob"] is None  # no error model
    x, y, z = suction[0]["point_m"]
    assert abs(z - TOP_M) < 0.003 and abs(x) < BOX_HALF_M[0] and abs(y) < BOX_HALF_M[1]
    a = np.array(suction[0]["approach"])
    assert np.degrees(np.arccos(np.clip(a @ [0, 0, 1], -1, 1))) < 5.0  # into the top face
    scores = [g["score"] for g in suction]
    assert scores == sorted(scores, reverse=True)

    parallel = moma.plan_grasps(depth, cam, gripper="parallel", mask=box, top=5)
    assert parallel and parallel[0]["kind"] == "parallel"
    g = parallel[0]
    assert set(g) == {"kind", "score", "success_prob", "center_m", "approach", "closing", "width_m"}
    closing = np.abs(np.array(g["closing"]))
    assert closing[1] > 0.9  # closes across the 40 mm side (y)
    assert 2 * BOX_HALF_M[1] <= g["width_m"] <= 0.085


def test_nothing_graspable_is_an_empty_list_and_bad_input_raises():
    cam, depth, _ = box_scene()
    table = np.full_like(depth, TABLE_M)
    with pytest.warns(UserWarning, match="no grasp: no object"):  # the reason, as the CLI prints it
        assert moma.plan_grasps(table, cam, gripper="suction") == []
    with pytest.raises(ValueError, match="gripper"):
        moma.plan_grasps(depth, cam, gripper="vacuum")
    with pytest.raises(ValueError):
        moma.plan_grasps(np.full_like(depth, np.nan), cam)
    with pytest.raises(ValueError):
        moma.plan_grasps(depth[:, :10], cam)


@pytest.mark.skipif(moma_bin() is None, reason="moma CLI not found: set MOMA_BIN")
def test_same_grasps_as_the_cli(tmp_path):
    cam, depth, _ = box_scene()
    moma.write_depth(str(tmp_path / "d.npy"), depth)
    cam.save(str(tmp_path / "camera.json"))
    for gripper in ("suction", "parallel"):
        out = subprocess.run(
            [moma_bin(), "grasp", "--depth", str(tmp_path / "d.npy"), "--camera",
             str(tmp_path / "camera.json"), "--gripper", gripper, "--top", "3", "--json"],
            capture_output=True, text=True, timeout=300,
        )
        assert out.returncode == 0, out.stderr
        cli = json.loads(out.stdout)
        py = moma.plan_grasps(depth, cam, gripper=gripper, top=3)
        assert len(py) == len(cli) > 0
        for a, b in zip(py, cli):
            assert a["kind"] == b["kind"]
            for key in a:
                if key == "success_prob":
                    assert a[key] == b[key]
                elif key != "kind":
                    np.testing.assert_allclose(a[key], b[key], rtol=1e-5, atol=1e-6)


def test_without_a_mask_regions_touching_the_border_are_not_objects():
    # the first 12 rows curl 15 mm towards the camera (a sensor's edge band): above the 10 mm
    # object height, but on the border, so only the box is planned on, unless asked
    cam, depth, _ = box_scene()
    depth = depth.copy()
    depth[:12] -= 0.015
    rows = lambda gs: [cam.fy * g["point_m"][1] / g["point_m"][2] + cam.cy for g in gs]
    # as `moma grasp` notes it: the dropped region is named
    with pytest.warns(UserWarning, match=r"1 region\(s\) above the support plane touch the image border.*keep_border_objects=True"):
        default = moma.plan_grasps(depth, cam, gripper="suction", top=10)
    assert default and all(v >= 12 for v in rows(default))
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # kept: nothing to say
        kept = moma.plan_grasps(depth, cam, gripper="suction", top=10, keep_border_objects=True)
    assert any(v < 12 for v in rows(kept))


def test_a_uniform_sigma_gives_probabilities_and_a_minimum_filters_them():
    cam, depth, box = box_scene()
    robust = moma.plan_grasps(depth, cam, gripper="suction", mask=box, top=5, sigma_m=0.003)
    assert robust and all(0.0 <= g["success_prob"] <= 1.0 for g in robust)
    # the same seed draws the same depth maps: the same probabilities
    again = moma.plan_grasps(depth, cam, gripper="suction", mask=box, top=5, sigma_m=0.003)
    assert [g["success_prob"] for g in again] == [g["success_prob"] for g in robust]
    # a minimum no grasp reaches under a 50 mm σ (compliance 15 mm): an empty list, with the
    # reason as a warning (1 is beyond what 4 draws can give: (4 + 1) / (4 + 2))
    with pytest.warns(UserWarning, match=r"below the minimum 1\.00.*with 4 depth draws no grasp can exceed 0\.83"):
        assert moma.plan_grasps(depth, cam, gripper="suction", mask=box, sigma_m=0.05, min_success_prob=1.0) == []
    # a reachable minimum above every grasp: the reason asks for another image
    with pytest.warns(UserWarning, match="re-image"):
        assert moma.plan_grasps(depth, cam, gripper="suction", mask=box, sigma_m=0.05, min_success_prob=0.8) == []
    for bad in (dict(grasp_draws=0), dict(min_success_prob=1.5), dict(grasp_quality="best")):
        with pytest.raises(ValueError):
            moma.plan_grasps(depth, cam, gripper="suction", sigma_m=0.003, **bad)
    with pytest.raises(ValueError, match="error model"):
        moma.plan_grasps(depth, cam, gripper="suction", grasp_quality="robust")


def test_planning_from_a_calibration_aligns_as_align_does_and_has_a_sigma_map():
    cam, gt, box = box_scene()
    # a prediction in inverse depth with a known affine map, its silhouettes softened over 3 px
    # (as a depth model's are): the calibration recovers the depth but at the box's edges
    soft = gt.copy()
    soft[1:-1, 1:-1] = sum(
        gt[1 + dv : H - 1 + dv, 1 + du : W - 1 + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)
    ) / 9.0
    pred = (2.0 / soft + 0.5).astype(np.float32)
    cal = moma.calibrate(pred, gt, cam, kind="relative-disparity", method="gssa", norm="none", space="inverse")
    model = cal.error_model
    assert model is not None and model["sigma_flat_m"] < 2e-3 and model["edge_gain"] > 0.0
    depth = cal.align(pred)
    sigma = cal.sigma_map(depth)
    assert sigma.shape == depth.shape and sigma.dtype == np.float32
    assert np.all(np.isfinite(sigma[np.isfinite(depth)])) and np.all(sigma >= 0)
    # near the box's edge the σ is larger than on the table (the edge part)
    assert sigma[H // 2, W // 2 + int(BOX_HALF_M[0] / TOP_M * F)] > sigma[5, 5]
    with pytest.raises(ValueError):
        cal.sigma_map(depth[:, :10])
    from_cal = moma.plan_grasps(cal, gripper="suction", mask=box, top=3, pred=pred)
    from_depth = moma.plan_grasps(depth, cam, gripper="suction", mask=box, top=3, grasp_quality="nominal")
    assert from_cal and all(g["success_prob"] is not None for g in from_cal)
    # planned on the error model's expected truth of the aligned depth: on the box top, within
    # 5 mm of its true depth and inside its footprint
    for g in from_cal:
        x, y, z = g["point_m"]
        assert abs(z - TOP_M) < 0.005, g
        assert abs(x) <= BOX_HALF_M[0] and abs(y) <= BOX_HALF_M[1], g
    assert from_depth
    with pytest.raises(ValueError, match="pred"):
        moma.plan_grasps(cal, gripper="suction")
    with pytest.raises(ValueError):
        moma.plan_grasps(depth, cam, pred=pred)


def test_an_object_that_pulls_the_calibration_gets_a_height_part(tmp_path):
    # a table seen obliquely (0.8 m at the top row, 0.6 m at the bottom: a flat table seen from
    # above alone would not determine a scale) and a box covering 16 % of the image, 50 mm
    # tall; the prediction flattens the box to half its height (as depth models flatten objects)
    cam = moma.Intrinsics(F, F, (W - 1) / 2, (H - 1) / 2, W, H)
    v, u = np.mgrid[0:H, 0:W]
    table = 1.0 / (1.0 / 0.8 + (1.0 / 0.6 - 1.0 / 0.8) * v / (H - 1))
    box = (np.abs(u - W / 2) < 0.2 * W) & (np.abs(v - H / 2) < 0.2 * H)
    gt = np.where(box, table - 0.05, table).astype(np.float32)
    flat = np.where(box, table - 0.025, table)
    pred = (2.0 / flat + 0.5).astype(np.float32)
    cal = moma.calibrate(pred, gt, cam, kind="relative-disparity", method="gssa", norm="none", space="inverse", seed=3)
    s = cal.samples
    on = box[s[:, 1].astype(int), s[:, 0].astype(int)]
    assert on.sum() >= 3

    def slope(keep):
        return np.polyfit(s[keep, 2], 1.0 / s[keep, 3], 1)[0]

    # GSSA's slope with and without the box's samples (the table alone fits exactly)
    pull = abs(slope(np.ones_like(on)) / slope(~on) - 1.0)
    assert pull > 0.02
    hs = cal.error_model["height_sigma"]
    assert pull * (1 - 1e-6) <= hs <= 1.25 * pull
    path = tmp_path / "calib.json"
    cal.save(path)
    assert moma.Calibration.load(str(path)).error_model["height_sigma"] == hs
    # a prediction that keeps the box's height: nothing pulls, no height part in the file
    exact = moma.calibrate((2.0 / gt + 0.5).astype(np.float32), gt, cam, kind="relative-disparity", method="gssa", norm="none", space="inverse", seed=3)
    assert exact.error_model.get("height_sigma", 0.0) < 1e-6


def test_grasp_check_executes_the_planned_grasps_on_the_truth():
    cam, gt, box = box_scene()
    # an exact prediction (inverse depth, affine): the grasps planned on its alignment hold on
    # the truth; the same prediction of a scene 30 mm farther off puts every suction cup 30 mm
    # behind the box top (compliance 15 mm): none holds
    pred = (2.0 / gt + 0.5).astype(np.float32)
    cal = moma.calibrate(pred, gt, cam, kind="relative-disparity", method="gssa", norm="none", space="inverse")
    check = moma.grasp_check(cal, pred, gt, gripper="suction", mask=box)
    assert set(check) == {
        "gripper", "scores", "grasps", "successes", "success_rate", "mean_success_prob",
        "failures", "no_grasp_reason", "notes",
    }
    assert check["notes"] == []
    assert check["gripper"] == "suction" and check["scores"] == "proxy"
    assert check["grasps"] > 0 and check["successes"] == check["grasps"], check
    assert check["success_rate"] == 1.0 and 0.0 < check["mean_success_prob"] < 1.0
    far = (2.0 / (gt + 0.03) + 0.5).astype(np.float32)
    missed = moma.grasp_check(cal, far, gt, gripper="suction", mask=box)
    assert missed["grasps"] > 0 and missed["successes"] == 0, missed
    assert sum(missed["failures"].values()) == missed["grasps"]
    # nothing to grasp: no grasp, and why
    table = np.full_like(gt, TABLE_M)
    empty = moma.grasp_check(cal, (2.0 / table + 0.5).astype(np.float32), table, gripper="parallel")
    assert empty["grasps"] == 0 and empty["success_rate"] is None
    assert "support plane" in empty["no_grasp_reason"]
    # without a mask, a band along the top edge 15 mm nearer (as a sensor's depth curls at a
    # frame's edge) touches the border: not tried, and the check says so, as a warning too
    curled = gt.copy()
    curled[:12] -= 0.015
    with pytest.warns(UserWarning, match="moma.grasp_check: 1 region.*image border"):
        edged = moma.grasp_check(cal, (2.0 / curled + 0.5).astype(np.float32), curled, gripper="suction")
    assert len(edged["notes"]) == 1 and "image border" in edged["notes"][0], edged
    assert edged["grasps"] > 0 and edged["successes"] == edged["grasps"], edged
    with pytest.raises(ValueError, match="gripper"):
        moma.grasp_check(cal, pred, gt, gripper="vacuum")
    with pytest.raises(ValueError):
        moma.grasp_check(cal, pred, gt[:, :10])


@pytest.mark.skipif(moma_bin() is None, reason="moma CLI not found: set MOMA_BIN")
def test_gripper_config_tie_tolerance_and_extrinsics_as_the_cli_takes_them(tmp_path):
    cam, depth, box = box_scene()
    moma.write_depth(str(tmp_path / "d.npy"), depth)
    cam.save(str(tmp_path / "camera.json"))
    # a jaw opening at most 60 mm: the box's 40 mm side fits, with less clearance
    config = {"stroke_m": 0.06, "opening_clearance_m": 0.005}
    (tmp_path / "jaw.json").write_text(json.dumps(config))
    # the camera 1 m above the base looking down: base = (x, −y, 1 − z)
    rows = [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 1], [0, 0, 0, 1]]
    (tmp_path / "ext.json").write_text(json.dumps({"camera_to_base": rows}))
    out = subprocess.run(
        [moma_bin(), "grasp", "--depth", str(tmp_path / "d.npy"), "--camera",
         str(tmp_path / "camera.json"), "--gripper", "parallel", "--top", "3", "--json",
         "--gripper-config", str(tmp_path / "jaw.json"), "--extrinsics", str(tmp_path / "ext.json")],
        capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr
    cli = json.loads(out.stdout)
    for gripper_config, extrinsics in (
        (config, np.array(rows, float)),
        (str(tmp_path / "jaw.json"), tmp_path / "ext.json"),
    ):
        py = moma.plan_grasps(depth, cam, gripper="parallel", top=3,
                              gripper_config=gripper_config, extrinsics=extrinsics)
        assert len(py) == len(cli) > 0
        for a, b in zip(py, cli):
            np.testing.assert_allclose(a["width_m"], b["width_m"], rtol=1e-6)
            assert a["width_m"] <= 0.06
            np.testing.assert_allclose(a["base"]["center_m"], b["base"]["center_m"], atol=1e-6)
            x, y, z = a["center_m"]
            np.testing.assert_allclose(a["base"]["center_m"], [x, -y, 1 - z], atol=1e-6)
    # a jaw narrower than the box finds nothing, and says so
    with pytest.warns(UserWarning, match="no grasp"):
        assert moma.plan_grasps(depth, cam, mask=box, gripper_config={"stroke_m": 0.03}) == []
    # bad settings are named
    with pytest.raises(moma.InvalidInputError, match="gripper_config"):
        moma.plan_grasps(depth, cam, gripper_config={"stroke_mm": 60})
    with pytest.raises(moma.InvalidInputError, match="extrinsics"):
        moma.plan_grasps(depth, cam, extrinsics=np.eye(4) * 2)
    with pytest.raises(moma.InvalidInputError, match="tolerance"):
        moma.plan_grasps(depth, cam, gripper="suction", sigma_m=0.005, tie_tolerance=1.5)
    assert moma.plan_grasps(depth, cam, gripper="suction", sigma_m=0.005, tie_tolerance=0.2)


def test_a_bins_walls_are_no_object_and_label_masks_keep_objects_apart():
    """Without a mask a tote's walls (15 cm, fully in view) are a container, not an object: a
    warning says so and every grasp is on the box inside. A mask of integer labels (one value
    per object, a segmentation's output) keeps two touching boxes apart: no suction cup on
    their seam, where a 0/1 mask of the same boxes puts the best ones."""
    w, h, f, table = 640, 480, 600.0, 0.8
    cam = moma.Intrinsics(f, f, (w - 1) / 2, (h - 1) / 2, w, h)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)

    def at(z):  # table-frame x, y of each pixel's ray at depth z (camera looks straight down)
        return (u - cam.cx) / f * z, (v - cam.cy) / f * z

    def inside(x, y, cx, hx, hy):
        return (np.abs(x - cx) < hx) & (np.abs(y) < hy)

    xw, yw = at(table - 0.15)
    walls = inside(xw, yw, -0.1, 0.2, 0.15) & ~inside(xw, yw, -0.1, 0.19, 0.14)
    xb, yb = at(table - 0.05)
    box = inside(xb, yb, -0.1, 0.03, 0.05)
    depth = np.where(walls, table - 0.15, np.where(box, table - 0.05, table)).astype(np.float32)
    with pytest.warns(UserWarning, match="enclose an opening of a container's size"):
        grasps = moma.plan_grasps(depth, cam, gripper="suction", top=5)
    assert grasps
    for g in grasps:
        x, y, z = g["point_m"]
        assert abs(z - (table - 0.05)) < 0.003 and abs(x / z * (table - 0.05) + 0.1) < 0.03, g

    # two 40 mm boxes side by side, touching along x = 0, one flat top
    xt, yt = at(0.65)
    both = (np.abs(xt) < 0.04) & (np.abs(yt) < 0.035)
    depth = np.where(both, 0.65, 0.70).astype(np.float32)
    labels = np.where(both, np.where(xt < 0, 1, 2), 0).astype(np.int32)
    for g in moma.plan_grasps(depth, cam, gripper="suction", mask=labels, top=5):
        assert abs(g["point_m"][0]) >= 0.01, g  # the cup's 10 mm radius off the seam
    binary = moma.plan_grasps(depth, cam, gripper="suction", mask=both, top=5)
    assert any(abs(g["point_m"][0]) < 0.01 for g in binary)
    with pytest.raises(moma.InvalidInputError, match="negative"):
        moma.plan_grasps(depth, cam, gripper="suction", mask=-labels)
