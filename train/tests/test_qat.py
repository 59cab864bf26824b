"""Quantization-aware fine-tuning (`train_marknet --qat`): activations rounded as the int8 build rounds
them, while the model's weights and checkpoints stay those of the float network."""

import torch

from gelstereo_train import train_marknet
from gelstereo_train.model import Marknet
from gelstereo_train.qat import ActivationRounding


def test_rounding_puts_every_block_output_on_a_uint8_grid_and_comes_off_again():
    torch.manual_seed(0)
    m = Marknet(stride=8, candidates=2, width=4, stem="s4").train()
    keys = set(m.state_dict())
    x = torch.rand(2, 3, 64, 64)
    rounding = ActivationRounding(m)
    # 18 convolution blocks (the stride-4 stem and the three downsampling blocks, the two in each of
    # the four residual blocks, the top-down path's reduction and two fusing blocks per step), each
    # before and after its LeakyReLU; the four residual sums; the two concatenations.
    assert len(rounding) == 2 * 18 + 4 + 2
    seen = []
    hook = m.s8[0].register_forward_hook(lambda _m, _i, out: seen.append(out.detach()))
    m(x)
    hook.remove()
    # The hook that registered first rounds: the tensor later hooks see takes at most 256 values.
    assert seen[0].unique().numel() <= 256
    rounding.remove()
    exact = []
    hook = m.s8[0].register_forward_hook(lambda _m, _i, out: exact.append(out.detach()))
    m(x)
    hook.remove()
    assert exact[0].unique().numel() > 256
    assert set(m.state_dict()) == keys


def test_a_qat_run_writes_a_float_checkpoint_of_the_same_architecture(tiny_root, tmp_path):
    ck = tmp_path / "qat.pt"
    args = train_marknet.parser().parse_args(
        ["--data", str(tiny_root), "--out", str(ck), "--steps", "3", "--batch", "2", "--crop", "64",
         "--input-size", "128", "--width", "4", "--candidates", "3", "--stem", "s4", "--qat"])
    train_marknet.train(args, log=lambda *_: None)
    model, meta = train_marknet.load_checkpoint(ck)
    assert meta["args"]["qat"] is True and meta["steps"] == 3
    assert set(model.state_dict()) == set(Marknet(stride=8, candidates=3, width=4, stem="s4").state_dict())
