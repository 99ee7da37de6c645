#!/usr/bin/env python3
"""Does the error model's σ hold away from the calibration samples? (docs/grasping.md, "σ away
from the samples").

Issue 22 asked for a σ that grows near depth edges and away from samples or anchors.  The error
model has edge parts, and a distance part (`sample_distance_gain`) that the calibration fits only
when its samples reach part of the image.  This measures whether σ holds away from the samples: for each opaque shared set, SIMULATED predictions
(`moma simulate`, simulator seeds 0–2), SSRA, GSSA and LWLR calibrated on the set's first frame
(`moma calibrate`, sampling seed 0, 100 samples), every later frame aligned one-shot with its σ
map (`moma align --sigma-map`), the share of true errors |truth − aligned| within ±1σ in bands of
the distance (pixels) to the nearest calibration sample: the pixels pooled over the frames and
the simulator seeds, split at the quartiles and the 90th percentile of that distance.  Where the
share falls with the distance, σ is too narrow far from the samples; where it stays level, the
model carries the distance.

    python3 benches/grasp/sigma_by_sample_distance.py ../shared OUT [--left-half]

With --left-half the samples are drawn in the image's left half only (`moma calibrate --mask`
with a mask the script writes): a cell whose samples cover part of the image, where the far
bands are extrapolation.

MOMA (default target/release/moma) may be set.  Needs numpy and the moma Python package
(`pip install .`, as .ci/run does).  About 2 minutes on the 2-core build machine.
"""

import json
import os
import struct
import subprocess
import sys
import zlib

import numpy as np

import moma

SETS = ["gqcnn-primesense", "graspnet6dof-table", "m2t2-table"]
METHODS = ["ssra", "gssa", "lwlr"]
SIM_SEEDS = [0, 1, 2]
BANDS = [0.25, 0.5, 0.75, 0.9]  # quantiles of the distance that split the bands


def run(moma_bin, *args):
    subprocess.run([moma_bin, *args], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def write_mask_png(path, inside):
    """An 8-bit greyscale PNG of the boolean array `inside` (255 inside), with the standard
    library only (no imaging package is needed by this script)."""
    h, w = inside.shape
    raw = b"".join(b"\x00" + (inside[v].astype(np.uint8) * 255).tobytes() for v in range(h))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    with open(path, "wb") as f:
        f.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
                + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def distance_to_samples(shape, uv):
    """Distance (pixels) of every pixel to the nearest of the sample pixels `uv` (n × 2: u, v)."""
    h, w = shape
    vv, uu = np.mgrid[0:h, 0:w]
    d2 = np.full(shape, np.inf)
    for u, v in uv:
        d2 = np.minimum(d2, (uu - u) ** 2 + (vv - v) ** 2)
    return np.sqrt(d2)


def main(shared, out, left_half=False):
    moma_bin = os.environ.get("MOMA", os.path.join(os.path.dirname(__file__), "../../target/release/moma"))
    print(
        "SIMULATED predictions: % of true errors within ±1σ by distance to the nearest calibration "
        f"sample (one-shot, frames after the first, simulator seeds 0–2, sampling seed 0"
        f"{'; samples in the left half only' if left_half else ''}); bands "
        "split at the distance's 25/50/75/90th percentiles (pixels in brackets)\n"
    )
    print("| set | method | region | d < q25 | q25–q50 | q50–q75 | q75–q90 | ≥ q90 | all |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|")
    for name in SETS:
        set_dir = f"{shared}/data/{name}"
        frames = sorted(os.listdir(f"{set_dir}/frames"))
        calib, later = frames[0], frames[1:]
        sample_mask = None
        if left_half:
            h, w = np.asarray(moma.read_depth(f"{set_dir}/frames/{calib}/depth.png")).shape
            sample_mask = f"{out}/{name}/left_half.png"
            os.makedirs(f"{out}/{name}", exist_ok=True)
            write_mask_png(sample_mask, np.arange(w)[None, :].repeat(h, 0) < w // 2)
        for method in METHODS:
            # per region: (distances, within 1σ) pooled over frames and seeds
            pooled = {"all": ([], []), "masks": ([], [])}
            for seed in SIM_SEEDS:
                pred = f"{out}/{name}/sim{seed}"
                if not os.path.isdir(pred):
                    run(moma_bin, "simulate", "--set", set_dir, "--seed", str(seed), "-o", pred)
                cal = f"{out}/{name}/sim{seed}.{method}.json"
                run(moma_bin, "calibrate", "--pred", f"{pred}/{calib}.npy",
                    "--gt", f"{set_dir}/frames/{calib}/depth.png", "--camera", f"{set_dir}/camera.json",
                    "--method", method, "--seed", "0", "-o", cal,
                    *(["--mask", sample_mask] if sample_mask else []))
                aligned = f"{out}/{name}/sim{seed}.{method}"
                run(moma_bin, "align", "--calib", cal, "--pred", *[f"{pred}/{f}.npy" for f in later],
                    "--sigma-map", "-o", aligned)
                with open(cal) as f:
                    samples = json.load(f)["calibration"]["samples"]["samples"]
                uv = np.array([[s["u"], s["v"]] for s in samples])
                dist = None
                for fr in later:
                    gt = np.asarray(moma.read_depth(f"{set_dir}/frames/{fr}/depth.png"), dtype=np.float64)
                    al = np.load(f"{aligned}/{fr}.depth.npy").astype(np.float64)
                    sg = np.load(f"{aligned}/{fr}.sigma.npy").astype(np.float64)
                    if dist is None:
                        dist = distance_to_samples(gt.shape, uv)
                    ok = np.isfinite(gt) & (gt > 0) & np.isfinite(al) & np.isfinite(sg)
                    within = np.abs(gt - al) <= sg
                    mask_file = f"{set_dir}/frames/{fr}/mask.png"
                    regions = {"all": ok}
                    if os.path.exists(mask_file):
                        regions["masks"] = ok & np.asarray(moma.read_mask(mask_file), dtype=bool)
                    for r, sel in regions.items():
                        pooled[r][0].append(dist[sel])
                        pooled[r][1].append(within[sel])
            for region, (ds, ws) in pooled.items():
                if not ds:
                    continue
                d, w = np.concatenate(ds), np.concatenate(ws)
                edges = [0.0, *np.quantile(d, BANDS), np.inf]
                cells = []
                for lo, hi in zip(edges[:-1], edges[1:]):
                    sel = (d >= lo) & (d < hi)
                    cells.append(f"{100 * w[sel].mean():.1f}" if sel.any() else "–")
                qs = "/".join(f"{q:.0f}" for q in edges[1:-1])
                print(f"| {name} | {method} | {region} ({qs} px) | {' | '.join(cells)} | {100 * w.mean():.1f} |")


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4) or (len(sys.argv) == 4 and sys.argv[3] != "--left-half"):
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2], left_half=len(sys.argv) == 4)
