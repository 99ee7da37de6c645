"""Round trips with the `moma` CLI: a calibration made in Python aligns identically with
`moma align`, and one made by `moma calibrate` aligns identically in Python. Runs the binary
from $MOMA_BIN or target/release/moma; skipped when neither exists."""

import json
import subprocess

import numpy as np
import pytest

import moma
from conftest import moma_bin, scene

BIN = moma_bin()
pytestmark = pytest.mark.skipif(
    BIN is None,
    reason="moma CLI not found: set MOMA_BIN or build it (cargo build --release -p moma-cli)",
)


def run(*args):
    r = subprocess.run([BIN, *map(str, args)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return r.stdout


@pytest.fixture
def frames(tmp_path, cam):
    pred, gt = scene()
    other = (pred * 1.1 + 0.05).astype(np.float32)
    np.save(tmp_path / "pred0.npy", pred)
    np.save(tmp_path / "pred1.npy", other)
    moma.write_depth(tmp_path / "gt.npy", gt)
    cam.save(tmp_path / "camera.json")
    return tmp_path, pred, gt, other


def test_python_calibration_aligns_identically_with_cli(frames, cam):
    d, pred, gt, other = frames
    ws = np.zeros(pred.shape, dtype=np.uint8)
    ws[5:115, 5:155] = 1
    cal = moma.calibrate(pred, gt, cam, kind="relative-disparity", samples=80, seed=9, workspace=ws)
    cal.save(d / "py.json")
    run("align", "--calib", d / "py.json", "--pred", d / "pred1.npy",
        "--pred-kind", "relative-disparity", "-o", d / "out_py")
    cli = np.load(d / "out_py" / "pred1.depth.npy")
    np.testing.assert_array_equal(cli, cal.align(other))


def test_cli_calibration_aligns_identically_in_python(frames):
    d, pred, gt, other = frames
    out = run("calibrate", "--pred", d / "pred0.npy", "--pred-kind", "relative-disparity",
              "--gt", d / "gt.npy", "--camera", d / "camera.json", "--samples", "50",
              "--seed", "2", "-o", d / "cli.json", "--json")
    summary = json.loads(out)
    cal = moma.Calibration.load(d / "cli.json")
    assert cal.report["model"] == summary["model"]
    assert cal.report["n_used"] == summary["n_used"] == 50
    # same seed and samples in Python: the same fit
    py = moma.calibrate(pred, gt, moma.Intrinsics.load(d / "camera.json"),
                        kind="relative-disparity", samples=50, seed=2)
    assert py.report["model"] == summary["model"]
    run("align", "--calib", d / "cli.json", "--pred", d / "pred1.npy",
        "--pred-kind", "relative-disparity", "-o", d / "out_cli")
    np.testing.assert_array_equal(np.load(d / "out_cli" / "pred1.depth.npy"), cal.align(other))
