"""Robot loop with moma: calibrate once from arrays, then align every frame in memory (no files).

    python examples/robot_loop.py

The "camera" and "depth model" here are simulated (a synthetic tabletop and a made-up inverse
depth); in a robot stack, `grab()` returns the RGB-D frame and `predict()` is
`moma.DepthModel(weights).predict(rgb)`. Nothing printed here is a result of a real model.
"""

import time

import numpy as np

import moma

H, W = 480, 640
CAM = moma.Intrinsics(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=W, height=H)
rng = np.random.default_rng(0)


def grab(t):
    """Simulated sensor depth (metres) of a table tilted towards the camera, with a box on it."""
    v, u = np.mgrid[0:H, 0:W]
    depth = 0.9 + 0.0004 * (v - H / 2) + 0.0001 * (u - W / 2)
    box = (np.abs(u - 320 - 40 * np.sin(t)) < 60) & (np.abs(v - 260) < 50)
    depth[box] -= 0.12
    return depth.astype(np.float32)


def predict(depth_m):
    """Simulated relative model output: inverse depth with an unknown scale and offset."""
    return (3.0 / depth_m + 0.5 + 0.01 * rng.standard_normal(depth_m.shape)).astype(np.float32)


# 1. one calibration frame: prediction + sensor depth (0/NaN where the sensor has none)
gt_m = grab(0.0)
gt_m[rng.random(gt_m.shape) < 0.2] = 0.0
cal = moma.calibrate(predict(grab(0.0)), gt_m, CAM, kind="relative-disparity", samples=100, seed=0)
print(cal)
print({k: v for k, v in cal.report.items() if k != "model"})

# 2. the loop: align each new prediction into a reused buffer
out = np.empty((H, W), dtype=np.float32)
times = []
for i in range(20):
    truth = grab(0.3 * i)
    pred = predict(truth)
    t0 = time.perf_counter()
    cal.align_into(pred, out)
    times.append((time.perf_counter() - t0) * 1e3)
    if i % 5 == 0:
        m = moma.metrics(out, truth)
        pts = moma.depth_to_points(out, CAM)
        print(f"frame {i:2d}: MAE {m['mae'] * 1000:.1f} mm, delta<1.05 {m['d105']:.3f}, {len(pts)} points")
print(f"median align_into: {np.median(times):.2f} ms per {W}x{H} frame")
