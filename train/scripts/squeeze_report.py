"""How far contacts squeeze the marker lattice in a dataset's test split: over every visible marker (left
view) of each frame with a marker in contact, its nearest neighbour's distance in pitches (the
experiment's rest-frame median), as quantiles and the shares below 0.5 and 0.6 pitch.

    cd train && ../.venv/bin/python scripts/squeeze_report.py ../V1 ../INDREF --frame-step 10

Used in docs/experiments/localization-independent-renderer.md to compare the simulator's rims with the
independent renderer's.
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gelstereo_train.data import median_nn_distance, nearest_neighbour_distances  # noqa: E402


def squeeze(root: Path, frame_step: int) -> np.ndarray:
    """Nearest-neighbour distances, pitches, of the visible markers of every `frame_step`-th frame that
    has a marker in contact, over the test split of `root`."""
    out = []
    for exp in sorted((root / "test").glob("exp_*")):
        frames = defaultdict(list)
        with open(exp / "markers.csv", newline="") as fh:
            for r in csv.DictReader(fh):
                if r["visible_left"] == "1":
                    frames[int(r["frame"])].append((float(r["x_left"]), float(r["y_left"]), r["in_contact"] == "1"))
        if len(frames.get(0, [])) < 2:
            continue
        pitch = median_nn_distance(np.array(frames[0])[:, :2])
        for f in sorted(frames)[::frame_step]:
            view = np.array(frames[f])
            if len(view) >= 2 and view[:, 2].any():
                out.append(nearest_neighbour_distances(view[:, :2]) / pitch)
    return np.concatenate(out) if out else np.zeros(0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=Path, nargs="+", help="datasets in gelstereo simulate's layout")
    p.add_argument("--frame-step", type=int, default=1)
    args = p.parse_args(argv)
    if args.frame_step < 1:
        p.error("--frame-step: expected at least 1")
    for root in args.data:
        if not (root / "test").is_dir():
            p.error(f"{root}: no test/ folder (expected a dataset written by gelstereo simulate)")
        d = squeeze(root, args.frame_step)
        if not len(d):
            print(f"{root}: no frame with a marker in contact")
            continue
        q = np.quantile(d, [0.01, 0.05, 0.1, 0.5])
        print(f"{root}: {len(d)} markers of contact frames; nearest neighbour, pitches: 1 / 5 / 10 / 50 % "
              f"quantiles {q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} / {q[3]:.2f}; below 0.5 pitch "
              f"{100 * np.mean(d < 0.5):.2f} %, below 0.6 {100 * np.mean(d < 0.6):.2f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
