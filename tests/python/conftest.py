"""Shared helpers of the Python tests: synthetic scenes with known answers, and NumPy
re-implementations of moma's maths written from docs/method.md (independent of the Rust code)."""

import os
import pathlib
import shutil
import struct
import zlib

import numpy as np
import pytest

REPO = pathlib.Path(__file__).resolve().parents[2]


def normalise_np(pred, kind, norm="minmax-unit", region=None):
    """docs/method.md §1 in NumPy (float64): inverse depth → 1/d (NaN for d ≤ 0), then min-max etc."""
    d = np.asarray(pred, dtype=np.float64)
    if kind == "relative-disparity":
        with np.errstate(divide="ignore"):
            z = np.where(d > 0, 1.0 / np.where(d > 0, d, 1.0), np.nan)
    else:
        z = d.copy()
    vals = z[np.isfinite(z) & (region if region is not None else True)]
    zmin, zmax = vals.min(), vals.max()
    if norm == "minmax":
        return (z - zmin) / (zmax - zmin) + zmin
    if norm == "minmax-unit":
        return (z - zmin) / (zmax - zmin)
    if norm == "median":
        m = np.median(vals)
        return (z - m) / np.mean(np.abs(vals - m))
    return z


def ssra_apply_np(zhat, alpha, beta, gamma, t3):
    """z = ẑ(αu + βv + γ) + T3 with u the column and v the row index (pixels)."""
    h, w = zhat.shape
    u = np.arange(w, dtype=zhat.dtype)[None, :]
    v = np.arange(h, dtype=zhat.dtype)[:, None]
    return zhat * (alpha * u + beta * v + gamma) + t3


def metrics_np(pred, gt, mask=None):
    """Depth metrics from their definitions (docs/method.md): pixels with valid gt and finite pred."""
    p = np.asarray(pred, dtype=np.float64)
    g = np.asarray(gt, dtype=np.float64)
    ok = np.isfinite(g) & (g > 0) & np.isfinite(p)
    if mask is not None:
        ok &= mask.astype(bool)
    p, g = p[ok], g[ok]
    ratio_ok = lambda t: np.mean((p < t * g) & (g < t * p))  # noqa: E731
    return {
        "d105": ratio_ok(1.05),
        "d110": ratio_ok(1.10),
        "d125": ratio_ok(1.25),
        "rel": np.mean(np.abs(p - g) / g),
        "rmse": np.sqrt(np.mean((p - g) ** 2)),
        "mae": np.mean(np.abs(p - g)),
        "n": int(ok.sum()),
    }


# Known SSRA parameters of the synthetic scenes (metres per unit ẑ per pixel, metres).
TRUE = dict(alpha=2.0e-4, beta=-1.5e-4, gamma=0.35, t3=0.12)


def scene(h=120, w=160, seed=0, kind="relative-disparity", norm="minmax-unit", holes=True):
    """A smooth random prediction and the metric ground truth SSRA maps it to exactly
    (TRUE parameters), with some invalid ground-truth pixels (0 and NaN)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    base = 1.0 + 0.5 * np.sin(xx / 17.0) * np.cos(yy / 23.0) + 0.3 * rng.random((h, w))
    pred = base.astype(np.float32)  # inverse depth or depth, arbitrary scale
    zhat = normalise_np(pred, kind, norm)
    gt = ssra_apply_np(zhat, **TRUE).astype(np.float32)
    # what no sensor measures (under 1 mm; the median-normalised scene reaches 0): no depth, as
    # a calibration refuses ground truth under 0.1 mm
    gt[gt < 1e-3] = 0.0
    if holes:
        gt[rng.random((h, w)) < 0.05] = 0.0
        gt[:3, :5] = np.nan
    return pred, gt


@pytest.fixture
def small_scene():
    return scene()


@pytest.fixture
def cam():
    import moma

    return moma.Intrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)


def moma_bin():
    """The `moma` CLI binary: $MOMA_BIN, else target/release/moma, else None."""
    env = os.environ.get("MOMA_BIN")
    if env:
        return env if shutil.which(env) or os.path.isfile(env) else None
    p = REPO / "target" / "release" / "moma"
    return str(p) if p.is_file() else None


def shared_dir():
    d = os.environ.get("MOMA_SHARED_DIR")
    return pathlib.Path(d) if d else None


def smooth_scene(h=120, w=160):
    """A smooth static scene (no per-pixel noise, so that the anchor rule's depth-edge test
    keeps its pixels): depth z = 0.9 + 0.0008·u − 0.001·v + 0.05·sin(u/25)·cos(v/30) metres and
    an inverse-depth prediction 1.6/z − 0.4 (a disparity with scale and shift)."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = 0.9 + 0.0008 * u - 0.001 * v + 0.05 * np.sin(u / 25.0) * np.cos(v / 30.0)
    return (1.6 / z - 0.4).astype(np.float32), z.astype(np.float32)


def textured_rgb(h=120, w=160, seed=0):
    """A smooth, strongly textured RGB background (uint8 H×W×3): every 3×3 patch is distinctive
    at half resolution, mid-grey so that neither end saturates."""
    rng = np.random.default_rng(seed)
    coarse = rng.integers(40, 216, size=(h // 4 + 1, w // 4 + 1, 3))
    img = np.repeat(np.repeat(coarse, 4, axis=0), 4, axis=1)[:h, :w]
    return np.ascontiguousarray(img.astype(np.uint8))


def write_png(path, rgb):
    """A minimal 8-bit RGB PNG writer (no filter), so that the tests need no imaging package."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    h, w, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[i].tobytes() for i in range(h))

    def chunk(tag, data):
        body = tag + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))
    with open(path, "wb") as f:
        f.write(png)
