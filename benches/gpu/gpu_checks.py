#!/usr/bin/env python3
"""GPU checks of a CUDA build of `moma` against the OFFICIAL Depth Anything V2 PyTorch code on the same
GPU, in one run: parity (f32, f16, bf16), per-image latency, and the LoRA training step (time and peak
GPU memory) against PyTorch + peft.

Every network here has RANDOM weights (seeded; see `randomise`): the outputs predict nothing and only
the machinery is compared. Nothing of this is a depth-quality result.

Usage (on the GPU machine; see benches/gpu/README.md for the build and the driver script run.sh):
  python3 benches/gpu/gpu_checks.py --moma BIN --official DIR --ref DIR --scene DIR --out DIR
    BIN       `moma` built with `--features cuda`
    DIR       --official: a checkout of github.com/DepthAnything/Depth-Anything-V2 (depth_anything_v2/)
              --ref: ../shared/reference/dav2 (input.png and the tiny-* files are enough)
              --scene: a moma set (`moma demo` writes one to OUT/scene)
              --out: where gpu_checks.json and the temporary files go
Needs torch (CUDA), peft, numpy, opencv-python-headless and safetensors.
"""
import argparse
import glob
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "pytorch"))

# The official configurations (Depth-Anything-V2/run.py).
CONFIGS = {
    "vits": dict(encoder="vits", features=64, out_channels=[48, 96, 192, 384]),
    "vitb": dict(encoder="vitb", features=128, out_channels=[96, 192, 384, 768]),
    "vitl": dict(encoder="vitl", features=256, out_channels=[256, 512, 1024, 1024]),
}
# The tiny reference configurations of ../shared/reference/dav2 (README there).
TINY = {"embed_dim": 64, "depth": 4, "num_heads": 2, "intermediate_layers": [0, 1, 2, 3],
        "features": 16, "out_channels": [8, 16, 32, 64]}
RANK = 16
LR = 5e-4
CLIP = 1.0

RESULTS = {"label": "RANDOM weights: machinery only, not depth quality", "errors": []}


def log(*a):
    print(*a, flush=True)


def error(where, e):
    log(f"!! {where}: {e}")
    RESULTS["errors"].append(f"{where}: {e}")


def cuda_lib_path():
    """Folders holding the CUDA 13 libraries the `moma` binary links (cuBLAS, cuBLASLt, cuRAND,
    NVRTC, the runtime): the toolkit's or PyTorch's wheels'."""
    want = ["libcublasLt.so.13", "libcublas.so.13", "libcurand.so.10", "libnvrtc.so.13",
            "libcudart.so.13"]
    roots = ["/usr/local/cuda/lib64", "/usr/local/cuda/targets/x86_64-linux/lib", "/usr/lib/x86_64-linux-gnu"]
    import torch
    site = os.path.dirname(os.path.dirname(torch.__file__))
    roots += glob.glob(os.path.join(site, "nvidia", "*", "lib")) + glob.glob(os.path.join(site, "nvidia", "*", "*", "lib"))
    dirs = []
    for lib in want:
        hit = next((r for r in roots if os.path.exists(os.path.join(r, lib))), None)
        if hit is None:
            error("libraries", f"{lib} not found in {roots}")
        elif hit not in dirs:
            dirs.append(hit)
    return dirs


class GpuMemSampler:
    """Peak of nvidia-smi's memory.used over a run, minus the value before it (MiB): the same
    measure for both programs, whatever their allocators do."""

    def __init__(self):
        self.base = self.read()
        self.peak = self.base
        self.stop = threading.Event()
        self.t = threading.Thread(target=self.loop, daemon=True)

    @staticmethod
    def read():
        try:
            out = subprocess.run(["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits"],
                                 capture_output=True, text=True, timeout=10).stdout
            return float(out.split()[0])
        except Exception:  # noqa: BLE001  (a missing reading is reported as NaN)
            return float("nan")

    def loop(self):
        while not self.stop.wait(0.05):
            v = self.read()
            if v == v:
                self.peak = max(self.peak, v)

    def __enter__(self):
        self.t.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.t.join()

    @property
    def used_mib(self):
        return self.peak - self.base


def moma(args, env, timeout=240):
    t0 = time.perf_counter()
    p = subprocess.run([ARGS.moma] + args, capture_output=True, text=True, env=env, timeout=timeout)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise RuntimeError(f"moma {' '.join(args[:1])} exited {p.returncode}: {p.stderr.strip()[-1500:]}")
    return p.stdout, wall


def compare(got, ref):
    """max and mean |got − ref| as fractions of ref's range, and the fraction of non-finite values."""
    rng = float(np.nanmax(ref) - np.nanmin(ref))
    d = np.abs(got.astype(np.float64) - ref.astype(np.float64))
    return {"max_rel": float(np.nanmax(d) / rng), "mean_rel": float(np.nanmean(d) / rng),
            "nonfinite": float(np.mean(~np.isfinite(got))), "ref_range": rng}


def randomise(model, seed):
    """Seeded random weights that keep activations O(1) through ViT-S/B/L (the official init leaves
    ViT-L's relative head all zeros): weights N(0, 1/fan_in), norms 1 + N(0, 0.1), LayerScale 0.1,
    small biases, tokens N(0, 0.5), and a positive last bias so the final ReLU keeps most pixels."""
    import torch
    g = torch.Generator().manual_seed(seed)
    out = {}
    for k, v in model.state_dict().items():
        if not v.is_floating_point():
            out[k] = v
            continue
        def n(s):
            return torch.randn(v.shape, generator=g) * s
        if k.endswith("weight") and v.ndim >= 2:
            out[k] = n(1.0 / math.sqrt(v[0].numel()))
        elif k.endswith(("ls1.gamma", "ls2.gamma")):
            out[k] = 0.1 + n(0.02)
        elif "norm" in k and k.endswith("weight"):
            out[k] = 1.0 + n(0.1)
        elif k.endswith("bias"):
            out[k] = n(0.05)
        else:
            out[k] = n(0.5)
    out["depth_head.scratch.output_conv2.2.bias"] = torch.tensor([1.0])
    model.load_state_dict(out, strict=True)
    return {k: v.contiguous() for k, v in out.items()}


def section_env(env):
    import torch
    smi = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                         capture_output=True, text=True).stdout.strip()
    ver, _ = moma(["--version"], env)
    RESULTS["env"] = {"gpu": smi, "torch": torch.__version__, "cuda_torch": torch.version.cuda,
                      "moma": ver.strip(), "ld_library_path": env.get("LD_LIBRARY_PATH", "")}
    log("env:", json.dumps(RESULTS["env"]))


def section_tiny(env, tmp):
    """The committed reference outputs of the official code (tiny random models) vs moma on CUDA."""
    rows = []
    img = os.path.join(ARGS.ref, "input.png")
    for name, head, size in [("tiny-rel", "relative", 518), ("tiny-metric-392", "metric", 392)]:
        cfg = dict(TINY, head=head, max_depth=20 if head == "metric" else None)
        cfg = {k: v for k, v in cfg.items() if v is not None}
        cfg_path = os.path.join(tmp, f"{name}.json")
        with open(cfg_path, "w") as f:
            json.dump(cfg, f)
        ref = np.load(os.path.join(ARGS.ref, f"{name}.output_full.npy"))
        for dtype in ["f32", "f16", "bf16"]:
            out = os.path.join(tmp, f"tiny-{name}-{dtype}")
            try:
                moma(["predict", "--weights", os.path.join(ARGS.ref, f"{name}.safetensors"), "--model", cfg_path,
                      "--input-size", str(size), "--device", ARGS.device, "--dtype", dtype, img, "-o", out, "--json"], env)
                got = np.load(os.path.join(out, "input.npy"))
                row = dict(model=name, dtype=dtype, **compare(got, ref))
                rows.append(row)
                log("tiny:", json.dumps(row))
            except Exception as e:  # noqa: BLE001
                error(f"tiny {name} {dtype}", e)
    RESULTS["tiny_reference"] = rows


def official_model(enc, seed, device):
    import torch
    from depth_anything_v2.dpt import DepthAnythingV2
    m = DepthAnythingV2(**CONFIGS[enc])
    sd = randomise(m, seed)
    return m.to(device).eval(), sd


def torch_device():
    return "cuda" if ARGS.device.startswith("cuda") else "cpu"


def cuda_time(fn, n, warm=3):
    import torch
    def sync():
        if torch.cuda.is_available():
            torch.cuda.synchronize()
    for _ in range(warm):
        fn()
    sync()
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        sync()
        ts.append(time.perf_counter() - t0)
    return ts


def section_models(env, tmp, weights):
    """ViT-S/B/L with the same random weights: the official code on the GPU in f32 (TF32 off) is the
    reference; moma on CUDA in f32/f16/bf16; end-to-end latency of both (read image excluded,
    preprocessing, network, resize back and copy to the host included)."""
    import cv2
    import torch
    from safetensors.torch import save_file
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    img = os.path.join(ARGS.ref, "input.png")
    raw = cv2.imread(img)
    frames = []
    for i in range(ARGS.frames):
        p = os.path.join(tmp, f"f{i:02d}.png")
        if not os.path.exists(p):
            os.symlink(os.path.abspath(img), p)
        frames.append(p)
    rows = []
    for seed, enc in enumerate(ARGS.encoders, start=1):
        try:
            m, sd = official_model(enc, seed, torch_device())
            w = os.path.join(tmp, f"{enc}.safetensors")
            save_file(sd, w)
            weights[enc] = w
            ref = m.infer_image(raw, 518)
            e2e = cuda_time(lambda: m.infer_image(raw, 518), ARGS.frames)
            x = m.image2tensor(raw, 518)[0]
            with torch.no_grad():
                net = cuda_time(lambda: m(x), ARGS.frames)
                with torch.autocast(torch_device(), dtype=torch.float16):
                    net16 = cuda_time(lambda: m(x), ARGS.frames)
            row = {"model": enc, "official_f32_ms": 1e3 * statistics.median(e2e),
                   "official_f32_net_ms": 1e3 * statistics.median(net),
                   "official_autocast_f16_net_ms": 1e3 * statistics.median(net16),
                   "ref_stats": [float(ref.min()), float(ref.max()), float(ref.mean())]}
            del m
            torch.cuda.empty_cache()
            for dtype in ["f32", "f16", "bf16"]:
                out = os.path.join(tmp, f"{enc}-{dtype}")
                try:
                    stdout, wall = moma(["predict", "--weights", w, "--model", enc, "--head", "relative",
                                         "--device", ARGS.device, "--dtype", dtype, *frames, "-o", out, "--json"], env)
                    idx = json.loads(stdout)
                    ms = [f["predict_ms"] for f in idx["frames"]]
                    got = np.load(os.path.join(out, "f00.npy"))
                    row[dtype] = dict(compare(got, ref), moma_ms=statistics.median(ms[1:]),
                                      moma_first_ms=ms[0], process_wall_s=wall)
                except Exception as e:  # noqa: BLE001
                    error(f"models {enc} {dtype}", e)
            rows.append(row)
            log("model:", json.dumps(row))
        except Exception as e:  # noqa: BLE001
            error(f"models {enc}", e)
    RESULTS["models"] = rows


def torch_lora_step_time(enc, w, steps):
    """PyTorch + peft: the official network, LoRA r 16 on q and v (torch_common.split_qkv), SSI loss,
    gradient clipping 1, AdamW, batch 1 at 518x686, f32 (TF32 off) on the GPU."""
    import peft
    import torch
    from safetensors.torch import load_file
    from depth_anything_v2.dpt import DepthAnythingV2
    from torch_common import lora_step, split_qkv
    torch.manual_seed(0)
    model = DepthAnythingV2(**CONFIGS[enc])
    model.load_state_dict(load_file(w), strict=True)
    split_qkv(model.pretrained)
    cfg = peft.LoraConfig(r=RANK, lora_alpha=RANK, lora_dropout=0.0, bias="none",
                          target_modules=r"pretrained\.blocks\.\d+\.attn\.qkv\.(q|v)")
    model = peft.get_peft_model(model, cfg).to(torch_device())
    model.train()
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=LR, betas=(0.9, 0.999), eps=1e-8, weight_decay=0.01)
    g = torch.Generator().manual_seed(0)
    x = torch.randn((1, 3, 518, 686), generator=g).to(torch_device())
    gt = (0.5 + 1.5 * torch.rand((518, 686), generator=g)).to(torch_device())
    valid = torch.nonzero((gt >= 0.001).flatten()).squeeze(1)

    def step():
        return lora_step(model, params, opt, x, gt, valid, CLIP)

    if torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()
    with GpuMemSampler() as mem:
        ts = cuda_time(step, steps, warm=1)
    out = {"s_per_step": statistics.median(ts), "all_s": ts, "gpu_mem_mib": mem.used_mib,
           "torch_max_allocated_mib": torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else None,
           "trained_params": sum(p.numel() for p in params)}
    del model, opt
    torch.cuda.empty_cache()
    return out


def section_train(env, tmp, weights):
    rows = []
    for enc in ARGS.encoders:
        w = weights.get(enc)
        if w is None:
            error(f"train {enc}", "no weights (the models section failed)")
            continue
        row = {"model": enc}
        try:
            with GpuMemSampler() as mem:
                stdout, wall = moma(["finetune", "--set", ARGS.scene, "--weights", w, "--model", enc,
                                     "--head", "relative", "--input-size", "518", "--steps", str(ARGS.steps + 1),
                                     "--val-frac", "0", "--lora-rank", str(RANK), "--device", ARGS.device,
                                     "-o", os.path.join(tmp, f"{enc}-lora.safetensors"), "--json"], env, timeout=400)
            rep = json.loads(stdout)
            row["moma"] = {"s_per_step": rep.get("step_time_s"), "gpu_mem_mib": mem.used_mib,
                           "process_wall_s": wall, "report": {k: rep.get(k) for k in
                                                              ("steps", "train_loss_first", "train_loss_last",
                                                               "train_frames")}}
        except Exception as e:  # noqa: BLE001
            error(f"train moma {enc}", e)
        try:
            row["pytorch_peft"] = torch_lora_step_time(enc, w, ARGS.steps)
        except Exception as e:  # noqa: BLE001
            error(f"train pytorch {enc}", e)
        rows.append(row)
        log("train:", json.dumps(row))
    RESULTS["train"] = rows


def main():
    global ARGS
    ap = argparse.ArgumentParser()
    ap.add_argument("--moma", required=True)
    ap.add_argument("--official", required=True)
    ap.add_argument("--ref", required=True)
    ap.add_argument("--scene", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--encoders", default="vits,vitb,vitl")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--sections", default="env,tiny,models,train")
    ap.add_argument("--device", default="cuda", help="cpu: a dry run of the script on a machine without a GPU")
    ARGS = ap.parse_args()
    ARGS.encoders = ARGS.encoders.split(",")
    sys.path.insert(0, os.path.abspath(ARGS.official))
    env = dict(os.environ)
    env["LD_LIBRARY_PATH"] = ":".join(cuda_lib_path() + [env.get("LD_LIBRARY_PATH", "")])
    tmp = tempfile.mkdtemp(prefix="moma-gpu-")
    weights = {}
    sections = ARGS.sections.split(",")
    t0 = time.perf_counter()
    for name, fn in [("env", lambda: section_env(env)), ("tiny", lambda: section_tiny(env, tmp)),
                     ("models", lambda: section_models(env, tmp, weights)),
                     ("train", lambda: section_train(env, tmp, weights))]:
        if name in sections:
            s0 = time.perf_counter()
            try:
                fn()
            except Exception as e:  # noqa: BLE001
                error(name, e)
            log(f"== {name}: {time.perf_counter() - s0:.1f} s")
            with open(os.path.join(ARGS.out, "gpu_checks.json"), "w") as f:
                json.dump(RESULTS, f, indent=1)
    log(f"total {time.perf_counter() - t0:.1f} s; errors: {len(RESULTS['errors'])}")


if __name__ == "__main__":
    main()
