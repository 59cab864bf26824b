"""Reference post-processing of the YOLOv3 baseline (docs/model-contract.md, ``yolo.onnx``); the Rust
``YoloLocalizer`` implements exactly this and is tested against fixtures written from it.

For one image of W x H original pixels and a network input of w x h:
1. decode every (head, cell, anchor) of ``raw`` [K, 5] (gelstereo_train.yolo_model), in f64;
2. keep those with objectness > ``conf_threshold``;
3. map to original pixels: ``x = x_in * W / w - 0.5``, ``y = y_in * H / h - 0.5``,
   ``bw = w_in * W / w``, ``bh = h_in * H / h``;
4. greedy NMS: visit in descending objectness (ties: lower flat index first), drop a box whose IoU with
   an already kept box is > ``nms_iou``;
5. the kept boxes' centres are the markers, their objectness the confidence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .yolo_model import OUTPUTS_PER_ANCHOR, TW_CLAMP


@dataclass
class YoloPost:
    """Thresholds (stored in the model's metadata_props). Defaults are Darknet's detector defaults
    (``-thresh 0.25``, ``nms 0.45``); the shipped model may carry values chosen on the val split."""

    conf_threshold: float = 0.25
    nms_iou: float = 0.45


def head_shapes(input_hw, strides) -> list[tuple[int, int]]:
    """(Gy, Gx) per head."""
    return [(input_hw[0] // s, input_hw[1] // s) for s in strides]


def decode_raw(raw: np.ndarray, input_hw, strides, anchors) -> np.ndarray:
    """raw [K, 5] of one image -> [K, 5] (x_in, y_in, w_in, h_in, objectness) in flat order, f64."""
    raw = np.asarray(raw, np.float64).reshape(-1, OUTPUTS_PER_ANCHOR)
    anchors = np.asarray(anchors, np.float64).reshape(len(strides), -1, 2)
    a_per = anchors.shape[1]
    out, off = [], 0
    for h, (s, (gy, gx)) in enumerate(zip(strides, head_shapes(input_hw, strides))):
        n = gy * gx * a_per
        r = raw[off : off + n].reshape(gy, gx, a_per, OUTPUTS_PER_ANCHOR)
        off += n
        sig = lambda v: 1.0 / (1.0 + np.exp(-v))  # noqa: E731
        xs = np.arange(gx).reshape(1, gx, 1)
        ys = np.arange(gy).reshape(gy, 1, 1)
        x = (sig(r[..., 0]) + xs) * s
        y = (sig(r[..., 1]) + ys) * s
        w = anchors[h, :, 0] * np.exp(np.clip(r[..., 2], -TW_CLAMP, TW_CLAMP))
        hh = anchors[h, :, 1] * np.exp(np.clip(r[..., 3], -TW_CLAMP, TW_CLAMP))
        out.append(np.stack([x, y, w, hh, sig(r[..., 4])], -1).reshape(-1, 5))
    if off != len(raw):
        raise ValueError(f"raw has {len(raw)} rows, the heads need {off}")
    return np.concatenate(out)


def iou_one_to_many(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """IoU of one (x, y, w, h) box with (n, 4) boxes."""
    x1 = np.maximum(box[0] - box[2] / 2, boxes[:, 0] - boxes[:, 2] / 2)
    x2 = np.minimum(box[0] + box[2] / 2, boxes[:, 0] + boxes[:, 2] / 2)
    y1 = np.maximum(box[1] - box[3] / 2, boxes[:, 1] - boxes[:, 3] / 2)
    y2 = np.minimum(box[1] + box[3] / 2, boxes[:, 1] + boxes[:, 3] / 2)
    inter = np.clip(x2 - x1, 0, None) * np.clip(y2 - y1, 0, None)
    union = box[2] * box[3] + boxes[:, 2] * boxes[:, 3] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def nms(boxes: np.ndarray, scores: np.ndarray, iou: float) -> np.ndarray:
    """Greedy NMS; returns the kept indices in visiting order (descending score, ties: lower index)."""
    order = np.lexsort((np.arange(len(scores)), -np.asarray(scores)))
    keep: list[int] = []
    for i in order:
        if keep and (iou_one_to_many(boxes[i], boxes[keep]) > iou).any():
            continue
        keep.append(int(i))
    return np.asarray(keep, np.int64)


def postprocess(raw: np.ndarray, input_hw, strides, anchors, image_wh, post: YoloPost) -> dict:
    """Steps 1-5 for one image. Returns ``candidates`` (n, 5: x, y, bw, bh, objectness in original px,
    flat order, above threshold) and ``markers`` (k, 3: x, y, confidence, in NMS keep order)."""
    dec = decode_raw(raw, input_hw, strides, anchors)
    sel = dec[dec[:, 4] > post.conf_threshold]
    sx = image_wh[0] / input_hw[1]
    sy = image_wh[1] / input_hw[0]
    cand = np.stack([sel[:, 0] * sx - 0.5, sel[:, 1] * sy - 0.5, sel[:, 2] * sx, sel[:, 3] * sy, sel[:, 4]], 1)
    keep = nms(cand[:, :4], cand[:, 4], post.nms_iou) if len(cand) else np.zeros(0, np.int64)
    return {"candidates": cand, "markers": cand[keep][:, [0, 1, 4]] if len(keep) else np.zeros((0, 3))}
