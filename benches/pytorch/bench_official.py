#!/usr/bin/env python3
"""The same-machine anchor for `moma-depth`: the OFFICIAL Depth Anything V2 PyTorch code, ViT-S relative
head, on `vits-rel` of ../shared/reference/dav2 (random weights: timing only). First checks parity with
the reference output (must be < 1e-4 of the range, proving it is the official network), then times it.

Usage: python benches/pytorch/bench_official.py OFFICIAL_DIR [N] [REF_DIR]
  OFFICIAL_DIR  a checkout of github.com/DepthAnything/Depth-Anything-V2 (holds depth_anything_v2/);
                its dpt.py imports cv2 and torchvision, so install opencv-python-headless and
                torchvision beside torch (and safetensors). Not vendored here: it is not our code.
  N             timed runs after one warm-up (default 5)
  REF_DIR       default ../shared/reference/dav2
Prints one line: median/min/max wall seconds per frame, CPU-s per run, peak RSS (VmHWM).
"""
import os
import statistics
import sys
import time

OFFICIAL = os.path.abspath(sys.argv[1]) if len(sys.argv) > 1 else sys.exit(__doc__)
sys.path.insert(0, OFFICIAL)
if os.path.isdir(os.path.join(OFFICIAL, "pydeps")):  # optional `pip --target` folder for cv2/torchvision
    sys.path.append(os.path.join(OFFICIAL, "pydeps"))

import numpy as np
import torch
from safetensors.torch import load_file

from depth_anything_v2.dpt import DepthAnythingV2

from torch_common import peak_rss_mib  # this folder

REF = sys.argv[3] if len(sys.argv) > 3 else os.path.join(
    os.path.dirname(os.path.abspath(__file__)), "..", "..", "..", "shared", "reference", "dav2")
THREADS = 2


def main():
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 5
    torch.set_num_threads(THREADS)

    # model_configs['vits'] in the official run.py / app.py
    model = DepthAnythingV2(encoder="vits", features=64, out_channels=[48, 96, 192, 384])
    sd = load_file(os.path.join(REF, "vits-rel.safetensors"))
    res = model.load_state_dict(sd, strict=True)
    print(f"load_state_dict(strict=True): missing={list(res.missing_keys)} unexpected={list(res.unexpected_keys)}")
    print(f"state dict: {len(sd)} tensors, dtypes {sorted({str(v.dtype) for v in sd.values()})}")
    model.eval()

    x_np = np.load(os.path.join(REF, "vits-rel.input.npy")).astype(np.float32)
    ref = np.load(os.path.join(REF, "vits-rel.output_net.npy")).astype(np.float32)
    C, H, W = x_np.shape
    x = torch.from_numpy(x_np).unsqueeze(0).contiguous()
    print(f"input {tuple(x.shape)}, reference output {ref.shape}")

    with torch.inference_mode():
        # parity (this forward is also the warm-up run)
        t0 = time.perf_counter()
        out = model(x).squeeze().numpy()
        warm = time.perf_counter() - t0
        assert out.shape == ref.shape, (out.shape, ref.shape)
        err = float(np.abs(out.astype(np.float64) - ref.astype(np.float64)).max())
        rng = float(ref.max() - ref.min())
        rel = err / rng
        print(f"parity: max abs err {err:.3e}, max abs err / (max-min of ref = {rng:.6f}) = {rel:.3e}, "
              f"out min/max/mean {out.min():.6f}/{out.max():.6f}/{out.mean():.6f} "
              f"(ref {ref.min():.6f}/{ref.max():.6f}/{ref.mean():.6f}) -> {'OK' if rel < 1e-4 else 'FAIL'}")
        print(f"warm-up run: {warm:.3f} s")

        times = []
        c0 = time.process_time()
        for _ in range(n):
            t0 = time.perf_counter()
            model(x)
            times.append(time.perf_counter() - t0)
        cpu = (time.process_time() - c0) / n

    print("per-run wall s: " + ", ".join(f"{t:.3f}" for t in times))
    print(f"pytorch official DAv2 vits {H}x{W} torch {torch.__version__} threads {torch.get_num_threads()}: "
          f"median {statistics.median(times):.3f} s, min {min(times):.3f}, max {max(times):.3f}, "
          f"cpu {cpu:.3f} CPU-s/run, peak RSS {peak_rss_mib():.0f} MiB")
    if rel >= 1e-4:
        sys.exit(1)


if __name__ == "__main__":
    main()
