"""Zero-shot check on a real mono recording (e.g. the GelSight Mini video in ../shared/real/).

    python -m gelstereo_train.real_check --video ../../shared/real/gelsight-mini-press/mini_example.avi \
        --marknet ../data/models/marknet.onnx --mre ../data/models/mre.onnx --frames 0-55 --expect 80

There are no annotations, so the check is structural: per frame, the number of Marknet + MRE markers
(expected: all 80 of the 8 x 10 grid), and whether they are the SAME markers in every frame (each
matched one-to-one within 0.25 x pitch to the markers of the first frame). The blob baseline (tuned
parameters) is reported alongside. Optionally writes an overlay PNG of one frame.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from .blob import BlobDetector
from .evaluate import MarknetRunner, load_mre
from .metrics import match
from .postprocess import PostConfig, input_per_px, postprocess


def read_frames(video: Path, first: int, last: int) -> list[np.ndarray]:
    import cv2

    cap = cv2.VideoCapture(str(video))
    if not cap.isOpened():
        raise SystemExit(f"{video}: cannot open video")
    frames = []
    i = 0
    while i <= last:
        ok, f = cap.read()
        if not ok:
            break
        if i >= first:
            frames.append(cv2.cvtColor(f, cv2.COLOR_BGR2RGB))
        i += 1
    return frames


def check(frames, runner, mre_fn, expect: int, post: PostConfig | None = None) -> dict:
    post = post or PostConfig()
    decoded = runner(frames)
    sizes = [(f.shape[1], f.shape[0]) for f in frames]
    dets = [postprocess(d, post, mre_fn, input_per_px(size, lay), size, looked, f)
            for d, size, lay, looked, f in zip(decoded, sizes, runner.layouts, runner.looked, frames)]
    blob = BlobDetector()
    ref = dets[0].marknet_mre[:, :2]
    pitch = dets[0].pitch_px
    r = 0.25 * pitch if np.isfinite(pitch) else 3.0
    rows = []
    for k, (img, det) in enumerate(zip(frames, dets)):
        pi, gi, d = match(det.marknet_mre[:, :2], ref, r)
        rows.append(
            {
                "frame": k,
                "marknet_mre": int(len(det.marknet_mre)),
                "marknet": int(len(det.marknet)),
                "blob": int(len(blob.detect(img))),
                "same_as_first": int(len(pi)),
                "mre_accepted": int(np.sum(det.mre_scores > post.accept)) if len(det.mre_scores) else 0,
            }
        )
    n = np.array([r_["marknet_mre"] for r_ in rows])
    same = np.array([r_["same_as_first"] for r_ in rows])
    return {
        "frames": len(rows),
        "expected": expect,
        "frames_with_all_found": int(((n == expect) & (same == expect)).sum()),
        "marknet_mre_count_min": int(n.min()),
        "marknet_mre_count_max": int(n.max()),
        "marknet_count_min": int(min(r_["marknet"] for r_ in rows)),
        "marknet_count_max": int(max(r_["marknet"] for r_ in rows)),
        "blob_count_min": int(min(r_["blob"] for r_ in rows)),
        "blob_count_max": int(max(r_["blob"] for r_ in rows)),
        "pitch_px_first_frame": float(pitch),
        "per_frame": rows,
    }, dets


def overlay(img: np.ndarray, det, path: Path) -> None:
    from PIL import Image, ImageDraw

    im = Image.fromarray(img).resize((img.shape[1] * 2, img.shape[0] * 2), Image.NEAREST)
    d = ImageDraw.Draw(im)
    for x, y, c in det.candidates:
        col = (0, 255, 0) if c > 0.4 else (255, 160, 0)
        X, Y = (x + 0.5) * 2 - 0.5, (y + 0.5) * 2 - 0.5
        d.ellipse((X - 3, Y - 3, X + 3, Y + 3), outline=col)
    for x, y, _ in det.marknet_mre:
        X, Y = (x + 0.5) * 2 - 0.5, (y + 0.5) * 2 - 0.5
        d.point((X, Y), fill=(255, 0, 0))
    im.save(path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--video", type=Path, required=True)
    p.add_argument("--marknet", type=Path, required=True)
    p.add_argument("--mre", type=Path, default=None)
    p.add_argument("--frames", default="0-55", help="first-last (inclusive)")
    p.add_argument("--expect", type=int, default=80)
    p.add_argument("--overlay", type=Path, default=None, help="PNG of the first frame's detections")
    p.add_argument("--out", type=Path, default=None, help="JSON report")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(2)
    first, last = (int(v) for v in args.frames.split("-"))
    frames = read_frames(args.video, first, last)
    res, dets = check(frames, MarknetRunner(args.marknet), load_mre(args.mre), args.expect)
    res["video"] = str(args.video)
    res["frame_range"] = args.frames
    print(json.dumps({k: v for k, v in res.items() if k != "per_frame"}, indent=1))
    if args.overlay:
        overlay(frames[0], dets[0], args.overlay)
    if args.out:
        args.out.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
