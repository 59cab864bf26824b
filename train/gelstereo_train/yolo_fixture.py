"""Write the fixtures of the Rust YOLO localizer tests (crates/gelstereo-markers/src/yolo.rs):

    cd train && ../.venv/bin/python -m gelstereo_train.yolo_fixture --out-dir ../data/fixtures/onnx

* ``yolo_tiny.onnx``: a tiny YOLOv3 (width 2, strides 8 and 16, 3 anchors each, input 64 x 64),
  trained for a few hundred steps on a tiny rendered dot dataset (gelstereo_train.tinydata), with a
  low ``conf_threshold`` so that NMS has duplicates to remove;
* ``yolo_tiny_input.png``: an 80 x 60 image of dots (so the resize to 64 x 64 is anisotropic);
* ``yolo_tiny_expected.json``: the model's raw output on that image as onnxruntime computes it (input
  resized with OpenCV ``INTER_LINEAR`` from 8-bit, exactly as the Rust side does), the decoded
  candidates above the threshold (flat order), and the markers after NMS (keep order), from the
  Rust post-processing (gelstereo_train.yolo_post calls it): a regression snapshot of it.

Deterministic for a given torch build (seeded); the JSON records what it was made with.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from . import yolo_train
from .runtime import ort_session
from .tinydata import grid_points, render_dots, write_tiny_dataset
from .yolo_export import box_description, export_yolo, parse_anchors, yolo_metadata
from .yolo_post import YoloPost, postprocess

INPUT = 64
IMAGE_WH = (80, 60)
PITCH = 12.0
POST = YoloPost(conf_threshold=0.2, nms_iou=0.45)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out-dir", type=Path, required=True)
    p.add_argument("--steps", type=int, default=300)
    args = p.parse_args(argv)
    import cv2
    import onnxruntime as ort

    torch.set_num_threads(1)
    out = args.out_dir
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        root = write_tiny_dataset(Path(tmp) / "data", size_hw=(IMAGE_WH[1], IMAGE_WH[0]), pitch_px=PITCH, frames=3,
                                  experiments={"train": 4, "val": 1, "test": 1}, seed=3)
        ck = Path(tmp) / "yolo.pt"
        targs = yolo_train.parser().parse_args(
            ["--data", str(root), "--out", str(ck), "--steps", str(args.steps), "--batch", "8", "--crop", "64",
             "--input-size", str(INPUT), "--width", "2", "--lr", "1e-2", "--log-every-s", "1e9"]
        )
        yolo_train.train(targs, log=lambda *_: None)
        model, meta = yolo_train.load_checkpoint(ck)
    meta_props = yolo_metadata(model, (INPUT, INPUT), "tinydata fixture (gelstereo_train.yolo_fixture)",
                               meta["trained"][:10], POST, box_description(meta["diameter_frac"]))
    onnx_path = out / "yolo_tiny.onnx"
    diff = export_yolo(model, onnx_path, (INPUT, INPUT), meta_props)

    rng = np.random.default_rng(7)
    w, h = IMAGE_WH
    rows, cols = int(h // PITCH) - 1, int(w // PITCH) - 1
    pts, _, _ = grid_points(h, w, PITCH, rows, cols, press=(w * 0.55, h * 0.5, PITCH * 1.5, PITCH * 0.4))
    img = render_dots(h, w, pts, PITCH * 0.28, rng)
    png = out / "yolo_tiny_input.png"
    Image.fromarray(img).save(png)
    # The Rust preprocessing: 8-bit BGR -> cv::resize INTER_LINEAR -> RGB / 255 planar.
    rgb = np.asarray(Image.open(png).convert("RGB"))
    resized = cv2.resize(rgb, (INPUT, INPUT), interpolation=cv2.INTER_LINEAR)
    x = (resized.astype(np.float32) / 255.0).transpose(2, 0, 1)[None]
    raw = ort_session(onnx_path, threads=1).run(["raw"], {"image": x})[0][0]
    anchors = parse_anchors(meta_props["anchors"])  # what the Rust loader reads
    res = postprocess(raw, (INPUT, INPUT), list(model.strides), anchors, IMAGE_WH, POST)
    cand, markers = res["candidates"], res["markers"]
    if not (len(cand) > len(markers) > 0):
        raise SystemExit(f"fixture does not exercise NMS: {len(cand)} candidates, {len(markers)} markers")
    expected = {
        "origin": "train/gelstereo_train/yolo_fixture.py (post-processing: gelstereo_markers::yolo)",
        "torch": torch.__version__,
        "onnxruntime": ort.__version__,
        "opencv_python": cv2.__version__,
        "onnx_vs_torch_max_abs_diff": diff,
        "image": png.name,
        "image_width": w,
        "image_height": h,
        "input_width": INPUT,
        "input_height": INPUT,
        "strides": list(model.strides),
        "anchors": anchors.tolist(),
        "conf_threshold": POST.conf_threshold,
        "nms_iou": POST.nms_iou,
        "raw_shape": list(raw.shape),
        "raw": [float(v) for v in raw.reshape(-1)],
        "candidates": [[float(v) for v in c] for c in cand],
        "markers": [[float(v) for v in m] for m in markers],
        "ground_truth": pts.tolist(),
    }
    (out / "yolo_tiny_expected.json").write_text(json.dumps(expected) + "\n")
    sizes = {f.name: f.stat().st_size for f in (onnx_path, png, out / "yolo_tiny_expected.json")}
    print(f"wrote {sizes} ({sum(sizes.values())} bytes); {len(cand)} candidates -> {len(markers)} markers, "
          f"{len(pts)} dots; onnx vs torch {diff:.2g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
