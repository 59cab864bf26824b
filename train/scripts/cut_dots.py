"""Dots cut by the image border at known centres: how many `gelstereo detect` finds, and how far from
their centres, by how far inside the image their centre lies; and how many centred outside it are
reported.

    python scripts/cut_dots.py render --out CUT
    gelstereo detect --threads 1 --out cut.csv CUT
    python scripts/cut_dots.py report --out CUT --detections cut.csv

40 images of 320 x 240 px, dark dots of radius 5.5 px at a 29 px pitch drawn at 1/16 px (as the CLI's
border test), the lattice's first column and row shifted from 3 px outside to 6.75 px inside the
outermost pixel centres. Distances in px; "inside" is to the nearest outermost pixel centre (the image
span ends 0.5 px beyond it).
"""

from __future__ import annotations

import argparse
import csv
import json
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

W, H, PITCH, RADIUS = 320, 240, 29.0, 5.5


def inside_px(p):
    return min(p[0], p[1], W - 1 - p[0], H - 1 - p[1])


def render(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    truth = {}
    for k in range(40):
        x0, y0 = -3.0 + 0.25 * k, -3.0 + 0.23 * ((k * 7) % 40)
        img = np.full((H, W, 3), (190, 180, 170), np.uint8)
        pts = []
        for r in range(-1, 11):
            for c in range(-1, 13):
                p = (x0 + PITCH * c, y0 + PITCH * r)
                if inside_px(p) > -RADIUS:
                    pts.append(p)
                    at = (int(round(p[0] * 16)), int(round(p[1] * 16)))
                    cv2.circle(img, at, 88, (45, 45, 45), -1, cv2.LINE_AA, 4)
        name = f"g{k:02d}.png"
        cv2.imwrite(str(out / name), img)
        truth[name] = pts
    (out / "truth.json").write_text(json.dumps(truth))


def report(out: Path, detections: Path) -> None:
    truth = json.loads((out / "truth.json").read_text())
    found = defaultdict(list)
    for row in csv.DictReader(detections.open()):
        found[Path(row["image"]).name].append((float(row["x"]), float(row["y"])))
    bins = defaultdict(lambda: [0, []])
    unmatched = 0
    for name, pts in truth.items():
        dets, used = found.get(name, []), set()
        for t in pts:
            d = inside_px(t)
            b = min(np.floor(d * 2) / 2, 6.0)
            bins[b][0] += 1
            dist = [np.hypot(q[0] - t[0], q[1] - t[1]) for q in dets]
            if dist and min(dist) < 0.25 * PITCH:
                used.add(int(np.argmin(dist)))
                bins[b][1].append(min(dist))
        unmatched += len(dets) - len(used)
    print("centre inside (px) | dots | found | error mean / max (px)")
    for b in sorted(bins):
        n, e = bins[b]
        err = f"{np.mean(e):.2f} / {max(e):.2f}" if e else "-"
        label = f"{b:+.1f} to {b + 0.5:+.1f}" if b < 6 else ">= +6.0"
        print(f"{label} | {n} | {len(e)} | {err}")
    outside = sum(len(bins[b][1]) for b in bins if b < -0.5)
    print(f"reported with the centre more than 0.5 px outside: {outside}; detections matching no dot: {unmatched}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["render", "report"])
    ap.add_argument("--out", type=Path, required=True, help="folder of the rendered images and truth.json")
    ap.add_argument("--detections", type=Path, help="gelstereo detect's CSV on that folder (report)")
    a = ap.parse_args()
    if a.what == "render":
        render(a.out)
    else:
        report(a.out, a.detections)


if __name__ == "__main__":
    main()
