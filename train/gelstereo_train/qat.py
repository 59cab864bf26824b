"""Quantization-aware fine-tuning (`train_marknet --qat`): the network trains with its activations
rounded as ONNX Runtime's static int8 build rounds them (`gelstereo_train.quantize`: uint8, one scale
and zero point per tensor), so that its weights learn to place markers through that rounding.

Rounding the weights alone (int8 per output channel) moves the localization loss of the shipped model by
less than 2 %; rounding the activations is what costs it (docs: the model card's int8 section). So only
the activations are fake-quantized, where the int8 build stores a tensor as uint8: every convolution's
output before its LeakyReLU (BatchNorm folded in, as exported) and after it, every residual sum and
every concatenation of the top-down path. The
observers follow each tensor's range by a moving average, and the rounding passes gradients straight
through (PyTorch's `FakeQuantize`). The hooks hold no weights of the model: checkpoints and exports are
those of the float network, which `gelstereo_train.quantize` then builds into int8.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.ao.quantization import FakeQuantize, MovingAverageMinMaxObserver

from .model import Residual


def is_conv_block(m: nn.Module) -> bool:
    """A `model.conv_bn` block: convolution, BatchNorm, LeakyReLU."""
    kinds = [type(c) for c in m.children()] if isinstance(m, nn.Sequential) else []
    return kinds == [nn.Conv2d, nn.BatchNorm2d, nn.LeakyReLU]


def activation_fake_quant() -> FakeQuantize:
    """uint8, per tensor, asymmetric: the activations of the int8 build."""
    return FakeQuantize(observer=MovingAverageMinMaxObserver, quant_min=0, quant_max=255,
                        dtype=torch.quint8, qscheme=torch.per_tensor_affine, averaging_constant=0.01)


class ActivationRounding:
    """Fake-quantizes `model`'s activations through hooks: the outputs of the BatchNorm and of the
    whole of each convolution block, of each residual block, and the input of each top-down step's
    first fusing block (the concatenation). `remove()` takes them off again. The quantizers live
    here, not in the model, so its state dict is unchanged."""

    def __init__(self, model: nn.Module):
        self.quantizers = nn.ModuleList()
        self.handles = []
        for m in model.modules():
            if is_conv_block(m):
                self.round_output(m[1])
            if is_conv_block(m) or isinstance(m, Residual):
                self.round_output(m)
            if isinstance(m, nn.ModuleDict) and "fuse1" in m:
                fq = self.quantizer()
                self.handles.append(m["fuse1"].register_forward_pre_hook(lambda _m, inp, fq=fq: (fq(inp[0]),)))

    def quantizer(self) -> FakeQuantize:
        fq = activation_fake_quant()
        self.quantizers.append(fq)
        return fq

    def round_output(self, m: nn.Module) -> None:
        fq = self.quantizer()
        self.handles.append(m.register_forward_hook(lambda _m, _inp, out, fq=fq: fq(out)))

    def to(self, device) -> "ActivationRounding":
        self.quantizers.to(device)
        return self

    def __len__(self) -> int:
        return len(self.handles)

    def remove(self) -> None:
        for h in self.handles:
            h.remove()
        self.handles.clear()
