"""Warm start from an exported Marknet ONNX file (the shipped models keep no PyTorch checkpoint).

The export folds every BatchNorm into the convolution before it (weight and a bias). To train on,
the folded weights go back into the convolutions and each BatchNorm is *re-inflated* so that the
network computes exactly the exported function: with the per-channel mean ``mu`` and variance
``var`` of the convolution's output measured on training crops, ``running_mean = mu``,
``running_var = var``, ``weight = sqrt(var + eps)``, ``bias = b + mu`` gives
``BN(x) = x + b`` in evaluation mode, and close to it in training mode (batch statistics near
``mu``, ``var``), so fine-tuning starts from the exported model rather than from a disturbed one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from .model import Marknet


def _onnx_convs(path: Path) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """(weight, bias) of every Conv node, in graph order."""
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(path))
    inits = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    out = []
    for node in model.graph.node:
        if node.op_type != "Conv":
            continue
        w = inits.get(node.input[1])
        b = inits.get(node.input[2]) if len(node.input) > 2 else None
        if w is None:
            raise SystemExit(f"{path}: Conv node {node.name} has no constant weight")
        out.append((w, b))
    return out


def _convs_in_forward_order(model: nn.Module, size: int = 64) -> list[nn.Conv2d]:
    order: list[nn.Conv2d] = []
    hooks = [m.register_forward_hook(lambda mod, i, o: order.append(mod))
             for m in model.modules() if isinstance(m, nn.Conv2d)]
    with torch.no_grad():
        model.eval()(torch.zeros(1, 3, size, size))
    for h in hooks:
        h.remove()
    return order


def _bn_after(model: nn.Module) -> dict[nn.Conv2d, nn.BatchNorm2d]:
    """The BatchNorm that follows each convolution inside a conv_bn block."""
    pairs = {}
    for m in model.modules():
        if isinstance(m, nn.Sequential):
            kids = list(m.children())
            for a, b in zip(kids, kids[1:]):
                if isinstance(a, nn.Conv2d) and isinstance(b, nn.BatchNorm2d):
                    pairs[a] = b
    return pairs


def load_onnx_weights(model: Marknet, path: Path, calibration_batches: list[torch.Tensor]) -> dict:
    """Copies an exported Marknet's weights into `model` (same architecture) and re-inflates its
    BatchNorms from `calibration_batches` (network inputs, N x 3 x H x W). Returns a record for the
    checkpoint's metadata, with the largest difference between the re-inflated model (evaluation
    mode) and ONNX Runtime on the first calibration batch."""
    convs = _convs_in_forward_order(model)
    folded = _onnx_convs(path)
    if len(folded) != len(convs):
        raise SystemExit(f"--init {path}: {len(folded)} convolutions in the ONNX graph, the model asked "
                         f"for has {len(convs)} (give the same --stem, --width, --grid, --candidates)")
    bns = _bn_after(model)
    with torch.no_grad():
        for conv, (w, b) in zip(convs, folded):
            if tuple(conv.weight.shape) != w.shape:
                raise SystemExit(f"--init {path}: convolution weight {w.shape} where the model has "
                                 f"{tuple(conv.weight.shape)}")
            conv.weight.copy_(torch.from_numpy(np.array(w)))
            bias = torch.zeros(w.shape[0]) if b is None else torch.from_numpy(np.array(b))
            if conv.bias is not None:
                conv.bias.copy_(bias)
            elif conv in bns:
                bn = bns[conv]
                bn.running_mean.zero_()
                bn.running_var.fill_(1.0 - bn.eps)
                bn.weight.fill_(1.0)
                bn.bias.copy_(bias)
            else:
                raise SystemExit(f"--init {path}: a convolution without bias or BatchNorm")
        # Statistics of each convolution's output under the exported function.
        sums = {c: [0.0, 0.0, 0] for c in bns}

        def record(mod, inp, out):
            s = sums[mod]
            s[0] = s[0] + out.sum(dim=(0, 2, 3))
            s[1] = s[1] + (out * out).sum(dim=(0, 2, 3))
            s[2] += out.shape[0] * out.shape[2] * out.shape[3]

        hooks = [c.register_forward_hook(record) for c in bns]
        model.eval()
        for x in calibration_batches:
            model(x)
        for h in hooks:
            h.remove()
        for conv, bn in bns.items():
            s1, s2, n = sums[conv]
            mu = s1 / n
            var = (s2 / n - mu * mu).clamp_min(1e-6)
            shift = bn.bias.clone()
            bn.running_mean.copy_(mu)
            bn.running_var.copy_(var)
            bn.weight.copy_((var + bn.eps).sqrt())
            bn.bias.copy_(shift + mu)
    diff = _max_difference(model, path, calibration_batches[0][:2])
    return {"path": str(path), "onnx": True, "max_abs_diff_vs_onnx": diff}


def _max_difference(model: Marknet, path: Path, x: torch.Tensor) -> float:
    import onnxruntime as ort

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    name = sess.get_inputs()[0].name
    ref = sess.run(None, {name: x.contiguous().numpy()})[0]
    with torch.no_grad():
        got = model.eval()(x.contiguous()).numpy()
    return float(np.abs(got - ref).max())
