#!/usr/bin/env python3
"""ONNX Runtime from Python, the side-by-side anchor for `moma-depth`'s ONNX backend.

Usage: target-ort/venv/bin/python benches/onnx/bench_ort.py ../shared/reference/dav2/vits-rel.onnx 10 [--no-spin]
(create the venv with `.ci/install-onnxruntime.sh --python`). Prints median wall time per frame, CPU-s and peak RSS.
"""
import sys, time, numpy as np, onnxruntime as ort
model = sys.argv[1]; runs = int(sys.argv[2]) if len(sys.argv) > 2 else 10
spin = "--no-spin" not in sys.argv
so = ort.SessionOptions()
so.intra_op_num_threads = 2
so.inter_op_num_threads = 1
so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
if not spin:
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
t = time.perf_counter()
s = ort.InferenceSession(model, so, providers=["CPUExecutionProvider"])
load = time.perf_counter() - t
x = np.load(model.replace(".onnx", ".input.npy"))[None].astype(np.float32)
t = time.perf_counter(); s.run(None, {"image": x}); warm = time.perf_counter() - t
ts = []
c0 = time.process_time()
for _ in range(runs):
    t = time.perf_counter(); s.run(None, {"image": x}); ts.append(time.perf_counter() - t)
cpu = (time.process_time() - c0) / runs
ts.sort()
hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM")][0].split()[1]
print(f"python onnxruntime {ort.__version__} spin={spin}: load {load:.3f} s, warm-up {warm:.3f} s, median {np.median(ts):.3f} s, min {ts[0]:.3f}, max {ts[-1]:.3f}, cpu {cpu:.3f} CPU-s/run, peak RSS {int(hwm)/1024:.1f} MiB")
