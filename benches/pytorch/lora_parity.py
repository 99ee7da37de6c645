#!/usr/bin/env python3
"""PyTorch + peft reference for the Rust LoRA training path (issue 10): loss, gradients and one AdamW
step of the OFFICIAL Depth Anything V2 metric network (`metric_depth/depth_anything_v2` of
github.com/DepthAnything/Depth-Anything-V2) in the tiny configuration of ../shared/reference/dav2
(random weights: this checks the machinery, not a depth model).

Usage: python benches/pytorch/lora_parity.py OFFICIAL_DIR [REF_DIR] [OUT]
  OFFICIAL_DIR  a checkout of Depth-Anything-V2 (holds metric_depth/depth_anything_v2 and
                metric_depth/util/loss.py); dpt.py imports cv2 and torchvision. Not vendored here.
  REF_DIR       default ../shared/reference/dav2
  OUT           default crates/moma-depth/tests/data/lora_parity_tiny_metric.safetensors

What it does:
  1. builds the tiny metric network with the official classes, loads tiny-metric.safetensors
     (strict) and reproduces tiny-metric.output_net.npy from tiny-metric.input.npy (asserted,
     < 1e-4 of the output range): it is the official network;
  2. replaces every block's fused `attn.qkv` Linear by `SplitQKV` (three Linear layers q, k, v
     holding the row slices of qkv; the forward concatenates: the same function, asserted) so that
     peft can put its LoRA on q and v; then `peft.LoraConfig(r, lora_alpha, target_modules,
     lora_dropout=0)` and `get_peft_model`;
  3. in float64, on a crop of the reference input with a seeded ground-truth depth map (some
     pixels zero, NaN or beyond max depth: invalid), sets seeded NON-ZERO lora_A (r x in) and
     lora_B (out x r) (scale alpha / r, as the Rust adapter), computes the official SiLogLoss
     (metric_depth/util/loss.py) over valid pixels (finite, min_depth <= gt <= max_depth),
     backward, and ONE torch.optim.AdamW step (betas 0.9/0.999, eps 1e-8, weight decay 0.01,
     fixed lr, no schedule: 1e-2 in case qv, 1e-3 (head 1e-2) in case all);
  4. writes OUT (< 300 kB; the loss in float64, the other values rounded to float32): the ground
     truth, A/B before, the loss, the gradients and A/B after, for two cases:
     `qv`  (r 4, alpha 6, targets q, v; the default recipe) and
     `all` (r 2, alpha 3, targets q, k, v, proj, fc1, fc2, and the DPT head trained fully with
            10x the learning rate, gradient-norm clipping as torch.nn.utils.clip_grad_norm_;
            gradients and updated values of a few head weights are stored).
The Rust test crates/moma-depth/tests/lora_parity.rs reads OUT. The pieces (import_official,
load_reference, check_official, training_sample, lora_model, train_whole_head, write_safetensors)
are importable: lora_parity_steps.py builds its multi-step reference from them.
"""
import json
import os
import re
import sys
from functools import partial
from types import SimpleNamespace

import numpy as np
import peft
import torch
from safetensors.torch import load_file, save_file

from torch_common import split_qkv  # this folder

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_REF = os.path.join(HERE, "..", "..", "..", "shared", "reference", "dav2")
DEFAULT_OUT = os.path.join(HERE, "..", "..", "crates", "moma-depth", "tests", "data",
                           "lora_parity_tiny_metric.safetensors")

# The official classes, set by import_official (the checkout is not vendored: its path is an argument).
OFFICIAL = None


def import_official(official_dir):
    """Puts `metric_depth` of the official checkout first on sys.path and imports the official
    classes and `SiLogLoss` (metric_depth/util/loss.py); returns them (also kept in OFFICIAL)."""
    global OFFICIAL
    sys.path.insert(0, os.path.join(os.path.abspath(official_dir), "metric_depth"))
    from depth_anything_v2.dpt import DepthAnythingV2, DPTHead
    from depth_anything_v2.dinov2 import DinoVisionTransformer
    from depth_anything_v2.dinov2_layers import MemEffAttention, NestedTensorBlock as Block
    from util.loss import SiLogLoss
    OFFICIAL = SimpleNamespace(DepthAnythingV2=DepthAnythingV2, DPTHead=DPTHead,
                               DinoVisionTransformer=DinoVisionTransformer,
                               MemEffAttention=MemEffAttention, Block=Block, SiLogLoss=SiLogLoss)
    return OFFICIAL


NAME = "tiny-metric"
# The crop of NAME.input.npy the training case uses (rows, cols; multiples of 14: a 9x12 patch
# grid, so the position embeddings are interpolated from the stored 37x37).
CROP = {"y0": 98, "x0": 140, "h": 126, "w": 168}
MIN_DEPTH_M = 0.001
SEED = 20261127
BETAS = (0.9, 0.999)
EPS = 1e-8
WEIGHT_DECAY = 0.01
HEAD_LR_MULT = 10.0
CASES = {
    # lr 1e-2 so that the weight decay's share of the update (lr * wd * w) is well above the tolerance.
    "qv": {"rank": 4, "alpha": 6.0, "targets": ["q", "v"], "train_head": False, "clip_grad_norm": 0.0,
           "lr": 1e-2},
    "all": {"rank": 2, "alpha": 3.0, "targets": ["q", "k", "v", "proj", "fc1", "fc2"], "train_head": True,
            "clip_grad_norm": None,  # None: set to half the measured global norm (so clipping acts)
            "lr": 1e-3},
}
# Head weights whose gradients and updated values are stored in case "all".
HEAD_KEYS = [
    "depth_head.projects.0.weight",
    "depth_head.resize_layers.0.weight",
    "depth_head.scratch.layer1_rn.weight",
    "depth_head.scratch.refinenet1.out_conv.weight",
    "depth_head.scratch.refinenet4.out_conv.bias",
    "depth_head.scratch.output_conv2.2.weight",
    "depth_head.scratch.output_conv2.2.bias",
]
# Rust target name -> the peft module path inside a block.
TARGET_PATH = {"q": "attn.qkv.q", "k": "attn.qkv.k", "v": "attn.qkv.v", "proj": "attn.proj",
               "fc1": "mlp.fc1", "fc2": "mlp.fc2"}


def tiny_model(cfg):
    """The official DepthAnythingV2 (metric) with the tiny DINOv2 of the reference README."""
    o = OFFICIAL
    assert o is not None, "call import_official(OFFICIAL_DIR) first"
    model = o.DepthAnythingV2(encoder="vits", features=cfg["features"], out_channels=cfg["out_channels"],
                            max_depth=cfg["max_depth"])
    # As DINOv2(model_name) in the official dinov2.py, with the tiny sizes.
    model.pretrained = o.DinoVisionTransformer(
        img_size=518, patch_size=14, embed_dim=cfg["embed_dim"], depth=cfg["depth"],
        num_heads=cfg["num_heads"], mlp_ratio=4, block_fn=partial(o.Block, attn_class=o.MemEffAttention),
        init_values=1.0, ffn_layer="mlp", block_chunks=0, num_register_tokens=0,
        interpolate_antialias=False, interpolate_offset=0.1)
    model.depth_head = o.DPTHead(cfg["embed_dim"], cfg["features"], False, out_channels=cfg["out_channels"],
                               use_clstoken=False)
    model.intermediate_layer_idx["tiny"] = cfg["intermediate_layers"]
    model.encoder = "tiny"
    return model


def load_base(cfg, sd):
    model = tiny_model(cfg)
    res = model.load_state_dict(sd, strict=True)
    assert not res.missing_keys and not res.unexpected_keys, res
    return model.eval()


def rel_to_range(got, want):
    err = float(np.abs(got.astype(np.float64) - want.astype(np.float64)).max())
    rng = float(want.max() - want.min())
    return err, rng, err / rng


def load_reference(ref_dir):
    """The tiny metric configuration, its state dict, the full reference input and output."""
    cfg_ref = json.load(open(os.path.join(ref_dir, f"{NAME}.json")))
    cfg = {"embed_dim": 64, "depth": 4, "num_heads": 2, "intermediate_layers": [0, 1, 2, 3], "features": 16,
           "out_channels": [8, 16, 32, 64], "max_depth": float(cfg_ref["max_depth"])}
    assert cfg_ref["head"] == "metric"
    sd = load_file(os.path.join(ref_dir, f"{NAME}.safetensors"))
    x_full = np.load(os.path.join(ref_dir, f"{NAME}.input.npy")).astype(np.float32)
    want = np.load(os.path.join(ref_dir, f"{NAME}.output_net.npy")).astype(np.float32)
    return cfg, sd, x_full, want


def check_official(cfg, sd, x_full, want):
    """Steps 1 and 2: the official network reproduces the reference output, and splitting qkv
    keeps the function (both asserted). Returns the reproduction errors."""
    model = load_base(cfg, sd)
    with torch.inference_mode():
        out = model(torch.from_numpy(x_full)[None]).squeeze(0).numpy()
    err, rng, rel = rel_to_range(out, want)
    print(f"[1] official network vs {NAME}.output_net.npy: max abs err {err:.3e}, range {rng:.4f}, "
          f"rel {rel:.3e} -> {'OK' if rel < 1e-4 else 'FAIL'}")
    assert rel < 1e-4, "not the official network"

    split_qkv(model.pretrained)
    with torch.inference_mode():
        out2 = model(torch.from_numpy(x_full)[None]).squeeze(0).numpy()
    err2, _, rel2 = rel_to_range(out2, out)
    print(f"[2] split qkv vs fused: max abs err {err2:.3e}, rel {rel2:.3e}")
    assert rel2 < 1e-6, "split qkv changed the output"
    return {"max_abs_err": err, "rel": rel}


def training_sample(x_full, max_depth_m):
    """The CROP of the reference input (float64, (1, 3, h, w)), the seeded ground truth (float32
    numpy (h, w): 5 % zeros, 2 % beyond max depth, 1 % NaN), as a float64 tensor (1, h, w), and
    its valid mask (finite, MIN_DEPTH_M <= gt <= max_depth_m)."""
    c = CROP
    x = torch.from_numpy(x_full[:, c["y0"]:c["y0"] + c["h"], c["x0"]:c["x0"] + c["w"]].copy())[None].double()
    rng_np = np.random.default_rng(SEED)
    h, w = c["h"], c["w"]
    yy, xx = np.mgrid[0:h, 0:w]
    gt = (2.0 + 6.0 * yy / h + 3.0 * np.sin(xx / 17.0) ** 2) * np.exp(rng_np.normal(0.0, 0.1, (h, w)))
    u = rng_np.random((h, w))
    gt[u < 0.05] = 0.0                       # no ground truth
    gt[(u >= 0.05) & (u < 0.07)] = 25.0      # beyond max depth 20 m
    gt[(u >= 0.07) & (u < 0.08)] = np.nan    # not finite
    gt = gt.astype(np.float32)
    gt_t = torch.from_numpy(gt).double()[None]
    valid = torch.isfinite(gt_t) & (gt_t >= MIN_DEPTH_M) & (gt_t <= max_depth_m)
    print(f"[3] crop {c}, ground truth {h}x{w}, valid pixels {int(valid.sum())} of {h * w}")
    return x, gt, gt_t, valid


def lora_model(cfg, sd, rank, alpha, targets, gen):
    """The official network with split qkv in float64 under peft LoRA (r, alpha, `targets` of
    TARGET_PATH, dropout 0), in train mode, with seeded NON-ZERO A (uniform, +-1/sqrt(in)) and B
    (uniform, +-0.2) drawn from `gen` in module order. Returns (peft model, {Rust name: parameter})."""
    base = load_base(cfg, sd)
    split_qkv(base.pretrained)
    base = base.double()
    paths = "|".join(re.escape(TARGET_PATH[t]) for t in targets)
    lcfg = peft.LoraConfig(r=rank, lora_alpha=alpha, lora_dropout=0.0, bias="none",
                           target_modules=rf"pretrained\.blocks\.\d+\.({paths})")
    pm = peft.get_peft_model(base, lcfg)
    pm.train()  # dropout is 0 everywhere (the official code has no dropout; LoRA dropout 0)
    lora = {}  # Rust name -> (peft parameter)
    for name, mod in pm.named_modules():
        if not isinstance(mod, peft.tuners.lora.LoraLayer):
            continue
        m = re.search(r"pretrained\.blocks\.(\d+)\.(.+)$", name)
        key = f"blocks.{m.group(1)}.{m.group(2)}"
        a, b = mod.lora_A["default"].weight, mod.lora_B["default"].weight  # (r, in), (out, r)
        assert mod.scaling["default"] == alpha / rank, mod.scaling
        with torch.no_grad():
            bound = 1.0 / np.sqrt(a.shape[1])
            a.copy_((torch.rand(a.shape, generator=gen, dtype=torch.float32) * 2 - 1) * bound)
            b.copy_((torch.rand(b.shape, generator=gen, dtype=torch.float32) * 2 - 1) * 0.2)
        lora[f"{key}.lora_A"] = a
        lora[f"{key}.lora_B"] = b
    expect = {f"blocks.{i}.{TARGET_PATH[t]}.lora_{ab}" for i in range(cfg["depth"]) for t in targets
              for ab in "AB"}
    assert set(lora) == expect, sorted(set(lora) ^ expect)
    return pm, lora


def train_whole_head(pm):
    """Makes every `depth_head.*` parameter trainable; returns {official name: parameter}."""
    head = {}
    for name, p in pm.named_parameters():
        k = name.removeprefix("base_model.model.")
        if k.startswith("depth_head."):
            p.requires_grad_(True)
            head[k] = p
    assert all(k in head for k in HEAD_KEYS)
    return head


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    import_official(sys.argv[1])
    ref_dir = sys.argv[2] if len(sys.argv) > 2 else DEFAULT_REF
    out_path = sys.argv[3] if len(sys.argv) > 3 else DEFAULT_OUT
    torch.manual_seed(SEED)
    cfg, sd, x_full, want = load_reference(ref_dir)

    # 1. The official network reproduces the reference output; 2. split qkv: the same function.
    repro = check_official(cfg, sd, x_full, want)

    # 3. Training cases in float64.
    max_depth_m = cfg["max_depth"]
    x, gt, gt_t, valid = training_sample(x_full, max_depth_m)
    criterion = OFFICIAL.SiLogLoss()

    tensors = {"gt_m": torch.from_numpy(gt)}
    meta = {
        "format": "moma-lora-parity-v1",
        "reference": NAME, "crop": json.dumps(CROP), "min_depth_m": repr(MIN_DEPTH_M),
        "max_depth_m": repr(max_depth_m), "head_lr_mult": repr(HEAD_LR_MULT),
        "weight_decay": repr(WEIGHT_DECAY), "eps": repr(EPS), "betas": json.dumps(BETAS),
        "dtype": "computed in float64; the loss stored as float64, every other tensor rounded to float32 "
                 "(relative rounding <= 6e-8, far below the test's tolerances) to keep the file small",
        "loss": "official SiLogLoss (lambda 0.5)",
        "torch": torch.__version__, "peft": peft.__version__, "official_reproduction": json.dumps(repro),
        "seed": str(SEED),
    }
    for case, s in CASES.items():
        gen = torch.Generator().manual_seed(SEED + len(case))
        pm, lora = lora_model(cfg, sd, s["rank"], s["alpha"], s["targets"], gen)
        head = train_whole_head(pm) if s["train_head"] else {}
        trainable = {n for n, p in pm.named_parameters() if p.requires_grad}
        assert len(trainable) == len(lora) + len(head), (len(trainable), len(lora), len(head))
        for k, p in lora.items():
            tensors[f"{case}/before/{k}"] = p.detach().float().clone()

        pred = pm(x)
        loss = criterion(pred, gt_t, valid)
        loss.backward()
        no_grad = sorted(k for k, p in head.items() if p.grad is None)  # unused: refinenet4's resConfUnit1
        print(f"    head tensors without a gradient (not used by the forward): {no_grad}")
        params = [p for p in list(lora.values()) + list(head.values()) if p.grad is not None]
        norm = float(torch.sqrt(sum((p.grad.double() ** 2).sum() for p in params)))
        clip = s["clip_grad_norm"]
        if clip is None:
            clip = float(f"{0.5 * norm:.3g}")
        # Stored before clipping: the Rust test compares the raw gradients.
        grads = {k: p.grad.detach().clone() for k, p in {**lora, **head}.items() if p.grad is not None}
        if clip > 0:
            total = torch.nn.utils.clip_grad_norm_(params, clip)
            assert abs(float(total) - norm) <= 1e-9 * norm
        lr = s["lr"]
        groups = [{"params": list(lora.values()), "lr": lr}]
        if head:
            groups.append({"params": list(head.values()), "lr": lr * HEAD_LR_MULT})
        opt = torch.optim.AdamW(groups, lr=lr, betas=BETAS, eps=EPS, weight_decay=WEIGHT_DECAY)
        opt.step()
        print(f"[3] case {case}: r {s['rank']} alpha {s['alpha']} targets {s['targets']} "
              f"train_head {s['train_head']} ({len(head)} head tensors): loss {loss.item():.12f}, "
              f"grad norm {norm:.6e}, clip {clip}")
        tensors[f"{case}/loss"] = loss.detach().reshape(1).clone()
        for k in lora:
            tensors[f"{case}/grad/{k}"] = grads[k].float()
            tensors[f"{case}/after/{k}"] = lora[k].detach().float()
        for k in HEAD_KEYS if head else []:
            tensors[f"{case}/grad/{k}"] = grads[k].float()
            tensors[f"{case}/after/{k}"] = head[k].detach().float()
        meta[f"{case}/settings"] = json.dumps({**s, "clip_grad_norm": clip, "grad_norm": norm,
                                               "head_without_grad": no_grad})

    write_safetensors(tensors, meta, out_path)


def write_safetensors(tensors, meta, out_path):
    """Writes atomically (a .tmp beside it, then os.replace), mode 644."""
    tensors = {k: v.contiguous() for k, v in tensors.items()}
    os.makedirs(os.path.dirname(os.path.abspath(out_path)), exist_ok=True)
    tmp = out_path + ".tmp"
    save_file(tensors, tmp, metadata=meta)
    os.chmod(tmp, 0o644)
    os.replace(tmp, out_path)
    print(f"wrote {out_path}: {len(tensors)} tensors, {os.path.getsize(out_path) / 1024:.0f} kB")


if __name__ == "__main__":
    main()
