"""Speed of `cal.align(pred)` on 640×480: Python (moma) vs the same Rust call vs NumPy.

    python benches/python/bench_align.py [--repeats 200] [--rust target/release/examples/align_timing]

Prints medians in milliseconds. The Rust number comes from the `align_timing` example of
crates/moma-py (build it with `cargo build --release -p moma-py --example align_timing`),
run in the same session on the same calibration file and prediction. The NumPy number is SSRA's
apply written in NumPy (float32, same normalisation: inverse depth → 1/d, min-max).

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


def numpy_ssra(pred, model):
    """z = ẑ(αu + βv + γ) + T3 with ẑ = min-max of 1/d (float32 throughout)."""
    with np.errstate(divide="ignore"):
        z = np.where(pred > 0, np.float32(1) / pred, np.float32(np.nan))
    if not np.isfinite(pred).all():
        raise ValueError("non-finite prediction")
    zmin, zmax = np.nanmin(z), np.nanmax(z)
    zhat = (z - zmin) / (zmax - zmin) + zmin
    h, w = pred.shape
    au = (model["alpha_m_per_px"] * np.arange(w)).astype(np.float32)[None, :]
    bv = (model["beta_m_per_px"] * np.arange(h) + model["gamma_m"]).astype(np.float32)[:, None]
    return zhat * (au + bv) + np.float32(model["t3_m"])


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
    cal = moma.calibrate(pred, gt, kind="inverse-depth", samples=100, seed=0)
    frame = (pred * 1.05).astype(np.float32)
    model = cal.report["model"]

    np.testing.assert_allclose(numpy_ssra(frame, model), cal.align(frame), rtol=1e-4, atol=1e-5)

    out = np.empty_like(frame)
    res = {
        "python_align_ms": median_ms(lambda: cal.align(frame), args.repeats),
        "python_align_into_ms": median_ms(lambda: cal.align_into(frame, out), args.repeats),
        "numpy_ssra_ms": median_ms(lambda: numpy_ssra(frame, model), args.repeats),
    }
    rust = pathlib.Path(args.rust)
    if rust.is_file():
        with tempfile.TemporaryDirectory() as d:
            cal.save(pathlib.Path(d) / "calib.json")
            np.save(pathlib.Path(d) / "frame.npy", frame)
            r = subprocess.run(
                [str(rust), str(pathlib.Path(d) / "calib.json"), str(pathlib.Path(d) / "frame.npy"),
                 str(args.repeats)], capture_output=True, text=True, check=True)
            res["rust_align_ms"] = json.loads(r.stdout)["median_ms"]
        res["python_over_rust"] = res["python_align_ms"] / res["rust_align_ms"]
    else:
        res["rust_align_ms"] = None
        print(f"(Rust timing skipped: {rust} not built)")
    res["numpy_over_python"] = res["numpy_ssra_ms"] / res["python_align_ms"]
    print(f"640x480 SSRA align, median of {args.repeats}:")
    for k, v in res.items():
        print(f"  {k:22s} {v:.3f}" if isinstance(v, float) else f"  {k:22s} {v}")


if __name__ == "__main__":
    main()
