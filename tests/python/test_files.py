"""Files: calibration save/load round trip (the CLI's format), depth and camera files, file errors."""

import json

import numpy as np
import pytest

import moma
from conftest import scene


def test_save_load_round_trip(tmp_path, cam):
    pred, gt = scene()
    cal = moma.calibrate(pred, gt, cam, kind="relative-disparity", samples=60, seed=4)
    path = tmp_path / "calib.json"
    cal.save(path)
    text = json.loads(path.read_text())
    assert text["format"] == "moma-calibration" and text["version"] == 9
    assert text["prediction_kind"] == "relative-disparity" and text["method"] == "ssra"
    back = moma.Calibration.load(str(path))
    assert back.report == cal.report
    assert back.intrinsics == cam and back.kind == cal.kind and back.shape == cal.shape
    np.testing.assert_array_equal(back.samples, cal.samples)
    other = (pred * 0.9 + 0.1).astype(np.float32)
    np.testing.assert_array_equal(back.align(other), cal.align(other))
    assert json.loads(back.to_json())["calibration"] == text["calibration"]


def test_workspace_mask_is_embedded_in_the_file(tmp_path):
    pred, gt = scene()
    ws = np.zeros(pred.shape, dtype=bool)
    ws[10:90, 20:150] = True
    cal = moma.calibrate(pred, gt, kind="relative-disparity", workspace=ws)
    cal.save(tmp_path / "cal.json")
    embedded = json.loads((tmp_path / "cal.json").read_text())["calibration"]["workspace"]
    assert embedded["inside_px"] == int(ws.sum())
    # the file alone is enough: move it elsewhere
    moved = tmp_path / "elsewhere" / "cal.json"
    moved.parent.mkdir()
    (tmp_path / "cal.json").rename(moved)
    back = moma.Calibration.load(moved)
    np.testing.assert_array_equal(back.workspace, ws)
    np.testing.assert_array_equal(back.align(pred), cal.align(pred))


def test_load_errors_are_os_errors(tmp_path):
    with pytest.raises(moma.MomaFileError, match="missing.json"):
        moma.Calibration.load(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "something-else", "version": 1}')
    with pytest.raises(OSError, match="unsupported calibration file"):
        moma.Calibration.load(bad)
    bad.write_text("{ not json")
    with pytest.raises(moma.MomaFileError, match="invalid JSON"):
        moma.Calibration.load(bad)


def test_save_into_missing_directory_is_an_os_error(tmp_path):
    pred, gt = scene()
    cal = moma.calibrate(pred, gt, kind="relative-disparity")
    with pytest.raises(OSError):
        cal.save(tmp_path / "no" / "such" / "dir" / "c.json")


@pytest.mark.parametrize("ext", ["npy", "pfm", "png"])
def test_depth_files_round_trip(tmp_path, ext):
    depth = np.array([[0.5, 1.2344, np.nan], [0.0, 2.0, 70.0]], dtype=np.float32)
    stats = moma.write_depth(tmp_path / f"d.{ext}", depth)
    assert stats["pixels"] == 6 and stats["invalid"] == 2
    back = moma.read_depth(tmp_path / f"d.{ext}")
    assert back.dtype == np.float32 and back.shape == (2, 3)
    if ext == "png":  # millimetres: rounded; > 65.535 m and invalid become "no depth"
        assert stats["out_of_range"] == 1
        np.testing.assert_allclose(back[0, :2], [0.5, 1.234], rtol=0, atol=1e-6)
        assert np.isnan(back[0, 2]) and np.isnan(back[1, 0]) and np.isnan(back[1, 2])
    else:
        valid = np.isfinite(depth) & (depth > 0)  # float metres: valid depths exact
        np.testing.assert_array_equal(back[valid], depth[valid])
        assert not (np.isfinite(back[~valid]) & (back[~valid] > 0)).any()


def test_npy_is_readable_by_numpy(tmp_path):
    depth = np.arange(12, dtype=np.float32).reshape(3, 4) / 10 + 0.1
    moma.write_depth(tmp_path / "d.npy", depth)
    np.testing.assert_array_equal(np.load(tmp_path / "d.npy"), depth)
    np.save(tmp_path / "p.npy", depth * 3)
    np.testing.assert_array_equal(moma.read_prediction(tmp_path / "p.npy"), depth * 3)


def test_read_depth_errors(tmp_path):
    with pytest.raises(moma.MomaFileError, match="nothing.png"):
        moma.read_depth(tmp_path / "nothing.png")
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(moma.MomaFileError):
        moma.read_depth(tmp_path / "x.txt")


def test_camera_json_round_trip(tmp_path, cam):
    cam.save(tmp_path / "camera.json")
    assert json.loads((tmp_path / "camera.json").read_text())["cx"] == 79.5
    assert moma.Intrinsics.load(tmp_path / "camera.json") == cam
    with pytest.raises(moma.MomaFileError):
        moma.Intrinsics.load(tmp_path / "none.json")


def _grey_png(path, img):
    """An 8-bit greyscale PNG written with the standard library (no imaging package needed)."""
    import struct
    import zlib

    h, w = img.shape
    raw = b"".join(b"\x00" + img[v].astype(np.uint8).tobytes() for v in range(h))

    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw))
    path.write_bytes(png + chunk(b"IEND", b""))


def test_read_mask_is_nonzero_as_bool(tmp_path):
    img = np.zeros((5, 7), np.uint8)
    img[1:3, 2:6] = 255
    img[4, 0] = 7  # any nonzero value is inside
    _grey_png(tmp_path / "mask.png", img)
    m = moma.read_mask(tmp_path / "mask.png")
    assert m.dtype == np.bool_ and m.shape == (5, 7)
    np.testing.assert_array_equal(m, img != 0)
    with pytest.raises(OSError, match="missing.png"):
        moma.read_mask(tmp_path / "missing.png")
