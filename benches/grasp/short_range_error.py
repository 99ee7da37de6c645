#!/usr/bin/env python3
"""Short-range error of the REAL Depth Anything 3 predictions in ../shared/data/zed-da3-office,
against the simulator's correlated noise (docs/grasping.md, "What the planning depth cannot show").

At a suction cup's scale (a few pixels) the simulated predictions carry a multiplicative noise of
0.5 % correlated over σ = 4 px (docs/method.md §6, component 5b), which makes a small patch's tilt
unobservable.  This script asks whether a real network's prediction is smoother than that.  For
each frame, on the pixels whose stereo reference lies in 0.3–3 m and away from depth edges (the
5 × 5 window's range under 3 % of the depth, in the reference and in the prediction), the
prediction is aligned to the reference by one global scale and shift (least squares), and the
relative error e = (aligned − reference) / reference is summarised by its semivariogram,
√(½·mean((e(p) − e(p + L))²)) over horizontal and vertical pixel pairs at lag L.  The reference
is stereo, not ground truth: its own noise is in e, so the real rows are an upper bound on the
network's short-range error.  For comparison, the simulator's noise alone at the same lags:
s·√(1 − exp(−L² / (4σ²))), s = 0.5 %, σ = 4 px (the set is 640 px wide, the simulator's scale).

    python3 benches/grasp/short_range_error.py ../shared/data/zed-da3-office

Needs numpy and the moma Python package (`pip install .`, as .ci/run does).  REAL predictions,
stereo reference.
"""

import json
import sys

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

import moma

LAGS = [1, 2, 4, 8, 16, 32]
NEAR_M, FAR_M = 0.3, 3.0
EDGE_RANGE = 0.03  # a 5 × 5 window whose depth range exceeds this share of the depth is an edge
SIM_NOISE, SIM_SIGMA_PX = 0.005, 4.0


def semivariogram(e, valid, lag):
    """√(½·mean of squared increments) of `e` over valid horizontal and vertical pairs at `lag`."""
    h, w = e.shape
    parts = []
    for dv, du in ((0, lag), (lag, 0)):
        both = valid[: h - dv, : w - du] & valid[dv:, du:]
        parts.append((e[: h - dv, : w - du] - e[dv:, du:])[both])
    d = np.concatenate(parts)
    return float(np.sqrt(0.5 * np.mean(d * d))) if d.size else float("nan")


def window_range(depth):
    """Range (max − min) of the finite values in each pixel's 5 × 5 window (NaN: none)."""
    windows = sliding_window_view(np.pad(depth, 2, mode="edge"), (5, 5))
    finite = np.isfinite(windows)
    hi = np.where(finite, windows, -np.inf).max(axis=(2, 3))
    lo = np.where(finite, windows, np.inf).min(axis=(2, 3))
    return np.where(finite.any(axis=(2, 3)), hi - lo, np.nan)


def main(set_dir):
    with open(f"{set_dir}/predictions/predictions.json") as f:
        manifest = json.load(f)
    if manifest.get("simulated", True):
        sys.exit("this check is for REAL predictions; the manifest says simulated (or does not say)")
    frames = manifest["frames"]
    print("| frame | pixels | " + " | ".join(f"L = {lag} px" for lag in LAGS) + " |")
    print("|---|---:|" + "---:|" * len(LAGS))
    for fid in frames:
        ref = np.asarray(moma.read_depth(f"{set_dir}/frames/{fid}/depth.png"), dtype=np.float64)
        pred = np.load(f"{set_dir}/predictions/{fid}.npy").astype(np.float64)
        if ref.shape != pred.shape:
            sys.exit(f"{fid}: reference {ref.shape} but prediction {pred.shape}")
        ref_nan = np.where(ref > 0, ref, np.nan)
        ok = (ref > NEAR_M) & (ref < FAR_M) & np.isfinite(pred) & (pred > 0)
        with np.errstate(invalid="ignore"):
            ok &= window_range(ref_nan) < EDGE_RANGE * ref
            ok &= window_range(np.where(pred > 0, pred, np.nan)) < EDGE_RANGE * pred
        if ok.sum() < 1000:
            sys.exit(f"{fid}: only {ok.sum()} usable pixels")
        a = np.stack([pred[ok], np.ones(int(ok.sum()))], axis=1)
        scale, shift = np.linalg.lstsq(a, ref[ok], rcond=None)[0]
        e = np.where(ok, (scale * pred + shift - ref) / np.where(ok, ref, 1.0), 0.0)
        cells = " | ".join(f"{100 * semivariogram(e, ok, lag):.2f} %" for lag in LAGS)
        print(f"| {fid} (REAL, vs stereo) | {int(ok.sum())} | {cells} |")
    sim = " | ".join(
        f"{100 * SIM_NOISE * np.sqrt(1 - np.exp(-lag * lag / (4 * SIM_SIGMA_PX**2))):.2f} %"
        for lag in LAGS
    )
    print(f"| simulator's noise alone (SIMULATED) | | {sim} |")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
