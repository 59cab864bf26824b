"""Placements that re-read the pixels around each detected marker, for `placement_bias.py --replace`
(tried, not shipped: docs/experiments/localization-placement.md). Markers within 0.8 pitch of another
or within half a pitch of the border keep their position; so does one whose new position moves more
than 0.2 pitch or whose dot cannot be told from the gel.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gelstereo_train.data import nearest_neighbour_distances  # noqa: E402

MIN_CONTRAST2 = 100.0  # squared colour distance between dot and gel below which nothing moves
RAYS = np.linspace(0, 2 * np.pi, 48, endpoint=False)


def _pitch_and_spaced(pts: np.ndarray):
    nn = nearest_neighbour_distances(pts)
    pitch = float(np.median(nn))
    return pitch, nn >= 0.8 * pitch


def _membership_centroid(win, xx, yy, c, pitch, fill):
    r = np.hypot(xx - c[0], yy - c[1])
    ring, core = (r >= 0.42 * pitch) & (r <= 0.5 * pitch), r <= max(1.0, 0.12 * pitch)
    if ring.sum() < 8 or not core.any():
        return None
    gel, dot = np.median(win[ring], 0), win[core].mean(0)
    axis = dot - gel
    if axis @ axis < MIN_CONTRAST2:
        return None
    proj = (win - gel) @ axis / (axis @ axis)
    # Filled: a glint is a hole in the dot's mask; else it counts as dot by its distance from the gel.
    m = np.clip(proj if fill else np.abs(proj), 0, 1)
    if fill:
        outside = (m <= 0.5).astype(np.uint8)
        _, lab = cv2.connectedComponents(outside, connectivity=4)
        edge = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
        m = np.where((outside == 1) & ~np.isin(lab, edge), 1.0, m)
    m = np.clip((m - 0.25) / 0.75, 0, 1) * (r <= 0.45 * pitch)
    s = m.sum()
    return None if s < 1 else np.array([(m * xx).sum() / s, (m * yy).sum() / s])


def membership(img: np.ndarray, pts: np.ndarray, fill: bool = False) -> np.ndarray:
    """Centroid of each dot's membership, 3 rounds: |projection| on the gel-to-dot colour axis, or
    with `fill` the projection itself, the holes of the dot's mask (membership > 0.5) filled."""
    if len(pts) < 3:
        return pts
    pitch, spaced = _pitch_and_spaced(pts)
    h = int(np.ceil(0.5 * pitch))
    out = pts.copy()
    for i in np.nonzero(spaced)[0]:
        xi, yi = (int(round(v)) for v in pts[i])
        if min(xi, yi) - h < 0 or xi + h >= img.shape[1] or yi + h >= img.shape[0]:
            continue
        win = img[yi - h:yi + h + 1, xi - h:xi + h + 1].astype(np.float64)
        yy, xx = np.mgrid[yi - h:yi + h + 1, xi - h:xi + h + 1].astype(np.float64)
        c = pts[i]
        for _ in range(3):
            c = _membership_centroid(win, xx, yy, c, pitch, fill)
            if c is None or np.hypot(*(c - pts[i])) > 0.2 * pitch:
                break
        else:
            out[i] = c
    return out


def _outline_centre(f, c, pitch):
    radii = np.arange(0.47 * pitch, 0.0, -0.25)
    xs = (c[0] + np.outer(np.cos(RAYS), radii)).astype(np.float32)
    ys = (c[1] + np.outer(np.sin(RAYS), radii)).astype(np.float32)
    s = cv2.remap(f, xs, ys, cv2.INTER_LINEAR).astype(np.float64)
    gel, dot = np.median(s[:, :3].reshape(-1, 3), 0), np.median(s[:, -4:].reshape(-1, 3), 0)
    axis = dot - gel
    if axis @ axis < MIN_CONTRAST2:
        return None
    m = (s - gel) @ axis / (axis @ axis)
    edge = []
    for a, row in enumerate(m):
        k = np.nonzero(row >= 0.5)[0]
        if len(k) and k[0] > 0:
            k = k[0]
            r = radii[k - 1] + (0.5 - row[k - 1]) / (row[k] - row[k - 1]) * (radii[k] - radii[k - 1])
            edge.append((c[0] + r * np.cos(RAYS[a]), c[1] + r * np.sin(RAYS[a])))
    if len(edge) < 0.75 * len(RAYS):
        return None
    e = np.asarray(edge)
    sol, *_ = np.linalg.lstsq(np.c_[2 * e, np.ones(len(e))], (e**2).sum(1), rcond=None)
    return sol[:2]


def outline(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """A circle fitted to each dot's outline: the outermost half-membership crossing on 48 rays, 2 rounds."""
    if len(pts) < 3:
        return pts
    pitch, spaced = _pitch_and_spaced(pts)
    f = img.astype(np.float32)
    out = pts.copy()
    w, h, half = img.shape[1] - 1, img.shape[0] - 1, 0.5 * pitch
    for i in np.nonzero(spaced)[0]:
        c = pts[i]
        if min(c) < half or c[0] > w - half or c[1] > h - half:
            continue
        for _ in range(2):
            c = _outline_centre(f, c, pitch)
            if c is None or np.hypot(*(c - pts[i])) > 0.2 * pitch:
                break
        else:
            out[i] = c
    return out


PLACEMENTS = {
    "membership": membership,
    "membership-filled": lambda img, pts: membership(img, pts, fill=True),
    "outline": outline,
}
