"""A small copy of a dataset's train split to carry to a training machine with little room for data:
a few images per experiment, re-encoded as JPEG, with their rows of markers.csv (the columns the
trainer reads).

    python scripts/pack_subset.py --data MIX --out PACK --per-experiment 2 --quality 88
    tar -czf pack.tgz PACK

On MIX (420 training experiments) this gives 840 images, 38 MB of JPEG and 46 MB as a .tgz; PNG would
be ~540 MB. JPEG q88 moves no marker centre measurably, and the trainer's own augmentation
compresses a fifth of its crops harder (q30-95).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import random
import sys
from pathlib import Path

from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gelstereo_train.data import REQUIRED_COLUMNS, VIEWS  # noqa: E402


def pack_experiment(src: Path, dst: Path, per_experiment: int, quality: int, rng: random.Random) -> int:
    """Copies `per_experiment` random (frame, view) images of one experiment; returns how many."""
    frames = sorted(int(p.stem) for p in (src / VIEWS[0]).glob("*.png"))
    choices = [(f, v) for f in frames for v in VIEWS if (src / v / f"{f:06d}.png").is_file()]
    picks = rng.sample(choices, min(per_experiment, len(choices)))
    keep = {f for f, _ in picks}
    dst.mkdir(parents=True)
    with open(src / "markers.csv", newline="") as fi, open(dst / "markers.csv", "w", newline="") as fo:
        rows = csv.reader(fi)
        header = next(rows)
        idx = [header.index(c) for c in REQUIRED_COLUMNS]
        out = csv.writer(fo)
        out.writerow(REQUIRED_COLUMNS)
        out.writerows([r[i] for i in idx] for r in rows if r and int(r[idx[0]]) in keep)
    for f, v in picks:
        (dst / v).mkdir(exist_ok=True)
        with Image.open(src / v / f"{f:06d}.png") as im:
            im.convert("RGB").save(dst / v / f"{f:06d}.jpg", "JPEG", quality=quality)
    return len(picks)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True, help="dataset root (its train/ split is packed)")
    p.add_argument("--out", type=Path, required=True, help="new dataset root to write (must not exist)")
    p.add_argument("--per-experiment", type=int, default=2, help="images per experiment (random frame and view)")
    p.add_argument("--quality", type=int, default=88, help="JPEG quality")
    p.add_argument("--seed", type=int, default=7)
    args = p.parse_args()
    if args.out.exists():
        raise SystemExit(f"{args.out}: exists; give a new folder")
    split = args.data / "train"
    if not split.is_dir():
        raise SystemExit(f"{split}: no train split (expected DATA/train/exp_NNNN/)")
    rng = random.Random(args.seed)
    images = 0
    for exp in sorted(os.listdir(split)):
        if (split / exp / "markers.csv").is_file():
            images += pack_experiment(split / exp, args.out / "train" / exp, args.per_experiment, args.quality, rng)
    (args.out / "dataset.json").write_text(json.dumps({
        "generator": "gelstereo-sim",
        "packed": f"{args.data.name} train, {args.per_experiment} image(s) per experiment, JPEG q{args.quality}",
    }))
    print(f"{images} images written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
