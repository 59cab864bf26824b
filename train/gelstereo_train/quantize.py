"""Quantize an exported Marknet to int8 with ONNX Runtime's static quantization.

    python -m gelstereo_train.quantize --model ../data/models/marknet.onnx --data DATA \
        --out marknet-int8.onnx [--format qdq|qoperator] [--images 96]

Static, per-channel int8 weights and uint8 activations; the activation ranges are calibrated on the
network inputs the Rust pipeline feeds it (the "auto" layout of each image at its ground-truth marker
pitch, docs/model-contract.md) for every n-th image of the dataset's `train` split (simulated frames
only: a calibration set drawn from the test split, or from real frames, would leak into the figures
measured on them). The model contract (metadata_props) is copied unchanged, so the Rust loader accepts
the quantized file in place of the float one; `quantized` records how it was made.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import onnx

from .data import list_samples, median_nn_distance
from .postprocess import fit_config_from_metadata, fit_layout, preprocess_layout


def calibration_inputs(model: onnx.ModelProto, data: Path, images: int, split: str = "train") -> list[np.ndarray]:
    """`images` network inputs (1, 3, H, W) float32 from the split, evenly spaced over its samples."""
    meta = {p.key: p.value for p in model.metadata_props}
    fit = fit_config_from_metadata(meta)
    samples = list_samples(data, split)
    if not samples:
        raise SystemExit(f"{data}/{split}: no images")
    picks = np.linspace(0, len(samples) - 1, min(images, len(samples))).round().astype(int)
    out = []
    for i in sorted(set(picks.tolist())):
        s = samples[i]
        rgb = s.load()
        pitch = median_nn_distance(s.points_px) if len(s.points_px) >= 2 else None
        lay = fit_layout(rgb.shape[1], rgb.shape[0], pitch, fit)
        out.append(preprocess_layout(rgb, lay).numpy().astype(np.float32))
    return out


def cropped_to_common_size(inputs: list[np.ndarray]) -> list[np.ndarray]:
    """`inputs` cut about their centres to the smallest height and width among them (multiples of the
    input multiple, as every layout is). ONNX Runtime's histogram calibrators (percentile, entropy)
    stack each tensor's values over all inputs and need them of one shape; MinMax does not."""
    h = min(x.shape[2] for x in inputs)
    w = min(x.shape[3] for x in inputs)
    out = []
    for x in inputs:
        top, left = (x.shape[2] - h) // 2, (x.shape[3] - w) // 2
        out.append(np.ascontiguousarray(x[:, :, top:top + h, left:left + w]))
    return out


class _Reader:
    """onnxruntime.quantization CalibrationDataReader over a list of inputs."""

    def __init__(self, inputs: list[np.ndarray]):
        self.inputs = iter(inputs)

    def get_next(self):
        x = next(self.inputs, None)
        return None if x is None else {"image": x}

    def rewind(self):  # pragma: no cover - the calibrators used here read the inputs once
        pass


FLOAT_PARTS = ("stem", "head")

# Every part `--keep-float` knows: the recipe's two and two more measured in the model card.
PARTS = ("stem", "head", "s4", "decoder")

# Node-name prefixes of the parts that are whole modules of `gelstereo_train.model.Marknet`: `s4` the
# stride-4 stage (the stem's convolution and the residual block after it), `decoder` the top-down path
# (the lateral reductions, upsampling, concatenations and fusing convolutions).
PART_PREFIXES = {"s4": ("/s4/",), "decoder": ("/reduce/", "/fuse1/", "/fuse2/", "/Resize", "/Concat")}


def check_parts(parts: tuple[str, ...]) -> None:
    """Raises ValueError naming any part `float_nodes` does not know."""
    unknown = sorted(set(parts) - set(PARTS))
    if unknown:
        raise ValueError(f"--keep-float: unknown part(s) {', '.join(unknown)}; expected some of {', '.join(PARTS)}")


def float_nodes(model: onnx.ModelProto, parts: tuple[str, ...]) -> list[str]:
    """Names of the nodes left in float. `stem`: the first convolution (it reads the 3-channel input;
    in int8 it is slower than in float, and it would need the input quantized first) and the
    activation after it. `head`: the 1x1 detection head and the reshape and transpose after it (int8
    logits move the decoded positions by ~0.3 px: one uint8 step of the logit range is ~0.1 in logit).
    `s4` and `decoder`: the nodes of those modules (`PART_PREFIXES`). `quantize` checks the parts."""
    graph_input = model.graph.input[0].name
    out = []
    if "stem" in parts:
        first = next(n for n in model.graph.node if graph_input in n.input)
        out.append(first.name)
        out += [n.name for n in model.graph.node if first.output[0] in n.input]
    if "head" in parts:
        out += [n.name for n in model.graph.node
                if n.name.startswith("/head/") or n.op_type in ("Reshape", "Transpose")]
    prefixes = tuple(x for part in parts for x in PART_PREFIXES.get(part, ()))
    if prefixes:
        out += [n.name for n in model.graph.node if n.name.startswith(prefixes)]
    return list(dict.fromkeys(out))


def quantize(model_path: Path, data: Path, out: Path, fmt: str = "qdq", images: int = 96,
             method: str = "percentile", keep_float: tuple[str, ...] = FLOAT_PARTS) -> dict:
    """Writes the quantized model to `out`; returns the metadata it added."""
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    check_parts(keep_float)
    model = onnx.load(str(model_path))
    inputs = calibration_inputs(model, data, images)
    if method != "minmax":
        inputs = cropped_to_common_size(inputs)
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(model_path), str(pre), skip_symbolic_shape=True)
        kept_float = float_nodes(onnx.load(str(pre)), keep_float)
        quantize_static(
            str(pre), str(out), _Reader(inputs),
            quant_format=QuantFormat.QDQ if fmt == "qdq" else QuantFormat.QOperator,
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            calibrate_method={"minmax": CalibrationMethod.MinMax,
                              "percentile": CalibrationMethod.Percentile,
                              "entropy": CalibrationMethod.Entropy}[method],
            nodes_to_exclude=kept_float,
            extra_options={"ActivationSymmetric": False, "WeightSymmetric": True},
        )
    q = onnx.load(str(out))
    floats = ", ".join(keep_float) or "nothing"
    added = {"quantized": f"int8 static per-channel {fmt} {method}, {len(inputs)} train-split inputs, "
             f"float: {floats}"}
    kept = {p.key: p.value for p in model.metadata_props}
    kept.update(added)
    del q.metadata_props[:]
    for k, v in kept.items():
        q.metadata_props.add(key=k, value=v)
    onnx.save(q, str(out))
    return added


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", type=Path, required=True, help="exported float Marknet (.onnx)")
    p.add_argument("--data", type=Path, required=True, help="simulated dataset (gelstereo simulate)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--format", choices=("qdq", "qoperator"), default="qdq")
    p.add_argument("--method", choices=("minmax", "percentile", "entropy"), default="percentile",
                   help="activation ranges: percentile (default: the 99.999th, ONNX Runtime's default) "
                        "placed markers closer to float than minmax")
    p.add_argument("--images", type=int, default=96, help="calibration inputs from the train split")
    p.add_argument("--keep-float", default=",".join(FLOAT_PARTS),
                   help="parts left in float, comma-separated from: " + ", ".join(PARTS) + " (empty: none)")
    args = p.parse_args(argv)
    keep_float = tuple(x for x in args.keep_float.split(",") if x)
    try:
        check_parts(keep_float)
    except ValueError as e:
        p.error(str(e))
    added = quantize(args.model, args.data, args.out, args.format, args.images, args.method, keep_float)
    print(f"wrote {args.out}: {added['quantized']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
