#!/usr/bin/env python3
"""The PyTorch + peft side of the LoRA training-step comparison (issue 10): one training step of the
OFFICIAL Depth Anything V2 ViT-S (relative head, `vits-rel.safetensors` of ../shared/reference/dav2:
random weights, timing only) at 518x686, batch 1, peft LoRA r = 16 (alpha 16) on the q and v parts of
`attn.qkv`, the scale-and-shift-invariant loss in disparity exactly as the Rust `moma finetune` uses for
a relative head (crates/moma-depth/src/candle/train/loss.rs, `LossKind::Ssi`), gradient-norm clipping
to 1 (the Rust default), AdamW (betas 0.9/0.999, eps 1e-8, weight decay 0.01), 2 threads.

Usage: python benches/pytorch/bench_lora_step.py OFFICIAL_DIR [N] [REF_DIR]
  OFFICIAL_DIR  a checkout of github.com/DepthAnything/Depth-Anything-V2 (holds depth_anything_v2/);
                needs torch, peft, torchvision, opencv-python-headless, safetensors, numpy.
  N             timed steps after one warm-up step (default 5)
  REF_DIR       default ../shared/reference/dav2
Prints the per-step wall times, the median step time in seconds, the CPU seconds per step (user +
system of this process: less sensitive to other load on the machine than wall time), the peak RSS
(VmHWM) and the load average.

The matching Rust command (its `step_time_s` is the mean over all steps, the first included):
  target/release/moma finetune --set ../shared/data/gqcnn-primesense \\
      --weights ../shared/reference/dav2/vits-rel.safetensors --model vits --head relative \\
      --input-size 518 --steps 3 --val-frac 0 --lora-rank 16 --device cpu -o /tmp/x.safetensors --json
Both process a 3x518x686 network input (the 640x480 frames of gqcnn-primesense, shorter side to 518)
and train the same set: 24 LoRA pairs (12 blocks x q, v), r 16, nothing else. The input here is
`vits-rel.input.npy` and the ground truth a seeded synthetic depth map (the step's cost does not
depend on the values); the Rust run adds its data preparation (crop, flip, colour jitter: a few ms).
"""
import os
import re
import statistics
import sys
import time

OFFICIAL = os.path.abspath(sys.argv[1]) if len(sys.argv) > 1 else sys.exit(__doc__)
sys.path.insert(0, OFFICIAL)

import numpy as np  # noqa: E402
import peft  # noqa: E402
import torch  # noqa: E402
from safetensors.torch import load_file  # noqa: E402

from depth_anything_v2.dpt import DepthAnythingV2  # noqa: E402

from torch_common import lora_step, peak_rss_mib, split_qkv, ssi_loss  # noqa: E402  (this folder)

REF = sys.argv[3] if len(sys.argv) > 3 else os.path.join(
    os.path.dirname(os.path.abspath(__file__)), "..", "..", "..", "shared", "reference", "dav2")
THREADS = 2
RANK = 16
LR = 5e-4  # the Rust default peak learning rate (the schedule does not change the step's cost)
CLIP = 1.0  # the Rust default --clip-grad-norm
MIN_DEPTH_M = 0.001  # the Rust default --min-depth; relative heads: no upper bound


def check_ssi():
    """`ssi_loss` gives the hand-computed values of the Rust unit test
    `ssi_is_zero_for_an_affine_disparity_and_hand_computed_otherwise` (loss.rs)."""
    gt = torch.tensor([1.0, 2.0, 4.0, 0.5], dtype=torch.float64)
    all4 = torch.arange(4)
    assert abs(float(ssi_loss(3.0 / gt + 2.0, gt, all4))) < 1e-9
    got = float(ssi_loss(torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64),
                         torch.tensor([1.0, 1.0, 0.5], dtype=torch.float64), torch.arange(3)))
    assert abs(got - 2.0 / 9.0) < 1e-9, got


def main():
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 5
    check_ssi()
    torch.set_num_threads(THREADS)
    torch.manual_seed(0)
    model = DepthAnythingV2(encoder="vits", features=64, out_channels=[48, 96, 192, 384])
    sd = {k: v.float() for k, v in load_file(os.path.join(REF, "vits-rel.safetensors")).items()}
    model.load_state_dict(sd, strict=True)
    split_qkv(model.pretrained)
    cfg = peft.LoraConfig(r=RANK, lora_alpha=RANK, lora_dropout=0.0, bias="none",
                          target_modules=r"pretrained\.blocks\.\d+\.attn\.qkv\.(q|v)")
    model = peft.get_peft_model(model, cfg)
    model.train()
    params = [p for p in model.parameters() if p.requires_grad]
    names = [n for n, p in model.named_parameters() if p.requires_grad]
    assert len(params) == 12 * 2 * 2 and all(re.search(r"lora_[AB]", n) for n in names), names
    n_train = sum(p.numel() for p in params)
    opt = torch.optim.AdamW(params, lr=LR, betas=(0.9, 0.999), eps=1e-8, weight_decay=0.01)

    x = torch.from_numpy(np.load(os.path.join(REF, "vits-rel.input.npy")).astype(np.float32))[None]
    _, _, h, w = x.shape
    rng = np.random.default_rng(0)
    gt = torch.from_numpy((0.5 + 1.5 * rng.random((h, w))).astype(np.float32))
    valid = torch.nonzero((torch.isfinite(gt) & (gt >= MIN_DEPTH_M)).flatten()).squeeze(1)
    print(f"official DAv2 ViT-S relative head, input {tuple(x.shape)}, peft {peft.__version__} LoRA r {RANK} "
          f"on q,v: {len(params)} tensors, {n_train} trained parameters; torch {torch.__version__}, "
          f"threads {torch.get_num_threads()}")

    def step():
        return lora_step(model, params, opt, x, gt, valid, CLIP)

    t0 = time.perf_counter()
    loss = step()
    print(f"warm-up step: {time.perf_counter() - t0:.3f} s, loss {loss:.5f} (random weights: not meaningful)")
    times = []
    c0 = time.process_time()
    for _ in range(n):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    cpu = (time.process_time() - c0) / n
    print("per-step wall s: " + ", ".join(f"{t:.3f}" for t in times))
    print(f"pytorch+peft LoRA step, DAv2 vits {h}x{w}, r {RANK} q,v, ssi loss, AdamW, {THREADS} threads: "
          f"median {statistics.median(times):.3f} s/step, min {min(times):.3f}, max {max(times):.3f}, "
          f"cpu {cpu:.2f} CPU-s/step, "
          f"peak RSS {peak_rss_mib():.0f} MiB; load average {os.getloadavg()}")


if __name__ == "__main__":
    main()
