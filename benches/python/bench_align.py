"""Speed of `cal.align(pred)` on 640×480: Python (moma) vs the same Rust call vs NumPy, for SSRA
and GSSA in depth and inverse space.

    python benches/python/bench_align.py [--repeats 200] [--rust target/release/examples/align_timing]

Prints medians in milliseconds. The Rust number comes from the `align_timing` example of
crates/moma-py (build it with `cargo build --release -p moma-py --example align_timing`),
run in the same session on the same calibration file and prediction. The NumPy number is the
same step written in NumPy (float32: normalisation, model, reciprocal in inverse space).

Run it with glibc's malloc thresholds pinned, so that the Python process (whose NumPy allocations
raise glibc's dynamic mmap threshold) and the Rust process allocate the 1.2 MB output the same way:

    MALLOC_MMAP_THRESHOLD_=67108864 MALLOC_TRIM_THRESHOLD_=134217728 python benches/python/bench_align.py

Without it, the stand-alone Rust process mmaps every fresh output buffer and pays ~1 ms of page
faults per call (1.5 ms instead of 0.5 ms at 640×480), which would flatter the Python number.
"""

import argparse
import json
import pathlib
import statistics
import subprocess
import tempfile
import time

import numpy as np

import moma

REPO = pathlib.Path(__file__).resolve().parents[2]


def median_ms(fn, repeats):
    for _ in range(5):
        fn()
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        t.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(t)


def numpy_align(pred, model, space):
    """The whole step in NumPy (float32 throughout), for a relative-disparity prediction:
    min-max normalisation in `space` (depth: z = 1/d, NaN for d ≤ 0; inverse: z = d), the model
    (SSRA ẑ(αu + βv + γ) + T3, or GSSA s·ẑ + t), and in inverse space the reciprocal of the
    fitted disparity (NaN where ≤ 0)."""
    if not np.isfinite(pred).all():
        raise ValueError("non-finite prediction")
    if space == "depth":
        with np.errstate(divide="ignore"):
            z = np.where(pred > 0, np.float32(1) / pred, np.float32(np.nan))
        zmin, zmax = np.nanmin(z), np.nanmax(z)
    else:
        z = pred
        zmin, zmax = z.min(), z.max()
    zhat = (z - zmin) / (zmax - zmin) + zmin
    if model["method"] == "ssra":
        h, w = pred.shape
        au = (model["alpha_m_per_px"] * np.arange(w)).astype(np.float32)[None, :]
        bv = (model["beta_m_per_px"] * np.arange(h) + model["gamma_m"]).astype(np.float32)[:, None]
        y = zhat * (au + bv) + np.float32(model["t3_m"])
    else:
        y = zhat * np.float32(model["scale"]) + np.float32(model["shift_m"])
    if space == "inverse":
        with np.errstate(divide="ignore", invalid="ignore"):
            y = np.where(y > 0, np.float32(1) / y, np.float32(np.nan))
    return y


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--rust", default=str(REPO / "target" / "release" / "examples" / "align_timing"))
    args = ap.parse_args()

    rng = np.random.default_rng(0)
    h, w = 480, 640
    yy, xx = np.mgrid[0:h, 0:w]
    pred = (1.0 + 0.5 * np.sin(xx / 40) * np.cos(yy / 50) + 0.2 * rng.random((h, w))).astype(np.float32)
    gt = (1.0 / pred * 0.8 + 0.1).astype(np.float32)
    frame = (pred * 1.05).astype(np.float32)
    out = np.empty_like(frame)
    rust = pathlib.Path(args.rust)
    if not rust.is_file():
        print(f"(Rust timing skipped: {rust} not built)")
    rows = []
    for method in ["ssra", "gssa"]:
        for space in ["depth", "inverse"]:
            cal = moma.calibrate(pred, gt, kind="relative-disparity", method=method, space=space,
                                 samples=100, seed=0)
            model = cal.report["model"]
            np.testing.assert_allclose(numpy_align(frame, model, space), cal.align(frame),
                                       rtol=1e-4, atol=1e-5)
            r = {
                "method": method,
                "space": space,
                "python_ms": median_ms(lambda: cal.align(frame), args.repeats),
                "python_into_ms": median_ms(lambda: cal.align_into(frame, out), args.repeats),
                "numpy_ms": median_ms(lambda: numpy_align(frame, model, space), args.repeats),
                "rust_ms": None,
            }
            if rust.is_file():
                with tempfile.TemporaryDirectory() as d:
                    cal.save(pathlib.Path(d) / "calib.json")
                    np.save(pathlib.Path(d) / "frame.npy", frame)
                    p = subprocess.run(
                        [str(rust), str(pathlib.Path(d) / "calib.json"),
                         str(pathlib.Path(d) / "frame.npy"), str(args.repeats)],
                        capture_output=True, text=True, check=True)
                    r["rust_ms"] = json.loads(p.stdout)["median_ms"]
            rows.append(r)
    print(f"640x480 cal.align, relative-disparity prediction, min-max, median of {args.repeats} (ms):")
    print(f"{'method':6s} {'space':7s} {'python':>7s} {'py_into':>7s} {'rust':>7s} {'numpy':>7s}"
          f" {'py/rust':>7s} {'numpy/py':>8s}")
    for r in rows:
        rust_ms = r["rust_ms"]
        ratio = f"{r['python_ms'] / rust_ms:7.2f}" if rust_ms else f"{'-':>7s}"
        rust_s = f"{rust_ms:7.3f}" if rust_ms else f"{'-':>7s}"
        print(f"{r['method']:6s} {r['space']:7s} {r['python_ms']:7.3f} {r['python_into_ms']:7.3f}"
              f" {rust_s} {r['numpy_ms']:7.3f} {ratio} {r['numpy_ms'] / r['python_ms']:8.2f}")
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
