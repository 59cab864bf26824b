"""Draw the markers of a `gelstereo detect --out FILE.csv` run on its images, zoomed, and count them.

    gelstereo detect --models MODELS --out dets.csv ../shared/real/gelslim
    python scripts/draw_detections.py --csv dets.csv --out-dir /tmp/overlays --zoom 3 [--video FILE --frames 0,60,120]

Images are read from the paths in the CSV's `image` column; for a video (`image` = `FILE#N`, frame N)
give --video and the frames to draw. Each detection is a circle (green: confidence >= 0.4, orange:
below) with a dot at its centre, on the image enlarged `--zoom` x with nearest-neighbour pixels, so
that a position can be judged against the dot to a third of a pixel. Prints `image count` per image and
the count's range over all images.
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw


def read_detections(path: Path) -> dict[str, np.ndarray]:
    """image -> (n, 3) array of x, y, confidence (pixel centres at integer coordinates)."""
    out: dict[str, list] = defaultdict(list)
    with open(path, newline="") as f:
        for rec in csv.DictReader(f):
            try:
                out[rec["image"]].append((float(rec["x"]), float(rec["y"]), float(rec["confidence"])))
            except (KeyError, ValueError) as e:
                raise SystemExit(f"{path}: expected columns image,x,y,confidence with numbers ({e})") from e
    return {k: np.asarray(v, np.float64) for k, v in out.items()}


def video_frames(video: Path, wanted: set[int]) -> dict[int, np.ndarray]:
    import cv2

    cap = cv2.VideoCapture(str(video))
    if not cap.isOpened():
        raise SystemExit(f"{video}: cannot open video")
    frames, i = {}, 0
    while wanted - frames.keys():
        ok, f = cap.read()
        if not ok:
            break
        if i in wanted:
            frames[i] = cv2.cvtColor(f, cv2.COLOR_BGR2RGB)
        i += 1
    return frames


def draw(img: np.ndarray, det: np.ndarray, zoom: int) -> Image.Image:
    im = Image.fromarray(img).resize((img.shape[1] * zoom, img.shape[0] * zoom), Image.NEAREST)
    d = ImageDraw.Draw(im)
    r = 2 * zoom
    for x, y, c in det:
        X, Y = (x + 0.5) * zoom - 0.5, (y + 0.5) * zoom - 0.5
        col = (0, 255, 0) if c >= 0.4 else (255, 160, 0)
        d.ellipse((X - r, Y - r, X + r, Y + r), outline=col)
        d.point((X, Y), fill=(255, 0, 0))
    return im


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--csv", type=Path, required=True)
    p.add_argument("--out-dir", type=Path, required=True)
    p.add_argument("--zoom", type=int, default=3)
    p.add_argument("--video", type=Path, default=None, help="the video the CSV's FILE#N rows come from")
    p.add_argument("--frames", default="0", help="video frames to draw, comma-separated")
    args = p.parse_args(argv)
    dets = read_detections(args.csv)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    counts = {k: len(v) for k, v in dets.items()}
    for k in sorted(counts):
        print(k, counts[k])
    if counts:
        print(f"images {len(counts)}, markers per image {min(counts.values())}-{max(counts.values())}")
    if args.video is not None:
        wanted = {int(v) for v in args.frames.split(",")}
        frames = video_frames(args.video, wanted)
        for n, img in sorted(frames.items()):
            key = next((k for k in dets if k.endswith(f"#{n}")), None)
            det = dets.get(key, np.zeros((0, 3)))
            draw(img, det, args.zoom).save(args.out_dir / f"{args.video.stem}_{n:04d}.png")
    else:
        for key, det in dets.items():
            img = np.asarray(Image.open(key).convert("RGB"))
            draw(img, det, args.zoom).save(args.out_dir / (Path(key).stem + ".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
