"""Evaluate the YOLOv3 baseline with the paper's metrics (gelstereo_train.metrics), and choose its
objectness threshold on the validation split.

    python -m gelstereo_train.yolo_eval --data ROOT --split val --model runs/yolo.pt \
        --sweep 0.1,0.15,0.2,0.25,0.3,0.4,0.5 --out runs/yolo_val.json

The model is a yolo_train checkpoint (.pt) or an exported ``yolo.onnx`` (run in onnxruntime). The
network runs once per image; every threshold of ``--sweep`` is then post-processed (decoding + NMS,
the Rust localizer's, through gelstereo_train.yolo_post) and scored; ``best`` is the threshold of highest F1 over all markers. The
official Table I figures come from the Rust ``gelstereo eval``, not from this script.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from .blob import BlobDetector
from .data import list_samples
from .metrics import Evaluator, hard_mask, radius_for
from .postprocess import preprocess
from .runtime import ort_session
from .yolo_export import anchors_text, parse_anchors
from .yolo_post import YoloPost, postprocess


class YoloRunner:
    """Runs a checkpoint or ONNX file; ``raw(images)`` gives each image's raw [K, 5] output."""

    def __init__(self, path: Path | str, threads: int = 1):
        path = Path(path)
        self.path = path
        if path.suffix == ".onnx":
            self.sess = ort_session(path, threads)
            meta = self.sess.get_modelmeta().custom_metadata_map
            self.input_hw = (int(meta["input_height"]), int(meta["input_width"]))
            self.strides = [int(s) for s in meta["strides"].split(",")]
            self.anchors = parse_anchors(meta["anchors"])
            self.post = YoloPost(float(meta["conf_threshold"]), float(meta["nms_iou"]))
            self.model = None
        else:
            from .yolo_train import load_checkpoint

            self.model, meta = load_checkpoint(path)
            self.input_hw = (int(meta["input_height"]), int(meta["input_width"]))
            self.strides = list(self.model.strides)
            self.anchors = parse_anchors(anchors_text(self.model.anchors.numpy()))
            self.post = YoloPost()
            self.sess = None
        self.meta = meta

    def raw(self, images: list[np.ndarray]) -> np.ndarray:
        x = torch.cat([preprocess(im, self.input_hw) for im in images])
        if self.sess is not None:
            return self.sess.run(["raw"], {"image": x.numpy()})[0]
        with torch.no_grad():
            return self.model(x).numpy()

    def markers(self, raw: np.ndarray, image: np.ndarray, post: YoloPost) -> np.ndarray:
        """(k, 3) x, y, confidence in original pixels."""
        wh = (image.shape[1], image.shape[0])
        return postprocess(raw, self.input_hw, self.strides, self.anchors, wh, post)["markers"]


def evaluate(samples, runner: YoloRunner, thresholds, nms_iou: float, batch: int = 8, log=print) -> dict:
    """Metrics per threshold (and of the blob baseline for reference) over ``samples``."""
    ev = {t: Evaluator() for t in thresholds}
    ev_blob = Evaluator()
    blob = BlobDetector()
    t0 = time.time()
    for i in range(0, len(samples), batch):
        chunk = samples[i : i + batch]
        imgs = [s.load() for s in chunk]
        raws = runner.raw(imgs)
        for s, img, raw in zip(chunk, imgs, raws):
            gt = s.points_px
            r = radius_for(gt)
            bl = blob.detect(img)
            hard = hard_mask(bl, gt, r)
            size = (img.shape[1], img.shape[0])
            ev_blob.add_image(bl, gt, hard, s.in_contact, r, size)
            for t in thresholds:
                ev[t].add_image(runner.markers(raw, img, YoloPost(t, nms_iou)), gt, hard, s.in_contact, r, size)
        if (i // batch) % 25 == 0:
            log(f"evaluated {i + len(chunk)}/{len(samples)} images ({time.time() - t0:.0f} s)")
    out = {"thresholds": {}, "blob": ev_blob.summary(), "images": len(samples), "nms_iou": nms_iou}
    best, best_f1 = None, -1.0
    for t in thresholds:
        s = ev[t].summary()
        a = s["all"]
        f1 = 2 * a["precision"] * a["recall"] / (a["precision"] + a["recall"]) if a["PT"] else 0.0
        s["f1_all"] = f1
        out["thresholds"][f"{t:g}"] = s
        if f1 > best_f1:
            best, best_f1 = t, f1
    out["best"] = best
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--split", default="val")
    p.add_argument("--model", type=Path, required=True, help=".pt checkpoint or .onnx")
    p.add_argument("--sweep", default="0.25", help="comma-separated objectness thresholds")
    p.add_argument("--nms-iou", type=float, default=YoloPost.nms_iou)
    p.add_argument("--frame-step", type=int, default=1)
    p.add_argument("--max-experiments", type=int, default=None)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    runner = YoloRunner(args.model, args.threads)
    samples = list_samples(args.data, args.split, frame_step=args.frame_step, max_experiments=args.max_experiments)
    thresholds = [float(t) for t in args.sweep.split(",") if t.strip()]
    res = evaluate(samples, runner, thresholds, args.nms_iou)
    res["split"] = args.split
    res["model"] = str(args.model)
    for t, s in res["thresholds"].items():
        print(f"conf > {t}: " + "  ".join(
            f"{k} P {100 * s[k]['precision']:.2f}% R {100 * s[k]['recall']:.2f}% loss {s[k]['loss_px2']:.3f}"
            for k in ("easy", "hard", "contact", "all")) + f"  F1 {s['f1_all']:.4f}")
    print(json.dumps({"best": res["best"], "images": res["images"], "split": res["split"]}))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
