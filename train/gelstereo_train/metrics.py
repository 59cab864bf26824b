"""The paper's metrics, as defined once in docs/design.md ("Metrics").

A prediction is correct when it is matched one-to-one, nearest pairs first, to a visible ground-truth
marker within r = 0.25 x the marker pitch in pixels (pitch = median nearest-neighbour distance of the
image's visible ground-truth markers, original pixels). precision = PT / (PT + PF), recall = PT / T,
loss = mean squared distance (original px^2) of the correct points. A matched prediction counts towards
the split(s) of its marker; an unmatched one towards the split(s) of its nearest ground-truth marker.
Splits: ``hard`` = markers the tuned blob baseline misses or places farther than r (its own one-to-one
matching), ``easy`` = the rest, ``contact`` = markers in contact per the ground truth, ``border`` = markers
whose centre lies within one pitch of the image border, ``all``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .data import median_nn_distance

RADIUS_FRAC = 0.25


def match(pred: np.ndarray, gt: np.ndarray, radius: float):
    """One-to-one greedy matching, nearest pairs first, within radius. Returns (pi, gi, d) arrays."""
    pred = np.asarray(pred, np.float64).reshape(-1, 2)
    gt = np.asarray(gt, np.float64).reshape(-1, 2)
    if len(pred) == 0 or len(gt) == 0:
        e = np.zeros(0, dtype=np.int64)
        return e, e, np.zeros(0)
    d = np.sqrt(((pred[:, None, :] - gt[None, :, :]) ** 2).sum(-1))
    pi, gi = np.nonzero(d <= radius)
    dd = d[pi, gi]
    order = np.lexsort((gi, pi, dd))
    used_p = np.zeros(len(pred), bool)
    used_g = np.zeros(len(gt), bool)
    mp, mg, md = [], [], []
    for k in order:
        p, g = pi[k], gi[k]
        if used_p[p] or used_g[g]:
            continue
        used_p[p] = used_g[g] = True
        mp.append(p)
        mg.append(g)
        md.append(dd[k])
    return np.asarray(mp, np.int64), np.asarray(mg, np.int64), np.asarray(md, np.float64)


def radius_for(gt: np.ndarray) -> float:
    """r = 0.25 x pitch (median NN distance of the ground truth)."""
    return RADIUS_FRAC * median_nn_distance(gt)


@dataclass
class Counts:
    """Counts of one split."""

    T: int = 0
    PT: int = 0
    PF: int = 0
    D: float = 0.0

    def add(self, o: "Counts") -> None:
        self.T += o.T
        self.PT += o.PT
        self.PF += o.PF
        self.D += o.D

    def summary(self) -> dict:
        p = self.PT / (self.PT + self.PF) if self.PT + self.PF else float("nan")
        r = self.PT / self.T if self.T else float("nan")
        loss = self.D / self.PT if self.PT else float("nan")
        return {"precision": p, "recall": r, "loss_px2": loss, "T": self.T, "PT": self.PT, "PF": self.PF}


SPLITS = ("all", "easy", "hard", "contact", "border")


@dataclass
class Evaluator:
    """Accumulates counts per split over images."""

    counts: dict = field(default_factory=lambda: {s: Counts() for s in SPLITS})
    radii: list = field(default_factory=list)

    def add_image(self, pred: np.ndarray, gt: np.ndarray, hard: np.ndarray, contact: np.ndarray, radius: float,
                  size: tuple[int, int]):
        """pred (n, >=2) original px; gt (g, 2); hard/contact (g,) bool masks; size (width, height) px."""
        pred = np.asarray(pred, np.float64).reshape(-1, np.asarray(pred).shape[-1] if np.size(pred) else 2)[:, :2]
        gt = np.asarray(gt, np.float64).reshape(-1, 2)
        self.radii.append(radius)
        masks = {"all": np.ones(len(gt), bool), "easy": ~hard, "hard": hard, "contact": contact,
                 "border": border_mask(gt, size, radius)}
        pi, gi, d = match(pred, gt, radius)
        matched = np.zeros(len(pred), bool)
        matched[pi] = True
        if len(gt) and (~matched).any():
            un = pred[~matched]
            nearest = np.sqrt(((un[:, None, :] - gt[None, :, :]) ** 2).sum(-1)).argmin(axis=1)
        else:
            nearest = np.zeros(0, np.int64)
        for s, m in masks.items():
            c = self.counts[s]
            c.T += int(m.sum())
            if len(gi):
                c.PT += int(m[gi].sum())
                c.D += float((d[m[gi]] ** 2).sum())
            if len(gt):
                c.PF += int(m[nearest].sum())
            elif s == "all":
                c.PF += int((~matched).sum())

    def summary(self) -> dict:
        out = {s: self.counts[s].summary() for s in SPLITS}
        if self.radii:
            out["radius_px"] = {"median": float(np.median(self.radii)), "min": float(np.min(self.radii)),
                                "max": float(np.max(self.radii))}
        return out


def edge_distances(points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(n, 4) distances of points to the left, top, right and bottom edges of a (width, height) image,
    which spans -0.5..width-0.5 (pixel-centre convention)."""
    p = np.asarray(points, np.float64).reshape(-1, 2)
    w, h = size
    return np.stack([p[:, 0] + 0.5, p[:, 1] + 0.5, w - 0.5 - p[:, 0], h - 0.5 - p[:, 1]], 1)


def border_mask(gt: np.ndarray, size: tuple[int, int], radius: float) -> np.ndarray:
    """GT markers within one pitch (radius / RADIUS_FRAC) of the border of a (width, height) image."""
    return edge_distances(gt, size).min(axis=1) < radius / RADIUS_FRAC


def hard_mask(blob_pts: np.ndarray, gt: np.ndarray, radius: float) -> np.ndarray:
    """GT markers the blob baseline misses or misplaces (no one-to-one match within radius)."""
    _, gi, _ = match(blob_pts, gt, radius)
    hard = np.ones(len(np.asarray(gt).reshape(-1, 2)), bool)
    hard[gi] = False
    return hard
