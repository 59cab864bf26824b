"""Marknet (grid regression of marker centres) and MRE (marker rationality evaluator).

Marknet follows the paper (section II-A): convolutions, residual shortcuts, upsampling and ONE detection
layer. The backbone always goes down to stride 32 (13 x 13 cells at 416 x 416); a top-down path with
upsampling brings it back to the stride of the single head: 32 (S = 13), 16 (S = 26) or 8 (S = 52). The
head outputs, for each cell, m candidates of raw logits (tx, ty, tc); decoding is
``x_in = (sigmoid(tx) + gx) * stride`` (the paper's eq. 5-6), ``c = sigmoid(tc)``.

At the default width (8) and S = 52, m = 5 the net has ~45k parameters and ~0.29 GFLOP at 416 x 416
with the stride-2 stem ("s2", the shipped model), ~0.24 GFLOP with the stride-4 stem ("s4").
"""

from __future__ import annotations

import torch
from torch import nn
import torch.nn.functional as F

STRIDE_FOR_GRID_416 = {13: 32, 26: 16, 52: 8}
# Stems: "s2" = 3x3 stride-2 convolution + residual block, then stride 4 (the first shipped model);
# "s4" = one 5x5 stride-4 convolution + residual block (skips the stride-2 stage's large maps);
# "s4-bare" = the same convolution without the residual block: the block's stride-4 maps are few
# channels at the largest size, memory-bound, and cost far more CPU time than their share of the FLOPs
# (figures: docs/experiments/localization-input-and-speed.md, "Where the network's time goes").
STEMS = ("s2", "s4", "s4-bare")
# The second fusing convolution of each top-down step: 3x3 (YOLOv3's), or 1x1, which is cheaper
# (the same figures); the backbone's 3x3 convolutions still give every cell its neighbourhood.
FUSE_KERNELS = (1, 3)


def conv_bn(cin: int, cout: int, k: int, s: int = 1) -> nn.Sequential:
    """Convolution + BatchNorm + LeakyReLU(0.1), the YOLO building block."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, k, s, k // 2, bias=False),
        nn.BatchNorm2d(cout),
        nn.LeakyReLU(0.1, inplace=True),
    )


class Residual(nn.Module):
    """Darknet residual block: 1x1 bottleneck, 3x3, shortcut addition."""

    def __init__(self, c: int):
        super().__init__()
        self.a = conv_bn(c, c // 2, 1)
        self.b = conv_bn(c // 2, c, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.b(self.a(x))


def top_down_path(chans: dict[int, int], to_stride: int, fuse_kernel: int = 3) -> tuple[nn.ModuleList, int]:
    """YOLOv3's top-down path from stride 32 down to `to_stride`: per halving, a 1x1 reduction,
    nearest upsampling, concatenation with the backbone's map of that stride and two fusing
    convolutions, the second `fuse_kernel` x `fuse_kernel`. `chans` = backbone channels per stride.
    Returns the blocks and the channels of the finest fused map."""
    blocks = nn.ModuleList()
    cur, s = chans[32], 32
    while s > to_stride:
        s //= 2
        lat = chans[s]
        blocks.append(
            nn.ModuleDict(
                {
                    "reduce": conv_bn(cur, lat // 2, 1),
                    "fuse1": conv_bn(lat // 2 + lat, lat // 2, 1),
                    "fuse2": conv_bn(lat // 2, lat, fuse_kernel),
                }
            )
        )
        cur = lat
    return blocks, cur


def run_top_down(blocks: nn.ModuleList, feats: dict[int, torch.Tensor]) -> dict[int, torch.Tensor]:
    """Runs `top_down_path` blocks on the backbone maps `feats` (stride -> map, 32 included); returns
    the fused map of every stride it reaches, stride 32 being the backbone's own."""
    fused = {32: feats[32]}
    y, s = feats[32], 32
    for block in blocks:
        s //= 2
        y = block["reduce"](y)
        y = F.interpolate(y, scale_factor=2.0, mode="nearest")
        y = block["fuse2"](block["fuse1"](torch.cat([y, feats[s]], dim=1)))
        fused[s] = y
    return fused


class Marknet(nn.Module):
    """Marknet. Input (N, 3, H, W) RGB in [0, 1]; output (N, H/stride, W/stride, m, 3) raw logits."""

    def __init__(self, stride: int = 8, candidates: int = 5, width: int = 8, stem: str = "s2",
                 fuse_kernel: int = 3):
        super().__init__()
        if stem not in STEMS:
            raise ValueError(f"stem must be one of {sorted(STEMS)}, got {stem!r}")
        if stride not in (8, 16, 32):
            raise ValueError(f"stride must be 8, 16 or 32 (S = 52, 26, 13 at 416), got {stride}")
        if not 1 <= candidates <= 5:
            raise ValueError(f"candidates m must be in 1..5, got {candidates}")
        if fuse_kernel not in FUSE_KERNELS:
            raise ValueError(f"fuse_kernel must be one of {FUSE_KERNELS}, got {fuse_kernel}")
        self.stride = stride
        self.candidates = candidates
        self.width = width
        self.stem_kind = stem
        self.fuse_kernel = fuse_kernel
        w = width
        # Backbone: stride 2, 4, 8, 16, 32.
        if stem == "s2":
            self.stem = nn.Sequential(conv_bn(3, w, 3, 2), Residual(w))
            self.s4 = nn.Sequential(conv_bn(w, 2 * w, 3, 2), Residual(2 * w))
        else:
            # One 5x5 stride-4 convolution straight to stride 4: the stride-2 stage's few-channel maps
            # at half the input size are memory-bound, far costlier than their share of the FLOPs.
            self.stem = nn.Identity()
            residual = [] if stem == "s4-bare" else [Residual(2 * w)]
            self.s4 = nn.Sequential(conv_bn(3, 2 * w, 5, 4), *residual)
        self.s8 = nn.Sequential(conv_bn(2 * w, 4 * w, 3, 2), Residual(4 * w))
        self.s16 = nn.Sequential(conv_bn(4 * w, 8 * w, 3, 2), Residual(8 * w))
        self.s32 = nn.Sequential(conv_bn(8 * w, 8 * w, 3, 2), Residual(8 * w))
        # Top-down path (upsampling + lateral concatenation) down to the head's stride.
        self.up, cur = top_down_path({8: 4 * w, 16: 8 * w, 32: 8 * w}, stride, fuse_kernel)
        self.head = nn.Conv2d(cur, candidates * 3, 1)
        with torch.no_grad():
            self.head.weight.mul_(0.1)
            b = self.head.bias.view(candidates, 3)
            b.zero_()
            b[:, 2] = -4.0  # confidence prior ~0.018

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f2 = self.stem(x)
        f4 = self.s4(f2)
        f8 = self.s8(f4)
        f16 = self.s16(f8)
        f32 = self.s32(f16)
        fused = run_top_down(self.up, {8: f8, 16: f16, 32: f32})
        out = self.head(fused[self.stride])  # (N, m*3, Gy, Gx), channel = k*3 + j
        n, _, gy, gx = out.shape
        return out.view(n, self.candidates, 3, gy, gx).permute(0, 3, 4, 1, 2).contiguous()

    def arch(self) -> dict:
        """The constructor's arguments, as checkpoints record them (`fuse_kernel` only where not 3,
        so the checkpoints written before it existed keep their records)."""
        arch = {"stride": self.stride, "candidates": self.candidates, "width": self.width, "stem": self.stem_kind}
        return arch | ({"fuse_kernel": self.fuse_kernel} if self.fuse_kernel != 3 else {})


def decode(raw: torch.Tensor, stride: int) -> torch.Tensor:
    """Raw logits (N, Gy, Gx, m, 3) -> (N, Gy, Gx, m, 3) of (x_in, y_in, c), continuous input pixels."""
    n, gy, gx, m, _ = raw.shape
    sig = torch.sigmoid(raw)
    ys = torch.arange(gy, dtype=raw.dtype, device=raw.device).view(1, gy, 1, 1)
    xs = torch.arange(gx, dtype=raw.dtype, device=raw.device).view(1, 1, gx, 1)
    x = (sig[..., 0] + xs) * stride
    y = (sig[..., 1] + ys) * stride
    return torch.stack([x, y, sig[..., 2]], dim=-1)


class MRE(nn.Module):
    """Marker rationality evaluator: 11 features -> 3 fully connected layers -> logit."""

    def __init__(self, features: int = 11, hidden: int = 32):
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(features, hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, hidden),
            nn.ReLU(inplace=True),
            nn.Linear(hidden, 1),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Logits (N, 1); apply sigmoid for the probability (the exported model does)."""
        return self.net(x)


def count_flops(model: Marknet, h: int = 416, w: int = 416) -> float:
    """Multiply-adds x 2 of the convolutions at an input size (GFLOP)."""
    total = 0

    def hook(mod, inp, out):
        nonlocal total
        k = mod.kernel_size[0] * mod.kernel_size[1] * (mod.in_channels // mod.groups)
        total += 2 * k * out.numel() // out.shape[0]

    hs = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, nn.Conv2d)]
    was = model.training
    model.eval()
    with torch.no_grad():
        model(torch.zeros(1, 3, h, w))
    model.train(was)
    for hh in hs:
        hh.remove()
    return total / 1e9
