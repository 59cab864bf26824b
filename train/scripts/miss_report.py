"""Why a localizer misses the markers it misses: each ground-truth marker that no detection matches
(within r = 0.25 pitch) is put in one class by what lies near it.

- placed off: a detection lies within half a pitch, but too far to match (placement);
- sure, dropped: no detection within half a pitch, but the network's candidates hold one of confidence
  >= 0.4 within 0.3 pitch, more than half a pitch inside the image (the post-processing left it out);
- sure, at the border: the same within half a pitch of the image's border;
- unsure: the network's best candidate within 0.3 pitch has confidence 0.1-0.4;
- none: the network has no candidate above 0.1 there.

    for e in DATA/test/exp_*; do for v in left right; do
      gelstereo detect --threads 1 --out DETS/$(basename $e)_$v.csv $e/$v; done; done
    python scripts/miss_report.py --detections DETS --data DATA --frames 0,4

The candidates are the trainer's reference passes (`MarknetRunner.fitted`: the auto layout, its probes
and relayouts, the closer look) of `--model`, the default's network unless given; split by whether
the marker is in contact.
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gelstereo_train.data import median_nn_distance  # noqa: E402
from gelstereo_train.metrics import RADIUS_FRAC, edge_distances, match  # noqa: E402

CLASSES = ("placed off", "sure, dropped", "sure, at the border", "unsure", "none")
SURE, UNSURE = 0.4, 0.1  # candidate confidences: conf_keep and conf_low of the post-processing
NEAR_PITCH = 0.3  # a candidate this close to a marker is the network's find of it
OUTPUT_PITCH = 0.5  # a detection this close to a missed marker is a misplaced find of it
BORDER_PITCH = 0.5  # a marker this close to the image's border is a border marker


def missed(gt: np.ndarray, det: np.ndarray) -> np.ndarray:
    """Which markers of `gt` (n, 2) no row of `det` (m, 2) matches (within r = 0.25 pitch)."""
    out = np.ones(len(gt), bool)
    if len(det):
        out[match(det, gt, RADIUS_FRAC * median_nn_distance(gt))[1]] = False
    return out


def classify_misses(gt: np.ndarray, det: np.ndarray, candidates: np.ndarray, wh: tuple[int, int]) -> list[int]:
    """The class (index into CLASSES) of each marker of `gt` (n, 2) that no row of `det` (m, 2)
    matches (`missed`), in the order of `gt`; `candidates` (k, 3): the network's x, y, confidence in
    the same image of size `wh`."""
    pitch = median_nn_distance(gt)
    det = np.asarray(det, np.float64).reshape(-1, 2)
    lost = missed(gt, det)
    border = edge_distances(gt, wh).min(1) < BORDER_PITCH * pitch
    classes = []
    for g, on_border in zip(gt[lost], border[lost]):
        if len(det) and np.hypot(*(det - g).T).min() < OUTPUT_PITCH * pitch:
            classes.append(0)
            continue
        near = np.hypot(*(candidates[:, :2] - g).T) < NEAR_PITCH * pitch if len(candidates) else np.zeros(0, bool)
        best = candidates[near, 2].max() if near.any() else 0.0
        if best >= SURE:
            classes.append(2 if on_border else 1)
        else:
            classes.append(3 if best >= UNSURE else 4)
    return classes


def read_detections(path: Path) -> dict[int, np.ndarray]:
    out: dict[int, list] = defaultdict(list)
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            out[int(Path(r["image"]).stem)].append((float(r["x"]), float(r["y"])))
    return {k: np.asarray(v, np.float64) for k, v in out.items()}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--detections", type=Path, required=True, help="folder of EXPERIMENT_VIEW.csv from gelstereo detect")
    p.add_argument("--data", type=Path, required=True, help="dataset root (test/EXPERIMENT/markers.csv, left/, right/)")
    p.add_argument("--frames", default="0,4", help="comma-separated frames of each experiment")
    p.add_argument("--model", type=Path, default=Path(__file__).resolve().parents[2] / "data/models/marknet.onnx")
    args = p.parse_args()
    from gelstereo_train.evaluate import MarknetRunner

    runner = MarknetRunner(args.model)
    frames = {int(f) for f in args.frames.split(",")}
    counts: Counter = Counter()
    markers = 0
    for det_csv in sorted(args.detections.glob("*_*.csv")):
        name, view = det_csv.stem.rsplit("_", 1)
        exp = args.data / "test" / name
        if view not in ("left", "right") or not (exp / "markers.csv").is_file():
            continue
        det = read_detections(det_csv)
        rows: dict[int, list] = defaultdict(list)
        with open(exp / "markers.csv", newline="") as f:
            for r in csv.DictReader(f):
                if int(r["frame"]) in frames and r[f"visible_{view}"] == "1":
                    rows[int(r["frame"])].append(r)
        for frame, rs in sorted(rows.items()):
            image = exp / view / f"{frame:06d}.png"
            if len(rs) < 2 or not image.is_file():
                continue
            gt = np.array([(float(r[f"x_{view}"]), float(r[f"y_{view}"])) for r in rs])
            contact = np.array([r["in_contact"] == "1" for r in rs])
            markers += len(gt)
            d = det.get(frame, np.zeros((0, 2)))
            lost = missed(gt, d)
            if not lost.any():
                continue
            with Image.open(image) as im:
                rgb = np.array(im.convert("RGB"))
            candidates, _ = runner.fitted(rgb)
            classes = classify_misses(gt, d, candidates, (rgb.shape[1], rgb.shape[0]))
            for c, in_contact in zip(classes, contact[lost]):
                counts[(c, bool(in_contact))] += 1
    if not markers:
        raise SystemExit(f"{args.detections}: no markers scored (no EXPERIMENT_VIEW.csv for {args.data}/test?)")
    lost_total = sum(counts.values())
    print(f"markers {markers}, missed {lost_total} ({100 * lost_total / markers:.2f} %)")
    print(f"{'class':22s} {'not in contact':>15s} {'in contact':>11s}")
    for c, label in enumerate(CLASSES):
        print(f"{label:22s} {counts[(c, False)]:15d} {counts[(c, True)]:11d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
