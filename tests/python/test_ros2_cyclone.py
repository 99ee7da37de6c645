"""Interoperability of `moma ros2` with a second, independent DDS implementation: Eclipse Cyclone
DDS (the `cyclonedds` package bundles it) subscribes to the node's `depth` and `grasps_json` with
the ROS 2 type names (`sensor_msgs::msg::dds_::Image_` on `rt/depth`). The depth it receives
must equal `moma align`'s on the same frames bit for bit, and the grasps must be
`moma grasp --json`'s shape.

All traffic stays in a network namespace of its own (`unshare --net`, `lo` only), which needs
root, as CI has. Outside CI the test is skipped, visibly, without root, the CLI, the shared data
or cyclonedds; under CI (CI=true) those are required."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO, moma_bin, shared_dir

BIN = moma_bin()
SHARED = shared_dir()
SET = "graspnet6dof-table"


def _missing():
    if BIN is None:
        return "the moma CLI (MOMA_BIN)"
    if SHARED is None or not (SHARED / "data" / SET).is_dir():
        return "the shared data (MOMA_SHARED_DIR)"
    if os.geteuid() != 0 or shutil.which("unshare") is None or shutil.which("ip") is None:
        return "root, unshare and ip (a network namespace of its own)"
    try:
        import cyclonedds  # noqa: F401
    except ImportError:
        return "the cyclonedds package"
    return None


MISSING = _missing()
pytestmark = pytest.mark.skipif(
    MISSING is not None and os.environ.get("CI") != "true",
    reason=f"needs {MISSING}",
)


def run(*args):
    out = subprocess.run([BIN, *args], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_cyclone_dds_receives_the_nodes_depth_and_grasps(tmp_path):
    assert MISSING is None, f"CI must provide {MISSING}"
    set_dir = SHARED / "data" / SET
    preds = tmp_path / "preds"
    run("simulate", "--set", str(set_dir), "-o", str(preds))
    names = sorted(p.stem for p in preds.glob("*.npy"))  # one set: OUT itself
    f0 = set_dir / "frames" / names[0]
    calib = tmp_path / "calib.json"
    run("calibrate", "--pred", str(preds / f"{names[0]}.npy"), "--gt",
        str(f0 / "depth.png"), "--camera", str(set_dir / "camera.json"), "-o", str(calib))
    aligned = tmp_path / "aligned"
    run("align", "--calib", str(calib), "--pred", *[str(preds / f"{n}.npy") for n in names],
        "-o", str(aligned))
    out = tmp_path / "received"
    out.mkdir()
    driver = REPO / "tests" / "python" / "ros2_cyclone_driver.py"
    proc = subprocess.run(["unshare", "--net", "--", sys.executable, str(driver), BIN,
                           str(set_dir), str(preds), str(calib), str(out)],
                          capture_output=True, text=True, timeout=150)
    assert proc.returncode == 0, proc.stderr[-4000:]
    summary = json.loads((out / "summary.json").read_text())
    assert sorted(summary["received"]) == names, summary["received"]
    for n in names:
        got = np.load(out / f"{n}.received.npy")
        want = np.load(aligned / f"{n}.depth.npy")
        same = (got.view(np.uint32) == want.view(np.uint32)) | (np.isnan(got) & np.isnan(want))
        assert same.all(), f"{n}: {np.count_nonzero(~same)} pixels differ from moma align"
    assert summary["n_grasp_messages"] > 0
    for grasps in summary["grasps"]:
        assert isinstance(grasps, list) and len(grasps) <= 3
        for g in grasps:
            assert g["kind"] == "suction"
            assert len(g["point_m"]) == 3 and len(g["approach"]) == 3
            assert "success_prob" in g
