"""Post-processing of the YOLOv3 baseline (docs/model-contract.md, ``yolo.onnx``): a thin wrapper of the
Rust ``YoloLocalizer``'s own (``gelstereo.postprocess.yolo_postprocess``, from ``gelstereo_markers::yolo``).

For one image of W x H original pixels and a network input of w x h: decode every (head, cell, anchor)
of ``raw`` [K, 5] (gelstereo_train.yolo_model); keep those with objectness > ``conf_threshold``; map to
original pixels (``x = x_in * W / w - 0.5``, ``bw = w_in * W / w``, likewise y); greedy NMS in descending
objectness (ties: lower flat index first) at ``nms_iou``; the kept boxes' centres are the markers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gelstereo import postprocess as _rust

from .yolo_model import TW_CLAMP

_DEFAULT = _rust.default_yolo_post()


@dataclass
class YoloPost:
    """Thresholds (stored in the model's metadata_props). Defaults are the Rust ``YoloPost``'s, Darknet's
    detector defaults (``-thresh 0.25``, ``nms 0.45``); the shipped model may carry values chosen on the val split."""

    conf_threshold: float = _DEFAULT["conf_threshold"]
    nms_iou: float = _DEFAULT["nms_iou"]


def postprocess(raw: np.ndarray, input_hw, strides, anchors, image_wh, post: YoloPost) -> dict:
    """One image's ``candidates`` (n, 5: x, y, bw, bh, objectness in original px, flat order, above
    threshold) and ``markers`` (k, 3: x, y, confidence, in NMS keep order)."""
    raw = np.ascontiguousarray(raw, dtype=np.float32).reshape(-1, 5)
    anchors = np.asarray(anchors, np.float64).reshape(len(strides), -1, 2).tolist()
    return _rust.yolo_postprocess(raw, tuple(input_hw), [int(s) for s in strides], anchors, float(TW_CLAMP),
                                  tuple(image_wh), float(post.conf_threshold), float(post.nms_iou))
