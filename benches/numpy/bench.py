#!/usr/bin/env python3
"""NumPy timings of the operations benchmarked in crates/moma-core/benches/core.rs (one core).

Run:  OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 python3 benches/numpy/bench.py
The thread variables are also set below, before NumPy is imported. Prints the median of each.
"""
import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import time  # noqa: E402

import numpy as np  # noqa: E402


def median_time(fn, min_time=1.0, min_runs=5):
    fn()  # warm-up
    times = []
    start = time.perf_counter()
    while len(times) < min_runs or time.perf_counter() - start < min_time:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def fmt(seconds):
    if seconds < 1e-3:
        return f"{seconds * 1e6:9.2f} µs"
    return f"{seconds * 1e3:9.3f} ms"


rng = np.random.default_rng(0)
results = []


def samples(n, w=640, h=480):
    u = rng.integers(0, w, n).astype(np.float64)
    v = rng.integers(0, h, n).astype(np.float64)
    p = rng.uniform(0.3, 1.5, n)
    z = p * (0.9 + 2e-4 * u - 1e-4 * v) + 0.1 + rng.uniform(-0.003, 0.003, n)
    return u, v, p, z


# --- fits: least squares as NumPy users write it -------------------------------------------
for n in (100, 3000):
    u, v, p, z = samples(n)

    def ssra_fit():
        x = np.stack([p * (u - u.mean()), p * (v - v.mean()), p, np.ones_like(p)], axis=1)
        return np.linalg.lstsq(x, z, rcond=None)[0]

    def gssa_fit():
        x = np.stack([p, np.ones_like(p)], axis=1)
        return np.linalg.lstsq(x, z, rcond=None)[0]

    results.append((f"fit/ssra/{n} (lstsq)", median_time(ssra_fit)))
    results.append((f"fit/gssa/{n} (lstsq)", median_time(gssa_fit)))

# --- apply: fused expression into a preallocated buffer ------------------------------------
for w, h in ((640, 480), (1280, 720)):
    zhat = (0.4 + ((np.arange(w)[None, :] * 7 + np.arange(h)[:, None] * 13) % 1000) * 1e-3).astype(np.float32)
    out = np.empty_like(zhat)
    a, b, g, t = np.float32(2e-4), np.float32(-1e-4), np.float32(0.9), np.float32(0.1)
    col = (a * np.arange(w, dtype=np.float32))[None, :]
    row = (b * np.arange(h, dtype=np.float32) + g)[:, None]

    def ssra_apply():
        np.add(col, row, out=out)
        np.multiply(out, zhat, out=out)
        np.add(out, t, out=out)

    def gssa_apply():
        np.multiply(zhat, a, out=out)
        np.add(out, t, out=out)

    results.append((f"apply/ssra/{w}x{h}", median_time(ssra_apply)))
    results.append((f"apply/gssa/{w}x{h}", median_time(gssa_apply)))

# --- exact LWLR maps 640x480, n = 100, b = 50 px, ridge 1 on the shift ---------------------
W, H, N, B, LAM = 640, 480, 100, 50.0, 1.0
u, v, p, z = samples(N)
uu = np.arange(W, dtype=np.float64)
vv = np.arange(H, dtype=np.float64)


def lwlr_dense():
    """Straightforward: per-pixel Gaussian weights to every sample (row chunks), weighted sums."""
    s = np.empty((H, W))
    t = np.empty((H, W))
    f = np.stack([np.ones_like(p), p, p * p, z, p * z], axis=1)  # n x 5
    for r0 in range(0, H, 32):
        r1 = min(H, r0 + 32)
        d2 = (uu[None, :, None] - u[None, None, :]) ** 2 + (vv[r0:r1, None, None] - v[None, None, :]) ** 2
        w = np.exp(-d2 / (2 * B * B))  # rows x W x n
        sums = w @ f  # rows x W x 5
        s0, s1, s2, s3, s4 = np.moveaxis(sums, -1, 0)
        det = s2 * (s0 + LAM) - s1 * s1
        a = (s4 * (s0 + LAM) - s1 * s3) / det
        s[r0:r1] = a
        t[r0:r1] = (s3 - a * s1) / (s0 + LAM)
    return s, t


def lwlr_separable():
    """Best NumPy: separable weights, the five sums as GEMMs (WV·diag(f_m))·WU."""
    wu = np.exp(-((uu[None, :] - u[:, None]) ** 2) / (2 * B * B))  # n x W
    wv = np.exp(-((vv[:, None] - v[None, :]) ** 2) / (2 * B * B))  # H x n
    f = [np.ones_like(p), p, p * p, z, p * z]
    s0, s1, s2, s3, s4 = [(wv * fm[None, :]) @ wu for fm in f]
    det = s2 * (s0 + LAM) - s1 * s1
    a = (s4 * (s0 + LAM) - s1 * s3) / det
    return a, (s3 - a * s1) / (s0 + LAM)


sa, ta = lwlr_dense()
sb, tb = lwlr_separable()
assert np.allclose(sa, sb) and np.allclose(ta, tb)
results.append(("lwlr_maps/exact_640x480_n100 (dense exp)", median_time(lwlr_dense, min_time=3.0, min_runs=3)))
results.append(("lwlr_maps/exact_640x480_n100 (separable GEMM)", median_time(lwlr_separable)))

# --- metrics 640x480 -------------------------------------------------------------------------
W, H = 640, 480
gi = np.arange(W)[None, :] * 3 + np.arange(H)[:, None]
gt = np.where((np.arange(W)[None, :] + np.arange(H)[:, None]) % 17 == 0, 0.0, 0.5 + (gi % 500) * 1e-3).astype(np.float32)
pred = (gt * 1.02 + 0.001).astype(np.float32)


def metrics():
    m = (gt > 0) & np.isfinite(gt) & np.isfinite(pred)
    p_, g_ = pred[m], gt[m]
    ratio = np.maximum(p_ / g_, g_ / p_)
    d = p_ - g_
    return (
        (ratio < 1.05).mean(),
        (ratio < 1.10).mean(),
        (ratio < 1.25).mean(),
        (np.abs(d) / g_).mean(),
        np.sqrt((d * d).mean()),
        np.abs(d).mean(),
        m.sum(),
    )


results.append(("metrics/640x480", median_time(metrics)))

print(f"NumPy {np.__version__}, one thread; medians")
for name, t in results:
    print(f"{name:50s} {fmt(t)}")
