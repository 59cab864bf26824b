"""Export the YOLOv3 baseline to ONNX (contract ``gelstereo-yolo/1``, docs/model-contract.md) and check
it in onnxruntime against PyTorch.

    python -m gelstereo_train.yolo_export --checkpoint runs/yolo.pt --out data/models/yolo.onnx \
        [--conf-threshold 0.25] [--nms-iou 0.45]

torch.onnx.export(dynamo=False, opset 17), input ``image`` [N, 3, H, W] (the Marknet preprocessing),
output ``raw`` [N, K, 5] (gelstereo_train.yolo_model), a dynamic batch axis; anchors, strides and the
post-processing thresholds in metadata_props. The max abs difference onnxruntime vs PyTorch on random
inputs is printed (and written to ``--report`` with the metadata).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from .export import export_image_model
from .yolo_model import OUTPUTS_PER_ANCHOR, TW_CLAMP, YoloV3
from .yolo_post import YoloPost

YOLO_CONTRACT = "gelstereo-yolo/1"


def anchors_text(anchors: np.ndarray) -> str:
    """Anchors (heads, A, 2) as 'w,h w,h ...' (input pixels, heads in ascending stride), 6 significant
    digits (k-means anchors are rounded to 0.01 px, so this is exact)."""
    return " ".join(f"{w:.6g},{h:.6g}" for w, h in np.asarray(anchors, np.float64).reshape(-1, 2))


def parse_anchors(text: str) -> np.ndarray:
    """The metadata's anchor text back to (n, 2) f64: the exact values the Rust loader decodes with."""
    return np.array([[float(v) for v in pair.split(",")] for pair in text.split()], dtype=np.float64)


def box_description(diameter_frac) -> str:
    """The metadata's `box` text from a checkpoint's diameter_frac record (a number or min/median/max)."""
    if isinstance(diameter_frac, dict):
        span = f"{diameter_frac['min']:.3g}-{diameter_frac['max']:.3g}, median {diameter_frac['median']:.3g}"
    else:
        span = f"{float(diameter_frac):.3g}"
    return f"marker diameter = sensor dot/pitch ({span}) x local lattice spacing per axis"


def yolo_metadata(model: YoloV3, input_hw, dataset: str, trained: str, post: YoloPost, box: str) -> dict:
    """metadata_props of a yolo.onnx (all values become strings)."""
    h, w = input_hw
    return {
        "contract": YOLO_CONTRACT,
        "input_height": h,
        "input_width": w,
        "strides": ",".join(str(s) for s in model.strides),
        "anchors_per_head": model.anchors_per_head,
        "anchors": anchors_text(model.anchors.numpy()),
        "outputs_per_anchor": OUTPUTS_PER_ANCHOR,
        "tw_clamp": f"{TW_CLAMP:g}",
        "normalisation": "rgb/255",
        "layout": "NCHW",
        "resize": "bilinear, half-pixel centres, no antialiasing",
        "conf_threshold": f"{post.conf_threshold:g}",
        "nms_iou": f"{post.nms_iou:g}",
        "box": box,
        "dataset": dataset,
        "trained": trained,
    }


def export_yolo(model: YoloV3, path: Path, input_hw, metadata: dict, seed: int = 0) -> float:
    """Export and verify; returns the max abs difference onnxruntime vs PyTorch on ``raw``."""
    return export_image_model(model, Path(path), input_hw, metadata, seed)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", type=Path, required=True, help="yolo_train checkpoint (.pt)")
    p.add_argument("--out", type=Path, required=True, help="the .onnx file to write")
    p.add_argument("--conf-threshold", type=float, default=YoloPost.conf_threshold)
    p.add_argument("--nms-iou", type=float, default=YoloPost.nms_iou)
    p.add_argument("--report", type=Path, default=None, help="JSON file for the check and the metadata")
    args = p.parse_args(argv)
    from .yolo_train import load_checkpoint

    torch.set_num_threads(1)
    model, meta = load_checkpoint(args.checkpoint)
    hw = (int(meta["input_height"]), int(meta["input_width"]))
    post = YoloPost(args.conf_threshold, args.nms_iou)
    md = yolo_metadata(model, hw, meta["dataset"], meta["trained"], post, box_description(meta["diameter_frac"]))
    diff = export_yolo(model, args.out, hw, md)
    print(f"{args.out}: onnxruntime vs PyTorch max abs diff (raw) {diff:.3g}")
    if args.report:
        report = {"max_abs_diff": diff, "metadata": {k: str(v) for k, v in md.items()}}
        args.report.parent.mkdir(parents=True, exist_ok=True)
        args.report.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
