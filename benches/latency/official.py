#!/usr/bin/env python3
"""The official Depth Anything V2 code on the CPU, the anchors of issue 26's latency table.

PyTorch f32 and int8 (`torch.ao.quantization.quantize_dynamic`: the ViT's and head's nn.Linear
layers with int8 weights, one scale per output channel, activations quantised per tensor at run
time) and ONNX Runtime f32 and int8 (an export of the same network at this input size, quantised
by `benches/onnx/quantize_int8.py`'s rule: its MatMul/Gemm nodes with a constant weight). All four
run side by side, alternating run by run, on the same input as `bench_candle` (its synthetic
pattern), with `--threads` threads each. RANDOM weights: timing, memory and precision only.

    python benches/latency/official.py --official DIR --weights W.safetensors --model vits \
        --height 518 --width 686 [--runs 3] [--backends torch-f32,torch-int8,ort-f32,ort-int8] \
        [--threads 2] [--onnx-dir DIR]

DIR: a checkout of github.com/DepthAnything/Depth-Anything-V2 (its depth_anything_v2/ package).
Needs torch, safetensors, onnx, onnxruntime (and onnxscript for torch's exporter). The ONNX
exports are cached in --onnx-dir (default: a temporary folder), one per model and size.
Prints each run, then one `median` line per backend (seconds; ratio to the first backend; max
and mean |difference| to the first backend's output over its range) and the peak RSS (`VmHWM`).
"""
import argparse
import os
import pathlib
import statistics
import sys
import tempfile
import time

import numpy as np

CONFIGS = {  # Depth-Anything-V2/run.py
    "vits": {"encoder": "vits", "features": 64, "out_channels": [48, 96, 192, 384]},
    "vitb": {"encoder": "vitb", "features": 128, "out_channels": [96, 192, 384, 768]},
    "vitl": {"encoder": "vitl", "features": 256, "out_channels": [256, 512, 1024, 1024]},
}


def peak_rss_mib():
    # not benches/pytorch/torch_common.peak_rss_mib: that module imports torch, and an ONNX
    # Runtime process here must not hold PyTorch when its memory is measured
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def bench_input(height, width):
    """bench_candle's pattern: ((c·7 + y·3 + x) mod 17) / 17 − 0.5, shape 1×3×H×W."""
    c, y, x = np.meshgrid(np.arange(3), np.arange(height), np.arange(width), indexing="ij")
    return (((c * 7 + y * 3 + x) % 17) / 17.0 - 0.5).astype(np.float32)[None]


def torch_model(args):
    import torch
    from safetensors.torch import load_file

    sys.path.insert(0, str(args.official))
    from depth_anything_v2.dpt import DepthAnythingV2

    model = DepthAnythingV2(**CONFIGS[args.model])
    state = {k: v.float() for k, v in load_file(str(args.weights)).items()}
    model.load_state_dict(state, strict=True)
    return model.eval()


def onnx_files(args, model, x, f32, int8):
    """Exports the network at this size to `f32` and quantises it to `int8`, unless they exist."""
    import torch

    here = pathlib.Path(__file__).resolve().parent
    sys.path.insert(0, str(here.parent / "onnx"))
    from quantize_int8 import quantize

    f32.parent.mkdir(parents=True, exist_ok=True)
    if not f32.exists():
        tmp = f32.with_suffix(".part.onnx")
        torch.onnx.export(model, torch.from_numpy(x), str(tmp), input_names=["image"],
                          output_names=["depth"], opset_version=17, dynamo=False)
        os.replace(tmp, f32)
    if not int8.exists():
        quantize(f32, int8, ops=["MatMul", "Gemm"], all_matmuls=False)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--official", type=pathlib.Path, required=True)
    ap.add_argument("--weights", type=pathlib.Path, required=True)
    ap.add_argument("--model", choices=sorted(CONFIGS), default="vits")
    ap.add_argument("--height", type=int, default=518)
    ap.add_argument("--width", type=int, default=686)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--backends", default="torch-f32,torch-int8,ort-f32,ort-int8")
    ap.add_argument("--onnx-dir", default=None)
    args = ap.parse_args()
    if args.height % 14 or args.width % 14:
        ap.error("--height and --width must be multiples of 14 (the ViT's patch size)")
    backends = args.backends.split(",")
    unknown = set(backends) - {"torch-f32", "torch-int8", "ort-f32", "ort-int8"}
    if unknown:
        ap.error(f"unknown backends: {sorted(unknown)}")

    x = bench_input(args.height, args.width)
    if args.onnx_dir is None:
        tmp = tempfile.TemporaryDirectory()
        args.onnx_dir = tmp.name
    f32 = pathlib.Path(args.onnx_dir) / f"{args.model}-{args.height}x{args.width}.onnx"
    int8 = f32.with_suffix(".int8.onnx")
    runners = {}
    # PyTorch only where a torch backend runs or an export is missing: an ONNX Runtime process
    # then measures ONNX Runtime's own memory.
    use_torch = any(b.startswith("torch-") for b in backends) or not (f32.exists() and int8.exists())
    if use_torch:
        import torch

        torch.set_num_threads(args.threads)
        torch.set_num_interop_threads(1)
        torch.set_grad_enabled(False)
        model = torch_model(args)
        print(f"torch {torch.__version__} ({torch.backends.cpu.get_cpu_capability()})")
        if "torch-f32" in backends:
            runners["torch-f32"] = lambda: model(torch.from_numpy(x))[0].numpy()
        if "torch-int8" in backends:
            q = torch.ao.quantization.quantize_dynamic(model, {torch.nn.Linear}, dtype=torch.qint8)
            runners["torch-int8"] = lambda: q(torch.from_numpy(x))[0].numpy()
        if any(b.startswith("ort-") for b in backends):
            onnx_files(args, model, x, f32, int8)
    if any(b.startswith("ort-") for b in backends):
        import onnxruntime as ort

        so = ort.SessionOptions()
        so.intra_op_num_threads = args.threads
        so.inter_op_num_threads = 1
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        for name, path in (("ort-f32", f32), ("ort-int8", int8)):
            if name in backends:
                s = ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
                runners[name] = (lambda s=s: s.run(None, {"image": x})[0][0])
        print(f"onnxruntime {ort.__version__}: {f32.name} ({f32.stat().st_size / 1e6:.1f} MB), "
              f"{int8.name} ({int8.stat().st_size / 1e6:.1f} MB)")
    order = [b for b in backends if b in runners]
    times = {b: [] for b in order}
    outs = {}
    print(f"{args.threads} threads, {args.model} {args.height}x{args.width}, RANDOM weights")
    for i in range(args.runs + 1):
        for b in order:
            t = time.perf_counter()
            outs[b] = np.asarray(runners[b](), dtype=np.float32)
            s = time.perf_counter() - t
            print(f"run {i} {b}{' (warm-up)' if i == 0 else ''}: {s:.3f} s")
            if i > 0:
                times[b].append(s)
    anchor_t = statistics.median(times[order[0]])
    ref = outs[order[0]]
    rng = float(ref.max() - ref.min()) or 1.0
    for b in order:
        m = statistics.median(times[b])
        d = np.abs(outs[b] - ref)
        print(f"{args.model} {args.height}x{args.width} {b}: median {m:.3f} s "
              f"({m / anchor_t:.2f}x the {order[0]} time); vs {order[0]}: max {d.max() / rng:.2e}, "
              f"mean {d.mean() / rng:.2e} of its range")
    print(f"peak RSS {peak_rss_mib():.0f} MiB")


if __name__ == "__main__":
    main()
