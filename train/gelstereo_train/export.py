"""Export Marknet and MRE to ONNX per docs/model-contract.md and check them in onnxruntime.

    python -m gelstereo_train.export --marknet runs/marknet.pt --mre runs/mre.pt --out-dir data/models

torch.onnx.export(dynamo=False, opset 17) with fixed names (image -> raw, features -> score), dynamic
batch (and, for Marknet, height and width) axes and the contract in metadata_props. Right after export each file is run in onnxruntime on
random inputs and compared with PyTorch; the max abs difference is printed and stored in a JSON report.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import onnx
import torch
from torch import nn

from .model import MRE, Marknet
from .runtime import ort_session
from .postprocess import MISSING_DISTANCE, NEIGHBOURS, FitConfig, PostConfig, fit_metadata

OPSET = 17
MARKNET_CONTRACT = "gelstereo-marknet/2"
MARKNET_CONTRACT_FIXED = "gelstereo-marknet/1"
MRE_CONTRACT = "gelstereo-mre/1"


class MREWithSigmoid(nn.Module):
    """The exported MRE: probability = sigmoid(logit)."""

    def __init__(self, mre: MRE):
        super().__init__()
        self.mre = mre

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.mre(features))


def _set_metadata(path: Path, props: dict) -> None:
    m = onnx.load(str(path))
    del m.metadata_props[:]
    for k, v in props.items():
        e = m.metadata_props.add()
        e.key, e.value = k, str(v)
    m.producer_name = "gelstereo-train"
    onnx.checker.check_model(m)
    onnx.save(m, str(path))


def marknet_metadata(model: Marknet, input_hw, dataset: str, trained: str, post: PostConfig,
                     fit: FitConfig | None = None, dynamic: bool = True) -> dict:
    """The contract's metadata_props: ``gelstereo-marknet/2`` (dynamic input, "auto" fit) or, with
    ``dynamic=False``, the fixed-input ``gelstereo-marknet/1`` (kept for the Rust loader's tests)."""
    h, w = input_hw
    fit = fit or FitConfig(nominal_hw=(h, w))
    return {
        **(fit_metadata(fit) if dynamic else {}),
        "contract": MARKNET_CONTRACT if dynamic else MARKNET_CONTRACT_FIXED,
        "input_height": h,
        "input_width": w,
        "stride": model.stride,
        "grid": w // model.stride,
        "candidates": model.candidates,
        "normalisation": "rgb/255",
        "layout": "NCHW",
        "resize": "bilinear, half-pixel centres, no antialiasing",
        "dataset": dataset,
        "trained": trained,
        "conf_keep": post.conf_keep,
        "conf_low": post.conf_low,
        "conf_marknet_only": post.conf_marknet_only,
        "dedup_radius_frac": post.dedup_radius_frac,
    }


def mre_metadata(dataset: str, post: PostConfig) -> dict:
    return {
        "contract": MRE_CONTRACT,
        "features": NEIGHBOURS + 1,
        "neighbours": NEIGHBOURS,
        "distance_unit": "pitch",
        "missing_distance": MISSING_DISTANCE,
        "accept": post.accept,
        "conf_low": post.conf_low,
        "conf_keep": post.conf_keep,
        "dataset": dataset,
    }


def export_marknet(model: Marknet, path: Path, input_hw, metadata: dict, seed: int = 0, dynamic: bool = True) -> float:
    """Export (dynamic input height and width: contract v2) and verify at the nominal size and at a
    non-square one; returns the max abs difference ONNX Runtime vs PyTorch on the raw output."""
    return export_image_model(model, path, input_hw, metadata, seed, dynamic_hw=dynamic)


def export_image_model(model: torch.nn.Module, path: Path, input_hw, metadata: dict, seed: int = 0,
                       dynamic_hw: bool = False) -> float:
    """Exports a network with the contract's `image` [N,3,H,W] -> `raw` [N,...] signature (Marknet, YOLO),
    writes `metadata` into metadata_props and checks it in ONNX Runtime on 2 random images (and, with a
    dynamic input, on a second, non-square size); returns the max abs difference against PyTorch."""
    model = model.eval()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = input_hw
    dummy = torch.rand(1, 3, h, w)
    torch.onnx.export(
        model,
        (dummy,),
        str(path),
        dynamo=False,
        opset_version=OPSET,
        input_names=["image"],
        output_names=["raw"],
        dynamic_axes=(
            {"image": {0: "batch", 2: "height", 3: "width"}, "raw": {0: "batch", 1: "grid_y", 2: "grid_x"}}
            if dynamic_hw
            else {"image": {0: "batch"}, "raw": {0: "batch"}}
        ),
        do_constant_folding=True,
    )
    _set_metadata(path, metadata)
    g = torch.Generator().manual_seed(seed)
    sess = ort_session(path)
    worst = 0.0
    for hh, ww in [(h, w), (h + 32, w + 64)] if dynamic_hw else [(h, w)]:
        x = torch.rand(2, 3, hh, ww, generator=g)
        with torch.no_grad():
            ref = model(x).numpy()
        got = sess.run(["raw"], {"image": x.numpy()})[0]
        if got.shape != ref.shape:
            raise RuntimeError(f"{path}: onnxruntime output shape {got.shape} != PyTorch {ref.shape}")
        worst = max(worst, float(np.abs(got - ref).max()))
    return worst


def export_mre(mre: MRE, path: Path, metadata: dict, seed: int = 0) -> float:
    """Export and verify the MRE; returns the max abs difference of the score."""
    wrapped = MREWithSigmoid(mre.eval()).eval()
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.onnx.export(
        wrapped,
        (torch.rand(4, NEIGHBOURS + 1),),
        str(path),
        dynamo=False,
        opset_version=OPSET,
        input_names=["features"],
        output_names=["score"],
        dynamic_axes={"features": {0: "batch"}, "score": {0: "batch"}},
    )
    _set_metadata(path, metadata)
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(64, NEIGHBOURS + 1, generator=g) * 3
    with torch.no_grad():
        ref = wrapped(x).numpy()
    got = ort_session(path).run(["score"], {"features": x.numpy()})[0]
    if got.shape != ref.shape:
        raise RuntimeError(f"{path}: onnxruntime output shape {got.shape} != PyTorch {ref.shape}")
    return float(np.abs(got - ref).max())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--marknet", type=Path, required=True, help="Marknet checkpoint (.pt)")
    p.add_argument("--mre", type=Path, default=None, help="MRE checkpoint (.pt)")
    p.add_argument("--out-dir", type=Path, required=True)
    p.add_argument("--preferred-layout", choices=("stretch", "isotropic"), default=None,
                   help="metadata preferred_layout (default: from the checkpoint's canonical crops)")
    args = p.parse_args(argv)
    from .train_marknet import load_checkpoint
    from .train_mre import load_mre_checkpoint

    torch.set_num_threads(2)
    model, meta = load_checkpoint(args.marknet)
    post = PostConfig()
    hw = (int(meta["input_height"]), int(meta["input_width"]))
    # The layout the net was trained on: its canonical crops (checkpoints before the option: stretch).
    preferred = args.preferred_layout or (
        "isotropic" if meta.get("aug", {}).get("canonical", "stretch") == "auto" else "stretch")
    fit = FitConfig(nominal_hw=hw, prefer_stretch=preferred == "stretch")
    report = {}
    mk = args.out_dir / "marknet.onnx"
    report["marknet_max_abs_diff"] = export_marknet(
        model, mk, hw, marknet_metadata(model, hw, meta["dataset"], meta["trained"], post, fit=fit)
    )
    print(f"{mk}: onnxruntime vs PyTorch max abs diff (raw logits) {report['marknet_max_abs_diff']:.3g}")
    if args.mre:
        mre, mmeta = load_mre_checkpoint(args.mre)
        mp = args.out_dir / "mre.onnx"
        report["mre_max_abs_diff"] = export_mre(mre, mp, mre_metadata(mmeta.get("dataset", meta["dataset"]), post))
        print(f"{mp}: onnxruntime vs PyTorch max abs diff (score) {report['mre_max_abs_diff']:.3g}")
    (args.out_dir / "export_report.json").write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
