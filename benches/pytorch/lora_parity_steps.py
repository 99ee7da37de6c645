#!/usr/bin/env python3
"""PyTorch + peft reference for MULTI-STEP AdamW parity of the Rust LoRA trainer (issue 23, item 3):
six optimiser steps of the OFFICIAL Depth Anything V2 metric network (tiny configuration of
../shared/reference/dav2, random weights: this checks the machinery, not a depth model) with LoRA on
all six targets, the whole DPT head trained, weight decay, a warm-up + poly learning-rate schedule
and gradient-norm clipping that acts on several steps, in float64.

Usage: python benches/pytorch/lora_parity_steps.py OFFICIAL_DIR [REF_DIR] [OUT]
  OFFICIAL_DIR  a checkout of Depth-Anything-V2 (metric_depth/depth_anything_v2 and
                metric_depth/util/loss.py); dpt.py imports cv2 and torchvision. Not vendored here.
  REF_DIR       default ../shared/reference/dav2
  OUT           default crates/moma-depth/tests/data/lora_parity_steps_tiny_metric.safetensors

What it does (the shared pieces come from lora_parity.py, so network, crop and ground truth are
those of the one-step reference):
  1. builds the tiny metric network with the official classes, reproduces
     tiny-metric.output_net.npy (asserted), splits qkv (asserted unchanged), converts to float64;
  2. peft LoRA r 2, alpha 3 on q, k, v, proj, fc1, fc2 (dropout 0) with seeded NON-ZERO A and B
     (generator seed SEED + 100), and every `depth_head.*` tensor trainable;
  3. the CROP of tiny-metric.input.npy and the seeded ground truth of lora_parity.py (zeros, NaN and
     beyond-max-depth pixels invalid), the official SiLogLoss over valid pixels;
  4. STEPS = 6 steps on that single sample (batch 1, no accumulation): loss, backward,
     torch.nn.utils.clip_grad_norm_(parameters with a gradient, CLIP), torch.optim.AdamW with two
     groups (LoRA lr 1e-3, head HEAD_LR_MULT x: 2, see there why not 10; betas 0.9/0.999, eps 1e-8,
     weight decay 0.01), then a LambdaLR step whose factor is the Rust
     `lr_factor(Schedule::Poly, step, STEPS, WARMUP)` (warm-up 2).
     CLIP is CLIP_OF_FIRST_NORM x the first step's global gradient norm, rounded to 3 significant
     digits; the clip factor CLIP / (norm + 1e-6) is asserted < 1 on at least two steps.
     Head tensors without a gradient (refinenet4's resConfUnit1: unused by the forward) are not
     touched by AdamW (no weight decay either); they are listed in the metadata;
  5. writes OUT (float64 scalars of shape (1,): `loss/{k}` before step k's update, `grad_norm/{k}`
     before clipping, `lr_factor/{k}`; float32 tensors: `gt_m`, `before/{lora name}`,
     `after/{k}/{name}` for every trained tensor after step k, k = 1..6; LoRA names as the Rust
     adapter `blocks.{i}.{attn.qkv.q|...|mlp.fc2}.lora_{A|B}`, head names as the official
     `depth_head....`), and `final_loss` (the loss after the last update, float64).
"""
import json
import os
import sys

import lora_parity as lp  # this folder
import peft
import torch

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT = os.path.join(HERE, "..", "..", "crates", "moma-depth", "tests", "data",
                           "lora_parity_steps_tiny_metric.safetensors")
FORMAT = "moma-lora-parity-steps-v1"
RANK = 2
ALPHA = 3.0
TARGETS = ["q", "k", "v", "proj", "fc1", "fc2"]
LR = 1e-3
# Head learning rate = HEAD_LR_MULT x LR. Not the trainer's default 10 (lora_parity.py's one step):
# with a head lr of 1e-2 this random-weight network's output sigmoid saturates by step 3 (logits up
# to 2.6e3: the prediction is max_depth everywhere, the gradients vanish, exactly 0 at step 6, and
# the loss stays flat), which would leave steps 3-6 checking nothing but momentum decay. With 2 the
# loss goes 0.54, 0.87, 0.57, 0.37, 0.40, 0.29 over the six steps; dropping the weight decay, the
# clipping or the schedule, or swapping the two groups' learning rates, moves the stored tensors by
# >= 5.7e-3 (relative, max-abs; the LoRA ones alone by >= 9e-4), far above the 1e-5 tolerance,
# while a relative error of 1e-5 in every gradient moves them by <= 7.2e-6 (measured).
HEAD_LR_MULT = 2.0
STEPS = 6
WARMUP = 2
SCHEDULE = "poly"
# CLIP = this x the first step's global gradient norm (3 significant digits).
CLIP_OF_FIRST_NORM = 0.6
LORA_SEED = lp.SEED + 100
# torch.nn.utils.clip_grad_norm_ (and the Rust clip_grad_norm): factor max_norm / (norm + 1e-6).
CLIP_EPS = 1e-6
# Files above this are trimmed (head tensors after every step only for HEAD_KEYS).
MAX_BYTES = 4 * 1024 * 1024


def lr_factor(step, total=STEPS, warmup=WARMUP):
    """The Rust `lr_factor(Schedule::Poly, step, total, warmup)` (step 0-based)."""
    if step < warmup:
        return (step + 1) / warmup
    span = float(max(total - warmup, 1))  # total.saturating_sub(warmup).max(1)
    t = min(max((step - warmup) / span, 0.0), 1.0)
    return (1.0 - t) ** 0.9


def scalar(v):
    return torch.tensor([v], dtype=torch.float64)


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    lp.import_official(sys.argv[1])
    ref_dir = sys.argv[2] if len(sys.argv) > 2 else lp.DEFAULT_REF
    out_path = sys.argv[3] if len(sys.argv) > 3 else DEFAULT_OUT
    torch.manual_seed(lp.SEED)
    cfg, sd, x_full, want = lp.load_reference(ref_dir)
    repro = lp.check_official(cfg, sd, x_full, want)
    max_depth_m = cfg["max_depth"]
    x, gt, gt_t, valid = lp.training_sample(x_full, max_depth_m)
    criterion = lp.OFFICIAL.SiLogLoss()

    gen = torch.Generator().manual_seed(LORA_SEED)
    pm, lora = lp.lora_model(cfg, sd, RANK, ALPHA, TARGETS, gen)
    head = lp.train_whole_head(pm)
    trainable = {n for n, p in pm.named_parameters() if p.requires_grad}
    assert len(trainable) == len(lora) + len(head), (len(trainable), len(lora), len(head))
    assert all(p.dtype == torch.float64 for p in list(lora.values()) + list(head.values()))
    print(f"[4] LoRA r {RANK} alpha {ALPHA} on {TARGETS}: {len(lora)} matrices; head: {len(head)} tensors "
          f"({sum(p.numel() for p in head.values())} values)")

    tensors = {"gt_m": torch.from_numpy(gt)}
    initial = {n: p.detach().float().clone() for n, p in {**lora, **head}.items()}
    for k, p in lora.items():
        tensors[f"before/{k}"] = p.detach().float().clone()

    head_lr = LR * HEAD_LR_MULT
    groups = [{"params": list(lora.values()), "lr": LR}, {"params": list(head.values()), "lr": head_lr}]
    opt = torch.optim.AdamW(groups, lr=LR, betas=lp.BETAS, eps=lp.EPS, weight_decay=lp.WEIGHT_DECAY)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_lambda=lr_factor)

    clip = None
    no_grad = None
    rows = []
    after = []  # per step: {name: float32 tensor}
    for k in range(1, STEPS + 1):
        opt.zero_grad(set_to_none=True)
        loss = criterion(pm(x), gt_t, valid)
        loss.backward()
        step_no_grad = sorted(n for n, p in head.items() if p.grad is None)
        assert all(p.grad is not None for p in lora.values())
        if no_grad is None:
            no_grad = step_no_grad
            print(f"    head tensors without a gradient (not used by the forward): {no_grad}")
        assert step_no_grad == no_grad
        params = [p for p in list(lora.values()) + list(head.values()) if p.grad is not None]
        norm = float(torch.sqrt(sum((p.grad.double() ** 2).sum() for p in params)))
        if clip is None:
            clip = float(f"{CLIP_OF_FIRST_NORM * norm:.3g}")
        factor = clip / (norm + CLIP_EPS)
        total = torch.nn.utils.clip_grad_norm_(params, clip)
        assert abs(float(total) - norm) <= 1e-9 * norm, (float(total), norm)
        f = lr_factor(k - 1)
        assert abs(opt.param_groups[0]["lr"] - LR * f) <= 1e-15 and \
            abs(opt.param_groups[1]["lr"] - head_lr * f) <= 1e-14, [g["lr"] for g in opt.param_groups]
        opt.step()
        sched.step()
        rows.append({"step": k, "loss": loss.item(), "grad_norm": norm, "clip_factor": factor,
                     "clipped": factor < 1.0, "lr_factor": f})
        tensors[f"loss/{k}"] = loss.detach().reshape(1).clone()
        tensors[f"grad_norm/{k}"] = scalar(norm)
        tensors[f"lr_factor/{k}"] = scalar(f)
        after.append({n: p.detach().float().clone() for n, p in {**lora, **head}.items()})
    with torch.no_grad():
        final_loss = criterion(pm(x), gt_t, valid).item()
    tensors["final_loss"] = scalar(final_loss)

    clipped = sum(r["clipped"] for r in rows)
    print(f"[5] {STEPS} AdamW steps, clip {clip} ({CLIP_OF_FIRST_NORM} x the first norm), "
          f"lr {LR} (head {head_lr}), warm-up {WARMUP}, {SCHEDULE}")
    print(f"    {'step':>4} {'loss (before update)':>22} {'grad norm':>14} {'clip factor':>12} "
          f"{'lr factor':>10}")
    for r in rows:
        print(f"    {r['step']:>4} {r['loss']:>22.15f} {r['grad_norm']:>14.8e} {r['clip_factor']:>12.6f} "
              f"{r['lr_factor']:>10.6f}{'  clipped' if r['clipped'] else ''}")
    print(f"    loss after step {STEPS}: {final_loss:.15f}")
    assert clipped >= 2, f"clipping acts on {clipped} step(s) only"
    # Every trained tensor with a gradient moved on every step; those without did not.
    for k in range(STEPS):
        for n in after[k]:
            old = after[k - 1][n] if k else initial[n]
            assert torch.equal(after[k][n], old) == (n in no_grad), (k + 1, n)

    # Every trained tensor after every step, unless the file would be too large.
    per_step = sum(t.numel() * 4 for t in after[0].values())
    head_every_step = "all"
    head_names = list(head)
    if per_step * STEPS > MAX_BYTES:
        head_every_step = "HEAD_KEYS"
    for k, vals in enumerate(after, start=1):
        for n, t in vals.items():
            if n in lora or head_every_step == "all" or n in lp.HEAD_KEYS or k == STEPS:
                tensors[f"after/{k}/{n}"] = t

    settings = {"rank": RANK, "alpha": ALPHA, "targets": TARGETS, "train_head": True, "lr": LR,
                "head_lr_mult": HEAD_LR_MULT, "weight_decay": lp.WEIGHT_DECAY, "betas": list(lp.BETAS),
                "eps": lp.EPS, "clip_grad_norm": clip, "steps": STEPS, "warmup": WARMUP, "schedule": SCHEDULE,
                "accumulate": 1, "batch": 1, "min_depth_m": lp.MIN_DEPTH_M, "max_depth_m": max_depth_m}
    meta = {
        "format": FORMAT,
        "reference": lp.NAME, "crop": json.dumps(lp.CROP),
        "settings": json.dumps(settings),
        "rank": str(RANK), "alpha": repr(ALPHA), "targets": json.dumps(TARGETS), "train_head": "true",
        "lr": repr(LR), "head_lr_mult": repr(HEAD_LR_MULT), "weight_decay": repr(lp.WEIGHT_DECAY),
        "betas": json.dumps(lp.BETAS), "eps": repr(lp.EPS),
        "clip_grad_norm": repr(clip),
        "clip_rule": f"{CLIP_OF_FIRST_NORM} x the first step's global gradient norm, 3 significant digits; "
                     f"factor clip / (norm + {CLIP_EPS}) applied when < 1 (torch clip_grad_norm_)",
        "clip_factors": json.dumps([r["clip_factor"] for r in rows]),
        "clipped_steps": json.dumps([r["step"] for r in rows if r["clipped"]]),
        "grad_norms": json.dumps([r["grad_norm"] for r in rows]),
        "lr_factors": json.dumps([r["lr_factor"] for r in rows]),
        "losses": json.dumps([r["loss"] for r in rows]),
        "steps": str(STEPS), "warmup": str(WARMUP), "schedule": SCHEDULE,
        "lr_schedule": "torch LambdaLR, factor of 0-based step s = (s + 1) / warmup for s < warmup, else "
                       "(1 - t)^0.9, t = clamp((s - warmup) / max(steps - warmup, 1), 0, 1): the Rust "
                       "lr_factor(Schedule::Poly, s, steps, warmup); step k (1-based) uses s = k - 1",
        "min_depth_m": repr(lp.MIN_DEPTH_M), "max_depth_m": repr(max_depth_m),
        "seed": str(lp.SEED), "lora_init_seed": str(LORA_SEED),
        "lora_init": "A uniform +-1/sqrt(in), B uniform +-0.2, drawn in float32 from torch.Generator"
                     "(lora_init_seed) in module order (lora_parity.py lora_model)",
        "head_without_grad": json.dumps(no_grad),
        "head_without_grad_note": "unused by the forward: no gradient, so AdamW leaves them unchanged "
                                  "(no weight decay either); stored after every step all the same",
        "head_after_every_step": head_every_step,
        "head_tensors": json.dumps(head_names),
        "keys": "loss/{k}: loss before step k's update; grad_norm/{k}: global L2 norm before clipping; "
                "lr_factor/{k}; after/{k}/{name}: value after step k (k = 1.." + str(STEPS) + "); "
                "before/{lora name}: initial A and B; gt_m; final_loss: loss after the last update",
        "dtype": "computed in float64; loss, grad_norm, lr_factor and final_loss stored as float64 "
                 "(shape (1,)), every other tensor rounded to float32",
        "loss": "official SiLogLoss (lambda 0.5), valid: finite, min_depth_m <= gt <= max_depth_m",
        "optimizer": "torch.optim.AdamW, groups: LoRA (lr), head (lr x head_lr_mult); "
                     "zero_grad, loss, backward, clip_grad_norm_, step, scheduler.step",
        "torch": torch.__version__, "peft": peft.__version__, "official_reproduction": json.dumps(repro),
    }
    lp.write_safetensors(tensors, meta, out_path)
    size = os.path.getsize(out_path)
    print(f"    {size} bytes; head tensors after every step: {head_every_step}")


if __name__ == "__main__":
    main()
