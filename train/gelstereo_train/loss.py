"""Assignment of ground-truth markers to cells/slots, and the Marknet loss.

Assignment: a marker whose centre (continuous input pixels) lies in cell (gy, gx) =
(floor(y / stride), floor(x / stride)) belongs to that cell. The markers of one cell are sorted by x,
then y, and take slots 0, 1, ... in that order; when a cell holds more than m markers (a strongly
compressed gel at a small pitch) the ones after the m-th are not assigned (they get no target, and the
slots of that cell are all positive). Every other slot is a negative for the confidence.

Loss (paper eq. 3-4): L = alpha * BCE(c) + beta * sum of Euclidean distances (input pixels) between the
decoded positions of the assigned slots and their markers; both sums are divided by the number of
assigned slots in the batch.

Distillation (`distillation_loss`): a student of another architecture learns a trained teacher's
outputs slot by slot, as well as the labels. Both nets share the head's layout (stride, m), and a
student warm-started from the teacher shares its slot order, so each slot's confidence learns the
teacher's probability and each slot the teacher is not sure is empty learns its position.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from .model import decode


def build_targets(labels: list[np.ndarray], gy: int, gx: int, stride: int, m: int):
    """Targets for a batch: positions (B, gy, gx, m, 2) float32 and mask (B, gy, gx, m) bool.
    Also returns the number of markers that could not be assigned (more than m in a cell)."""
    b = len(labels)
    tgt = np.zeros((b, gy, gx, m, 2), dtype=np.float32)
    mask = np.zeros((b, gy, gx, m), dtype=bool)
    dropped = 0
    for i, pts in enumerate(labels):
        if len(pts) == 0:
            continue
        cx = np.clip(np.floor(pts[:, 0] / stride).astype(np.int64), 0, gx - 1)
        cy = np.clip(np.floor(pts[:, 1] / stride).astype(np.int64), 0, gy - 1)
        cell = cy * gx + cx
        order = np.lexsort((pts[:, 1], pts[:, 0], cell))  # by cell, then x, then y
        cell_s = cell[order]
        first = np.r_[0, np.nonzero(np.diff(cell_s))[0] + 1]
        starts = np.repeat(first, np.diff(np.r_[first, len(cell_s)]))
        rank = np.arange(len(cell_s)) - starts
        ok = rank < m
        dropped += int((~ok).sum())
        sel = order[ok]
        tgt[i, cy[sel], cx[sel], rank[ok]] = pts[sel]
        mask[i, cy[sel], cx[sel], rank[ok]] = True
    return torch.from_numpy(tgt), torch.from_numpy(mask), dropped


def ignore_cells(ignore: torch.Tensor, stride: int) -> torch.Tensor:
    """Cells (B, H/stride, W/stride) that touch an ignored pixel of a bool (B, H, W) crop mask: a
    marker centre could lie anywhere in such a cell."""
    return F.max_pool2d(ignore[:, None].float(), stride)[:, 0] > 0.5


def marknet_loss(raw: torch.Tensor, tgt: torch.Tensor, mask: torch.Tensor, stride: int, alpha=1.0, beta=1.0,
                 ignore: torch.Tensor | None = None):
    """The Marknet loss; returns (total, confidence part, distance part, mean distance in input px).
    ``ignore``: bool (B, gy, gx) cells whose empty slots are no negatives (pseudo-labels' uncertain
    regions, ``ignore_cells``); their assigned slots still count."""
    npos = mask.sum().clamp_min(1).float()
    weight = None
    if ignore is not None:
        weight = (~(ignore[..., None] & ~mask)).float()
    bce = F.binary_cross_entropy_with_logits(raw[..., 2], mask.float(), weight=weight, reduction="sum")
    dec = decode(raw, stride)
    d = torch.sqrt(((dec[..., :2] - tgt) ** 2).sum(-1) + 1e-8)[mask]
    dist = d.sum()
    total = (alpha * bce + beta * dist) / npos
    mean_d = d.mean() if d.numel() else torch.zeros(())
    return total, bce / npos, dist / npos, mean_d


def distillation_loss(raw: torch.Tensor, teacher_raw: torch.Tensor, stride: int, conf_from: float = 0.1):
    """Loss of a student's raw logits against a teacher's on the same crops, both (B, gy, gx, m, 3):
    BCE of every slot's confidence against the teacher's probability, plus the Euclidean distance
    (input px) between decoded positions, weighted by the teacher's confidence, over the slots where
    it exceeds `conf_from` (post-processing's lowest tier: the rest are never read). Divided by the
    teacher's expected marker count (its summed confidence), as `marknet_loss` divides by the
    assigned slots. Returns (total, confidence part, distance part)."""
    if raw.shape != teacher_raw.shape:
        raise ValueError(f"student output {tuple(raw.shape)} and teacher output {tuple(teacher_raw.shape)} "
                         "differ: give the student the teacher's --grid and --candidates")
    with torch.no_grad():
        p = torch.sigmoid(teacher_raw[..., 2])
        norm = p.sum().clamp_min(1.0)
        weight = torch.where(p > conf_from, p, torch.zeros_like(p))
        target_xy = decode(teacher_raw, stride)[..., :2]
    bce = F.binary_cross_entropy_with_logits(raw[..., 2], p, reduction="sum")
    # the soft targets' own entropy is the BCE's floor: subtract it so that a perfect copy scores 0
    floor = F.binary_cross_entropy(p, p, reduction="sum")
    d = torch.sqrt(((decode(raw, stride)[..., :2] - target_xy) ** 2).sum(-1) + 1e-8)
    dist = (weight * d).sum()
    conf = (bce - floor) / norm
    return conf + dist / norm, conf, dist / norm
