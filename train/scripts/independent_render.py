"""Marker images drawn by a renderer that shares no code and no rendering model with `gelstereo simulate`,
for an honest second opinion on the localizer (docs/localization.md, "An independent renderer").

    cd train && ../.venv/bin/python scripts/independent_render.py --out ../IND --experiments 24 --seed 5
    gelstereo eval --dataset IND --methods blob,marknet-mre

What it draws, per experiment (one sensor look, a rest frame and three frames of one contact):
- a square or hexagonal lattice of dots (dark on a light gel, or light on a dark one), slightly rotated,
  at 640 x 480 or 1280 x 720, with a pitch of 3-6 % of the shorter side, slightly larger than the view
  so that it runs past every border;
- one contact: a sphere (dots pushed outwards and shifted by a slide), or a flat punch or a box whose
  rim squeezes the dots around it into a narrow band (pile-ups of touching and overlapping dots,
  each squeezed along the radial direction); `in_contact` marks the dots under the indenter and in
  that band;
- a tint over the contact, dust specks off the lattice, blur, noise and JPEG.
`--sensor reference` keeps the contacts and looks but lays out the reference sensor instead: a
23 x 23 lattice of dark dots at a 16-18 px pitch inside a 640 x 480 view. Dots are anti-aliased
ellipses drawn at 1/16 px; the truth is each dot's centre. A dot counts as
visible when its centre lies within the outermost pixel centres. The two views are two draws of the same scene with
their own lattice phase. `markers.csv` lists every dot of the lattice, those outside the view with
visible 0 (where a detection near the border came from). The output is `gelstereo simulate`'s test-split layout (`markers.csv` with
`visible_left`, `visible_right`, `in_contact`), so `gelstereo eval --dataset` scores it.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

import cv2
import numpy as np

SHIFT = 4  # OpenCV drawing: coordinates in 1/16 px
REFERENCE_GRID = (23, 23)  # `--sensor reference`: the reference sensor's lattice
FRAMES = 4  # rest, then three steps of the contact
COLUMNS = ["frame", "row", "col", "x_left", "y_left", "x_right", "y_right", "X_mm", "Y_mm", "Z_mm",
           "dX_mm", "dY_mm", "dZ_mm", "status", "visible_left", "visible_right", "in_contact"]


def lattice(rng, w: int, h: int, hexagonal: bool, grid: tuple[int, int] | None = None
            ) -> tuple[np.ndarray, np.ndarray, float]:
    """Rest centres (n, 2), their (row, col) and the pitch: a lattice slightly larger than the view, or
    `grid` (rows, columns) at a pitch of 16-18 px, inside it."""
    if grid is None:
        pitch = float(rng.uniform(0.03, 0.06) * min(w, h))
        rows = int(math.ceil(h / (pitch * (math.sqrt(3) / 2 if hexagonal else 1.0)))) + 1
        cols = int(math.ceil(w / pitch)) + 1
    else:
        pitch = float(rng.uniform(16.0, 18.0))
        rows, cols = grid
    angle = math.radians(rng.uniform(-3, 3))
    origin = np.array([w / 2, h / 2]) + rng.uniform(-0.5, 0.5, 2) * pitch
    pts, idx = [], []
    for r in range(rows):
        for c in range(cols):
            x = (c - (cols - 1) / 2 + (0.5 * (r % 2) if hexagonal else 0.0)) * pitch
            y = (r - (rows - 1) / 2) * pitch * (math.sqrt(3) / 2 if hexagonal else 1.0)
            pts.append([x * math.cos(angle) - y * math.sin(angle), x * math.sin(angle) + y * math.cos(angle)])
            idx.append((r, c))
    return np.array(pts) + origin, np.array(idx), pitch


def contact_distance(p: np.ndarray, centre: np.ndarray, kind: str) -> np.ndarray:
    """Distance from the contact's centre: Euclidean, or Chebyshev for a box."""
    d = p - centre
    return np.abs(d).max(axis=1) if kind == "box" else np.hypot(d[:, 0], d[:, 1])


def deform(rest: np.ndarray, pitch: float, contact: dict, amount: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Displaced centres, the radial squeeze of each dot (1: none) and whether it is in contact: under
    the indenter, or in the band its rim squeezes."""
    c, radius, kind = contact["centre"], contact["radius"], contact["kind"]
    d = contact_distance(rest, c, kind)
    direction = rest - c
    norm = np.hypot(direction[:, 0], direction[:, 1])[:, None]
    direction = np.divide(direction, norm, out=np.zeros_like(direction), where=norm > 0)
    if kind == "sphere":
        push = amount * contact["depth"] * pitch * (d / radius) * np.exp(-(d / radius) ** 2)
        moved = rest + push[:, None] * direction
        moved += amount * contact["slide"] * np.exp(-(d / (1.5 * radius)) ** 2)[:, None]
        return moved, np.ones(len(rest)), d < radius
    # A flat punch or a box: the band [radius - a, radius + b] is squeezed to k of its width, and the
    # gel beyond it follows.
    a, b = 0.6 * pitch, 1.6 * pitch
    k = 1.0 - amount * (1.0 - contact["squeeze"])
    band = np.clip(d - (radius - a), 0.0, a + b)
    beyond = np.clip(d - (radius + b), 0.0, None)
    shrink = np.where(beyond > 0, (a + b) * (1.0 - k) * np.exp(-beyond / (2 * pitch)), band * (1.0 - k))
    moved = rest - shrink[:, None] * direction
    moved += amount * contact["slide"] * (d < radius + b)[:, None]
    squeeze = np.where((d > radius - a) & (d < radius + b), k, 1.0)
    return moved, squeeze, d < radius + b


def draw_view(rng, look: dict, centres: np.ndarray, squeeze: np.ndarray, contact: dict, amount: float,
              size: tuple[int, int]) -> np.ndarray:
    """One 8-bit BGR view of the dots at `centres`."""
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    g = look["gel"] * (1.0 + look["gradient"] * ((xx / w - 0.5)[..., None] * look["tilt"][0]
                                                 + (yy / h - 0.5)[..., None] * look["tilt"][1]))
    if amount > 0:
        d = np.hypot(xx - contact["centre"][0], yy - contact["centre"][1]) / contact["radius"]
        tint = (amount * look["tint_strength"] * np.exp(-d ** 2))[..., None]
        g = g * (1 - tint) + look["tint"] * tint
    image = np.clip(g, 0, 255).astype(np.uint8).copy()
    c = centres - contact["centre"]
    for (x, y), k, (dx, dy) in zip(centres, squeeze, c):
        if not (-look["radius"] * 2 < x < w + look["radius"] * 2 and -look["radius"] * 2 < y < h + look["radius"] * 2):
            continue
        angle = math.degrees(math.atan2(dy, dx))
        axes = (max(1, int(round(look["radius"] * max(k, 0.45) * (1 << SHIFT)))),
                int(round(look["radius"] * (1 << SHIFT))))
        centre = (int(round(x * (1 << SHIFT))), int(round(y * (1 << SHIFT))))
        cv2.ellipse(image, centre, axes, angle, 0, 360, look["dot"], -1, cv2.LINE_AA, SHIFT)
    for _ in range(look["dust"]):
        p = (int(rng.uniform(0, w) * (1 << SHIFT)), int(rng.uniform(0, h) * (1 << SHIFT)))
        cv2.circle(image, p, int(rng.uniform(0.6, 2.5) * (1 << SHIFT)), look["dust_colour"], -1, cv2.LINE_AA, SHIFT)
    image = cv2.GaussianBlur(image, (0, 0), look["blur"])
    noisy = image.astype(np.float32) + rng.normal(0, look["noise"], image.shape)
    image = np.clip(noisy, 0, 255).astype(np.uint8)
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, look["jpeg"]])
    return cv2.imdecode(jpeg, cv2.IMREAD_COLOR)


def random_look(rng, pitch: float, light_dots: bool | None = None) -> dict:
    """Colours, dot size, shading, dust, blur, noise and JPEG quality; `light_dots` None: light dots on a
    dark gel a quarter of the time."""
    if light_dots is None:
        light_dots = bool(rng.random() < 0.25)
    gel = rng.uniform(150, 225, 3) if not light_dots else rng.uniform(30, 90, 3)
    dot = rng.uniform(20, 70, 3) if not light_dots else rng.uniform(190, 250, 3)
    return {
        "gel": gel.astype(np.float32), "dot": tuple(float(v) for v in dot),
        "radius": float(rng.uniform(0.18, 0.3) * pitch), "gradient": float(rng.uniform(0.0, 0.35)),
        "tilt": rng.uniform(-1, 1, 2), "tint": rng.uniform(60, 230, 3).astype(np.float32),
        "tint_strength": float(rng.uniform(0.1, 0.45)), "dust": int(rng.integers(0, 6)),
        "dust_colour": tuple(float(v) for v in (dot * 0.9 + gel * 0.1)),
        "blur": float(rng.uniform(0.5, 1.4)), "noise": float(rng.uniform(1.0, 4.0)),
        "jpeg": int(rng.integers(60, 96)), "light_dots": bool(light_dots),
    }


def write_experiment(rng, root: Path, name: str, sensor: str) -> dict:
    reference = sensor == "reference"
    size = (640, 480) if reference or rng.random() < 0.7 else (1280, 720)
    hexagonal = not reference and bool(rng.random() < 0.3)
    rest, idx, pitch = lattice(rng, *size, hexagonal, REFERENCE_GRID if reference else None)
    kind = str(rng.choice(["sphere", "flat", "box"]))
    contact = {"kind": kind, "centre": np.array(size) / 2 + rng.uniform(-0.15, 0.15, 2) * np.array(size),
               "radius": float(rng.uniform(2.5, 5.0) * pitch), "depth": float(rng.uniform(0.3, 0.8)),
               "squeeze": float(rng.uniform(0.35, 0.7)),
               "slide": rng.uniform(-0.6, 0.6, 2) * pitch}
    look = random_look(rng, pitch, light_dots=False if reference else None)
    offsets = [np.zeros(2), rng.uniform(-0.5, 0.5, 2) * pitch]  # the right view: another lattice phase
    exp = root / "test" / name
    rows = []
    for f in range(FRAMES):
        amount = f / (FRAMES - 1)
        moved, squeeze, in_contact = deform(rest, pitch, contact, amount)
        views = []
        for v, off in zip(("left", "right"), offsets):
            centres = moved + off
            (exp / v).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(exp / v / f"{f:06d}.png"), draw_view(rng, look, centres, squeeze, contact, amount, size))
            w, h = size
            visible = (centres[:, 0] >= 0) & (centres[:, 0] <= w - 1) & (centres[:, 1] >= 0) & (centres[:, 1] <= h - 1)
            views.append((centres, visible))
        for i, (r, c) in enumerate(idx):
            (lc, lv), (rc, rv) = views
            rows.append([f, r, c, f"{lc[i, 0]:.4f}", f"{lc[i, 1]:.4f}", f"{rc[i, 0]:.4f}", f"{rc[i, 1]:.4f}",
                         0, 0, 0, 0, 0, 0, "", int(lv[i]), int(rv[i]), int(bool(in_contact[i]) and f > 0)])
    with open(exp / "markers.csv", "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(COLUMNS)
        out.writerows(rows)
    return {"name": name, "path": f"test/{name}", "frames": FRAMES, "image_width": size[0],
            "image_height": size[1], "lattice": "hexagonal" if hexagonal else "square", "indenter": kind,
            "pitch_px": round(pitch, 2), "light_dots": look["light_dots"], "split": "test",
            "sensor": f"independent-render-{sensor}"}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--experiments", type=int, default=24)
    p.add_argument("--seed", type=int, default=5)
    p.add_argument("--sensor", choices=("wide", "reference"), default="wide",
                   help="wide: the lattices and looks above; reference: the reference sensor's layout, a "
                   "23 x 23 lattice of dark dots at a 16-18 px pitch inside a 640 x 480 view")
    args = p.parse_args(argv)
    if args.experiments < 1:
        p.error("--experiments: expected at least 1")
    rng = np.random.default_rng(args.seed)
    experiments = [write_experiment(rng, args.out, f"exp_{i:04d}", args.sensor) for i in range(args.experiments)]
    manifest = {"counts": {"test": {"experiments": len(experiments), "frames": FRAMES * len(experiments)}},
                "experiments": experiments, "generator": "train/scripts/independent_render.py", "seed": args.seed}
    (args.out / "dataset.json").write_text(json.dumps(manifest, indent=2))
    print(f"wrote {len(experiments)} experiments of {FRAMES} stereo frames to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
