"""The paper's YOLOv3 baseline (Table I): an anchor-based detector whose box centres are the markers.

YOLOv3 (Redmon & Farhadi 2018) "with modified anchor size and output for this marker detection task":

* backbone: the Darknet building blocks of Marknet (conv + BatchNorm + LeakyReLU, residual
  shortcuts, gelstereo_train.model), down to stride 32;
* neck: YOLOv3's top-down path (1x1 reduce, 2x nearest upsampling, concatenation with the lateral
  feature, 1x1 / 3x3 fuse) down to stride 8;
* heads: one detection layer per stride in ``strides`` (default 8 and 16, the two finest of YOLOv3's
  three: at stride 32 a 32 px cell holds ~6 markers of the reference sensor, more than its anchors),
  each with ``anchors_per_head`` anchors fitted by k-means (1 - IoU distance) to the training boxes;
* output per anchor: ``(tx, ty, tw, th, to)`` (one class, so no class scores: the "modified output").

Decoding (docs/model-contract.md, ``yolo.onnx``): for head h of stride s, cell (gy, gx), anchor
(aw, ah) in input pixels::

    x_in = (sigmoid(tx) + gx) * s          w_in = aw * exp(clamp(tw, -TW_CLAMP, TW_CLAMP))
    y_in = (sigmoid(ty) + gy) * s          h_in = ah * exp(clamp(th, -TW_CLAMP, TW_CLAMP))
    objectness = sigmoid(to)

The exported output ``raw`` is ``[N, K, 5]``: heads in ascending stride, then gy, gx, anchor.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from .model import Residual, conv_bn, run_top_down, top_down_path

OUTPUTS_PER_ANCHOR = 5
TW_CLAMP = 20.0  # |tw|, |th| are clamped before exp (both in PyTorch, in the reference and in Rust)
BACKBONE_STRIDES = (8, 16, 32)


class YoloV3(nn.Module):
    """Input (N, 3, H, W) RGB in [0, 1] (H, W multiples of 32); output raw (N, K, 5)."""

    def __init__(self, anchors: np.ndarray | list, strides=(8, 16), width: int = 8):
        super().__init__()
        strides = tuple(int(s) for s in strides)
        if not strides or any(s not in BACKBONE_STRIDES for s in strides) or list(strides) != sorted(set(strides)):
            raise ValueError(f"strides must be ascending, distinct, from {BACKBONE_STRIDES}; got {strides}")
        anchors = np.asarray(anchors, dtype=np.float64).reshape(len(strides), -1, 2)
        if not (np.isfinite(anchors).all() and (anchors > 0).all()):
            raise ValueError(f"anchors must be positive (w, h) in input pixels, got {anchors.tolist()}")
        self.strides = strides
        self.width = width
        self.anchors_per_head = anchors.shape[1]
        self.register_buffer("anchors", torch.tensor(anchors, dtype=torch.float32))
        w = width
        self.stem = nn.Sequential(conv_bn(3, w, 3, 2), Residual(w))
        self.s4 = nn.Sequential(conv_bn(w, 2 * w, 3, 2), Residual(2 * w))
        self.s8 = nn.Sequential(conv_bn(2 * w, 4 * w, 3, 2), Residual(4 * w))
        self.s16 = nn.Sequential(conv_bn(4 * w, 8 * w, 3, 2), Residual(8 * w))
        self.s32 = nn.Sequential(conv_bn(8 * w, 8 * w, 3, 2), Residual(8 * w))
        chans = {8: 4 * w, 16: 8 * w, 32: 8 * w}
        self.up, _ = top_down_path(chans, strides[0])
        self.heads = nn.ModuleDict()
        for st in strides:
            c = chans[st]
            conv = nn.Conv2d(c, self.anchors_per_head * OUTPUTS_PER_ANCHOR, 1)
            with torch.no_grad():
                conv.weight.mul_(0.1)
                b = conv.bias.view(self.anchors_per_head, OUTPUTS_PER_ANCHOR)
                b.zero_()
                b[:, 4] = -4.5  # objectness prior ~0.011 (few cells hold a marker)
            self.heads[str(st)] = nn.Sequential(conv_bn(c, c, 3), conv)

    def head_maps(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Per head (ascending stride): raw (N, Gy, Gx, A, 5)."""
        f8 = self.s8(self.s4(self.stem(x)))
        f16 = self.s16(f8)
        f32 = self.s32(f16)
        fused = run_top_down(self.up, {8: f8, 16: f16, 32: f32})
        out = []
        for st in self.strides:
            o = self.heads[str(st)](fused[st])
            n, _, gy, gx = o.shape
            out.append(o.view(n, self.anchors_per_head, OUTPUTS_PER_ANCHOR, gy, gx).permute(0, 3, 4, 1, 2))
        return out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        maps = self.head_maps(x)
        return torch.cat([m.reshape(m.shape[0], -1, OUTPUTS_PER_ANCHOR) for m in maps], dim=1)


def decode_head(raw: torch.Tensor, stride: int, anchors: torch.Tensor) -> torch.Tensor:
    """Raw (N, Gy, Gx, A, 5) of one head -> (N, Gy, Gx, A, 5) of (x_in, y_in, w_in, h_in, objectness)."""
    _, gy, gx, _, _ = raw.shape
    ys = torch.arange(gy, dtype=raw.dtype).view(1, gy, 1, 1)
    xs = torch.arange(gx, dtype=raw.dtype).view(1, 1, gx, 1)
    x = (torch.sigmoid(raw[..., 0]) + xs) * stride
    y = (torch.sigmoid(raw[..., 1]) + ys) * stride
    a = anchors.to(raw.dtype)
    w = a[:, 0] * torch.exp(raw[..., 2].clamp(-TW_CLAMP, TW_CLAMP))
    h = a[:, 1] * torch.exp(raw[..., 3].clamp(-TW_CLAMP, TW_CLAMP))
    return torch.stack([x, y, w, h, torch.sigmoid(raw[..., 4])], dim=-1)


def wh_iou(wh1: np.ndarray, wh2: np.ndarray) -> np.ndarray:
    """IoU of boxes sharing a centre: (n, 2) x (k, 2) -> (n, k)."""
    wh1 = np.asarray(wh1, np.float64).reshape(-1, 1, 2)
    wh2 = np.asarray(wh2, np.float64).reshape(1, -1, 2)
    inter = np.minimum(wh1, wh2).prod(-1)
    return inter / (wh1.prod(-1) + wh2.prod(-1) - inter)


def kmeans_anchors(wh: np.ndarray, k: int, seed: int = 0, iters: int = 300) -> np.ndarray:
    """YOLOv2/v3 anchor clustering: k-means on box (w, h) with distance 1 - IoU, k-means++ seeding,
    median update. Returns (k, 2) sorted by area (ascending)."""
    wh = np.asarray(wh, np.float64).reshape(-1, 2)
    wh = wh[np.isfinite(wh).all(1) & (wh > 0).all(1)]
    if len(wh) < k:
        raise ValueError(f"k-means needs at least k={k} boxes, got {len(wh)}")
    rng = np.random.default_rng(seed)
    centres = [wh[rng.integers(len(wh))]]
    for _ in range(1, k):
        d = (1.0 - wh_iou(wh, np.asarray(centres))).min(1) ** 2
        centres.append(wh[rng.choice(len(wh), p=d / d.sum())] if d.sum() > 0 else wh[rng.integers(len(wh))])
    c = np.asarray(centres)
    assign = None
    for _ in range(iters):
        new = (1.0 - wh_iou(wh, c)).argmin(1)
        if assign is not None and (new == assign).all():
            break
        assign = new
        for j in range(k):
            if (assign == j).any():
                c[j] = np.median(wh[assign == j], axis=0)
    return c[np.argsort(c.prod(1), kind="stable")]


def mean_best_iou(wh: np.ndarray, anchors: np.ndarray) -> float:
    """Average over boxes of the best IoU with any anchor (the fit statistic reported for k-means)."""
    return float(wh_iou(wh, anchors).max(1).mean())
