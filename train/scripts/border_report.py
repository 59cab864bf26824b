"""How a localizer does at the image border: the ground-truth markers within one pitch of it, by their
distance from it, found (within r = 0.25 pitch) or not, and how far the found ones sit out- or inward;
and the detections near the border that match no marker (phantoms).

    for e in DATA/test/exp_*; do gelstereo detect --models MODELS --threads 1 --out DETS/$(basename $e).csv $e/left; done
    python scripts/border_report.py --detections DETS --data DATA

Left views of a `gelstereo simulate` dataset's test split; the ground truth's `visible_left` markers
(centre inside the image). Distances and the pitch (median nearest-neighbour distance of the image's
markers) in original px; "outward" is along the normal of the nearest edge, out of the image.
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gelstereo_train.data import median_nn_distance  # noqa: E402
from gelstereo_train.metrics import RADIUS_FRAC, edge_distances  # noqa: E402

BANDS = ((0.0, 0.25), (0.25, 0.5), (0.5, 0.75), (0.75, 1.0))  # distance from the border, pitches
OUTWARD = np.array([[-1.0, 0.0], [0.0, -1.0], [1.0, 0.0], [0.0, 1.0]])  # the order of edge_distances


def read_points(path: Path, frame_of, xy_of, keep=lambda r: True) -> dict[int, np.ndarray]:
    out: dict[int, list] = defaultdict(list)
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            if keep(r):
                out[frame_of(r)].append(xy_of(r))
    return {k: np.asarray(v, np.float64) for k, v in out.items()}


def score_image(gt: np.ndarray, det: np.ndarray, w: int, h: int):
    """Rows (distance / pitch, found, outward offset px) for the border markers; phantom distances / pitch."""
    pitch = median_nn_distance(gt)
    r = RADIUS_FRAC * pitch
    edges = edge_distances(gt, (w, h))
    rows = []
    for i in np.where(edges.min(1) < pitch)[0]:
        d = np.sqrt(((det - gt[i]) ** 2).sum(1)) if len(det) else np.zeros(0)
        j = int(d.argmin()) if len(d) else -1
        found = j >= 0 and d[j] <= r
        offset = float((det[j] - gt[i]) @ OUTWARD[edges[i].argmin()]) if found else np.nan
        rows.append((edges[i].min() / pitch, found, offset))
    phantoms = []
    if len(det):
        far = np.sqrt(((det[:, None] - gt[None]) ** 2).sum(-1)).min(1) > r
        near = edge_distances(det, (w, h)).min(1)
        phantoms = list(near[far & (near < pitch)] / pitch)
    return rows, phantoms


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--detections", type=Path, required=True, help="folder of EXPERIMENT.csv from gelstereo detect")
    p.add_argument("--data", type=Path, required=True, help="dataset root (test/EXPERIMENT/markers.csv, left/)")
    args = p.parse_args()
    rows, phantoms = [], []
    for det_csv in sorted(args.detections.glob("*.csv")):
        exp = args.data / "test" / det_csv.stem
        det = read_points(det_csv, lambda r: int(Path(r["image"]).stem), lambda r: (float(r["x"]), float(r["y"])))
        gt = read_points(exp / "markers.csv", lambda r: int(r["frame"]),
                         lambda r: (float(r["x_left"]), float(r["y_left"])), lambda r: r["visible_left"] == "1")
        for frame, g in gt.items():
            image = exp / "left" / f"{frame:06d}.png"
            if len(g) < 2 or not image.is_file():
                continue
            with Image.open(image) as im:
                w, h = im.size
            r, ph = score_image(g, det.get(frame, np.zeros((0, 2))), w, h)
            rows += r
            phantoms += ph
    if not rows:
        raise SystemExit(f"{args.detections}: no border markers scored (no detections for {args.data}/test?)")
    a = np.asarray(rows, np.float64)
    print(f"border markers {len(a)}, found {100 * a[:, 1].mean():.1f} %")
    for lo, hi in BANDS:
        band = (a[:, 0] >= lo) & (a[:, 0] < hi)
        found = band & (a[:, 1] == 1)
        print(f"  {lo:.2f}-{hi:.2f} pitch from the border: {band.sum():5d} markers, found {100 * a[band, 1].mean():5.1f} %, "
              f"mean outward offset {np.nanmean(a[found, 2]):+.2f} px")
    ph = np.asarray(phantoms)
    print(f"phantoms within one pitch of the border: {len(ph)}, within a quarter pitch: {int((ph < 0.25).sum())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
