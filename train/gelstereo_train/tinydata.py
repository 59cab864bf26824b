"""A tiny dataset in the exact layout of `gelstereo simulate`, for tests and fixtures only.

Dots on a smooth shaded background, a regular grid displaced radially by a Gaussian "press" in some
frames (markers there are flagged in_contact). This is NOT training data for the shipped model.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

HEADER = (
    "frame,row,col,x_left,y_left,x_right,y_right,X_mm,Y_mm,Z_mm,dX_mm,dY_mm,dZ_mm,status,"
    "visible_left,visible_right,in_contact"
)


def render_dots(h: int, w: int, pts: np.ndarray, radius_px: float, rng: np.random.Generator) -> np.ndarray:
    """uint8 RGB image of dark anti-aliased dots (centres in pixel-centre convention)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    base = np.stack(
        [0.75 + 0.1 * np.sin(xx / w * 3 + k + rng.uniform(0, 1)) * np.cos(yy / h * 2) for k in range(3)], -1
    )
    dark = np.zeros((h, w))
    for x, y in pts:
        x0, x1 = int(max(0, x - radius_px - 2)), int(min(w, x + radius_px + 3))
        y0, y1 = int(max(0, y - radius_px - 2)), int(min(h, y + radius_px + 3))
        if x1 <= x0 or y1 <= y0:
            continue
        r = np.sqrt((xx[y0:y1, x0:x1] - x) ** 2 + (yy[y0:y1, x0:x1] - y) ** 2)
        dark[y0:y1, x0:x1] = np.maximum(dark[y0:y1, x0:x1], np.clip(radius_px + 0.5 - r, 0, 1))
    img = base * (1 - 0.8 * dark[..., None]) + rng.normal(0, 0.01, base.shape)
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def grid_points(h, w, pitch_px, rows, cols, press=None):
    """Marker grid (rows x cols) centred in the image, optionally displaced by a press
    (cx, cy, sigma_px, amplitude_px). Returns (points (n, 2), rowcol (n, 2), in_contact (n,))."""
    r, c = np.mgrid[0:rows, 0:cols]
    x = (w - 1) / 2 + (c - (cols - 1) / 2) * pitch_px
    y = (h - 1) / 2 + (r - (rows - 1) / 2) * pitch_px
    contact = np.zeros(x.shape, bool)
    if press is not None:
        cx, cy, sig, amp = press
        dx, dy = x - cx, y - cy
        g = np.exp(-(dx**2 + dy**2) / (2 * sig**2))
        norm = np.sqrt(dx**2 + dy**2) + 1e-9
        x = x + amp * g * dx / norm
        y = y + amp * g * dy / norm
        contact = g > 0.3
    return np.stack([x.ravel(), y.ravel()], 1), np.stack([r.ravel(), c.ravel()], 1), contact.ravel()


def write_tiny_dataset(
    root: Path | str,
    size_hw=(96, 128),
    pitch_px=12.0,
    experiments=None,
    frames=3,
    seed=0,
) -> Path:
    """Write ROOT/dataset.json and ROOT/{split}/exp_NNNN/... with small images. Returns root."""
    root = Path(root)
    experiments = experiments or {"train": 2, "val": 1, "test": 1}
    rng = np.random.default_rng(seed)
    h, w = size_hw
    rows, cols = int(h // pitch_px) - 1, int(w // pitch_px) - 1
    root.mkdir(parents=True, exist_ok=True)
    (root / "dataset.json").write_text(
        json.dumps({"generator": "tinydata", "generator_version": "1", "seed": seed, "image_size": [w, h]})
    )
    n_exp = 0
    for split, n in experiments.items():
        for e in range(n):
            exp = root / split / f"exp_{n_exp:04d}"
            n_exp += 1
            for v in ("left", "right"):
                (exp / v).mkdir(parents=True, exist_ok=True)
            lines = [HEADER]
            for f in range(frames):
                press = None
                if f > 0:
                    press = (rng.uniform(0.3, 0.7) * w, rng.uniform(0.3, 0.7) * h, pitch_px * 1.5, pitch_px * 0.3 * f)
                pts, rc, contact = grid_points(h, w, pitch_px, rows, cols, press)
                shift = np.array([rng.uniform(-3, 3), rng.uniform(-2, 2)])
                pts_r = pts + np.array([-4.0, 0.0]) + shift * 0.2
                for view, p in (("left", pts), ("right", pts_r)):
                    img = render_dots(h, w, p, pitch_px * 0.28, rng)
                    Image.fromarray(img).save(exp / view / f"{f:06d}.png")
                for k in range(len(pts)):
                    xl, yl = pts[k]
                    xr, yr = pts_r[k]
                    vl = int(0 <= xl <= w - 1 and 0 <= yl <= h - 1)
                    vr = int(0 <= xr <= w - 1 and 0 <= yr <= h - 1)
                    lines.append(
                        f"{f},{rc[k, 0]},{rc[k, 1]},{xl:.4f},{yl:.4f},{xr:.4f},{yr:.4f},"
                        f"0,0,10,,,,tracked,{vl},{vr},{int(contact[k])}"
                    )
            (exp / "markers.csv").write_text("\n".join(lines) + "\n")
            (exp / "frames.csv").write_text("frame,contact\n" + "".join(f"{f},{int(f > 0)}\n" for f in range(frames)))
            (exp / "calib.yaml").write_text("%YAML:1.0\n---\n")
            (exp / "meta.json").write_text(json.dumps({"frames": frames}))
    return root
