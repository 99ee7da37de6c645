"""Helpers shared by the PyTorch scripts of this folder (imported from the script's own
directory, which Python puts first on sys.path): peft's LoRA on the q and v parts of DINOv2's
fused `attn.qkv`, the Rust trainer's scale-and-shift-invariant loss, and the peak memory of the
process."""
import torch
from torch import nn


class SplitQKV(nn.Module):
    """`attn.qkv` as three Linear layers q, k, v (row slices of the fused weight); the forward
    concatenates them: the same function as the fused Linear, so that peft can put its LoRA on q
    and v (`target_modules` ending in `attn.qkv.q` / `attn.qkv.v`)."""

    def __init__(self, qkv: nn.Linear):
        super().__init__()
        d = qkv.in_features
        assert qkv.out_features == 3 * d
        self.q, self.k, self.v = (nn.Linear(d, d, bias=qkv.bias is not None) for _ in range(3))
        with torch.no_grad():
            for i, lin in enumerate((self.q, self.k, self.v)):
                lin.weight.copy_(qkv.weight[i * d:(i + 1) * d])
                if qkv.bias is not None:
                    lin.bias.copy_(qkv.bias[i * d:(i + 1) * d])

    def forward(self, x):
        return torch.cat([self.q(x), self.k(x), self.v(x)], dim=-1)


def split_qkv(dinov2):
    """Replaces every block's fused `attn.qkv` of a DINOv2 (`model.pretrained`) by `SplitQKV`."""
    for blk in dinov2.blocks:
        blk.attn.qkv = SplitQKV(blk.attn.qkv)


def peak_rss_mib():
    """Peak resident memory of this process (VmHWM), MiB; NaN where /proc is missing."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def ssi_loss(pred, gt_m, valid):
    """`LossKind::Ssi` of the Rust trainer: least-squares scale and shift of the prediction onto the
    ground-truth disparity 1/gt over valid pixels (closed form, differentiable), then the mean
    absolute residual."""
    p = pred.flatten()[valid]
    y = 1.0 / gt_m.flatten()[valid]
    n = p.numel()
    mp, my = p.mean(), y.mean()
    pc, yc = p - mp, y - my
    var_p = (pc * pc).sum() / n
    cov = (pc * yc).sum() / n
    s = cov / (var_p + 1e-12)
    fitted = pc * s + my
    return (fitted - y).abs().mean()


def lora_step(model, params, opt, x, gt_m, valid, clip):
    """One training step as the Rust trainer takes it: the SSI loss, backward, gradient-norm
    clipping to `clip`, the optimiser's step; returns the loss."""
    opt.zero_grad(set_to_none=True)
    loss = ssi_loss(model(x), gt_m, valid)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(params, clip)
    opt.step()
    return loss.item()
