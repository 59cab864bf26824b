"""Default against adapted models on the frames `gelstereo adapt` held out (never trained on).

    gelstereo detect --models A --out A.csv INPUT          # once per model
    gelstereo track --grid RxC --models A --out A_track INPUT   # optional, once per model
    python scripts/compare_adapted.py --input INPUT --adapt-json ADAPTED/adapt.json \\
        --model default A.csv [A_track] --model adapted B.csv [B_track] [--out table.md]

Per model, over the held-out frames (`heldout_frames` of adapt.json): markers per frame (min, median,
max), the share of them that are lattice members (the Python twin of the Rust lattice check,
`postprocess.lattice_fit`, the Rust lattice check), and with a track folder: markers `tracked` per frame, and the ids
tracked in every held-out frame (the same marker kept from the reference frame through them all).
Frames are numbered as `gelstereo adapt` numbers them: the frame of a video, the position of an image
in the sorted folder.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gelstereo_train.postprocess import lattice_fit  # noqa: E402

IMAGE_EXTENSIONS = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pnm"}


def frame_keys(inp: Path) -> dict[str, int]:
    """The detect CSV's `image` value -> frame number, for a folder of images; empty for a video
    (whose `image` is `PATH#N`)."""
    if inp.is_dir():
        files = sorted(p for p in inp.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
        return {str(p): k for k, p in enumerate(files)} | {p.name: k for k, p in enumerate(files)}
    return {}


def read_detect(path: Path, keys: dict[str, int]) -> dict[int, np.ndarray]:
    out: dict[int, list] = defaultdict(list)
    with open(path, newline="") as f:
        for rec in csv.DictReader(f):
            img = rec["image"]
            if "#" in img:
                frame = int(img.rsplit("#", 1)[1].split(":")[0])
            else:
                frame = keys.get(img, keys.get(Path(img).name, -1))
            if frame < 0:
                raise SystemExit(f"{path}: image {img!r} is not a frame of the input")
            out[frame].append((float(rec["x"]), float(rec["y"])))
    return {k: np.asarray(v) for k, v in out.items()}


def read_track(folder: Path) -> dict[int, dict[tuple[int, int], str]]:
    out: dict[int, dict] = defaultdict(dict)
    with open(folder / "markers.csv", newline="") as f:
        for rec in csv.DictReader(f):
            out[int(rec["frame"])][(int(rec["row"]), int(rec["col"]))] = rec["status"]
    return out


def summarise(name: str, dets: dict[int, np.ndarray], track, frames: list[int]) -> dict:
    counts, lattice = [], []
    for fr in frames:
        pts = dets.get(fr, np.zeros((0, 2)))
        counts.append(len(pts))
        if len(pts):
            lattice.append(float(lattice_fit(pts, 1.0)[0].mean()))
    row = {
        "model": name,
        "frames": len(frames),
        "markers_min": int(min(counts)),
        "markers_median": float(np.median(counts)),
        "markers_max": int(max(counts)),
        "lattice_share": float(np.mean(lattice)) if lattice else float("nan"),
    }
    if track is not None:
        tracked = [sum(s == "tracked" for s in track.get(fr, {}).values()) for fr in frames]
        ids = [k for k in set().union(*(track.get(fr, {}).keys() for fr in frames))
               if all(track.get(fr, {}).get(k) == "tracked" for fr in frames)]
        row |= {"tracked_min": int(min(tracked)), "tracked_median": float(np.median(tracked)),
                "ids_kept_all_frames": len(ids)}
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--input", type=Path, required=True, help="the recording given to gelstereo adapt")
    p.add_argument("--adapt-json", type=Path, required=True, help="ADAPTED/adapt.json (held-out frames)")
    p.add_argument("--model", nargs="+", action="append", required=True, metavar="NAME CSV [TRACK_DIR]")
    p.add_argument("--out", type=Path, default=None, help="also write the table (Markdown) and a JSON beside it")
    args = p.parse_args(argv)
    info = json.loads(args.adapt_json.read_text())
    frames = sorted(info["heldout_frames"])
    if not frames:
        raise SystemExit(f"{args.adapt_json}: no held-out frames")
    keys = frame_keys(args.input)
    rows = []
    for spec in args.model:
        if len(spec) not in (2, 3):
            raise SystemExit(f"--model {' '.join(spec)}: expected NAME CSV [TRACK_DIR]")
        track = read_track(Path(spec[2])) if len(spec) == 3 else None
        rows.append(summarise(spec[0], read_detect(Path(spec[1]), keys), track, frames))
    cols = list(rows[0].keys())
    for r in rows[1:]:
        cols += [c for c in r if c not in cols]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join(
            f"{r[c]:.3f}" if isinstance(r.get(c), float) else str(r.get(c, "")) for c in cols) + " |")
    table = "\n".join(lines)
    print(f"held-out frames ({len(frames)}): {frames[0]}..{frames[-1]}\n{table}")
    if args.out:
        args.out.write_text(table + "\n")
        args.out.with_suffix(".json").write_text(json.dumps({"frames": frames, "rows": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
