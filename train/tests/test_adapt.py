"""Pseudo-label support (`gelstereo adapt`): ignore masks follow the crop's geometry, leave the random
stream alone, silence only the negatives of ignored cells; the base architecture is read from an
exported file."""

from pathlib import Path

import numpy as np
import pytest
import torch

from gelstereo_train.adapt import base_architecture, compact
from gelstereo_train.augment import AugConfig, make_batch, make_batch_with_ignore, sample_crops
from gelstereo_train.export import export_marknet, marknet_metadata
from gelstereo_train.loss import build_targets, ignore_cells, marknet_loss
from gelstereo_train.model import Marknet
from gelstereo_train.postprocess import PostConfig
from gelstereo_train.tinydata import grid_points, render_dots

ROOT = Path(__file__).resolve().parents[2]


def _scene(seed=3):
    rng = np.random.default_rng(seed)
    pts, _, _ = grid_points(160, 200, 20.0, 7, 9)
    return render_dots(160, 200, pts, 5.0, rng), pts


def test_ignore_masks_do_not_change_the_crops():
    img, pts = _scene()
    rgb = np.repeat(img[..., None], 3, axis=2).astype(np.uint8) if img.ndim == 2 else img
    cfg = AugConfig(crop=(96, 96), input_size=(160, 160))
    mask = np.zeros(rgb.shape[:2], bool)
    torch.manual_seed(0)  # the noise augmentation draws from torch
    a = make_batch([rgb], [pts], np.array([20.0]), 4, cfg, np.random.default_rng(1))
    torch.manual_seed(0)
    b = make_batch_with_ignore([rgb], [pts], np.array([20.0]), 4, cfg, np.random.default_rng(1), ignore=[mask])
    assert torch.equal(a[0], b[0])
    assert all(np.array_equal(p, q) for p, q in zip(a[1], b[1]))
    assert b[2].shape == (4, 96, 96) and not b[2].any()


def test_the_ignore_mask_moves_with_the_image():
    """Ignore the left half of the source; with a flip-free, rotation-free stretch crop, the ignored
    crop pixels are exactly those whose source x is in the left half."""
    img, pts = _scene()
    rgb = np.repeat(img[..., None], 3, axis=2).astype(np.uint8) if img.ndim == 2 else img
    h, w = rgb.shape[:2]
    mask = np.zeros((h, w), bool)
    mask[:, : w // 2] = True
    cfg = AugConfig(crop=(h, w), input_size=(h, w), p_canonical=1.0, canonical="stretch")
    out: list = []
    x, labels = sample_crops([rgb], [pts], np.array([20.0]), np.array([0]), cfg, np.random.default_rng(0),
                             None, [mask], out)
    crop = out[0].numpy()
    assert crop[:, : w // 2].all() and not crop[:, w // 2:].any()
    # The same pixels as the image: the crop is the whole image at scale 1.
    assert np.abs(x[0].numpy().transpose(1, 2, 0) * 255 - rgb).max() < 1.0


def test_ignored_cells_lose_only_their_negatives():
    torch.manual_seed(0)
    raw = torch.randn(1, 4, 4, 2, 3)
    raw[0, 1, 1, :, 2] = 6.0  # a confident find in an empty cell: a false positive unless ignored
    labels = [np.array([[20.0, 20.0]], np.float32)]  # one marker, in cell (2, 2) at stride 8
    tgt, mask, _ = build_targets(labels, 4, 4, 8, 2)
    full = marknet_loss(raw, tgt, mask, 8)[1]
    ignore = torch.zeros(1, 4, 4, dtype=torch.bool)
    ignore[0, 1, 1] = True
    part = marknet_loss(raw, tgt, mask, 8, ignore=ignore)[1]
    assert part < full - 5.0
    # Ignoring the labelled cell keeps its positive slot.
    ignore_lab = torch.zeros(1, 4, 4, dtype=torch.bool)
    ignore_lab[0, 2, 2] = True
    with_pos = marknet_loss(raw, tgt, mask, 8, ignore=ignore_lab)[1]
    raw2 = raw.clone()
    raw2[0, 2, 2, 0, 2] = -8.0  # the positive slot made wrong: the loss must notice it
    assert marknet_loss(raw2, tgt, mask, 8, ignore=ignore_lab)[1] > with_pos + 5.0


def test_ignore_cells_take_any_ignored_pixel():
    m = torch.zeros(1, 16, 16, dtype=torch.bool)
    m[0, 9, 3] = True
    cells = ignore_cells(m, 8)
    assert cells.shape == (1, 2, 2) and cells[0, 1, 0] and cells.sum() == 1


def test_base_architecture_of_the_shipped_model():
    arch = base_architecture(ROOT / "data/models/marknet.onnx")
    assert (arch["stem"], arch["width"], arch["grid"], arch["candidates"]) == ("s4", 8, 52, 5)
    assert arch["canonical"] == "auto" and arch["input_hw"] == (416, 416)


@pytest.mark.parametrize("stem", ["s2", "s4", "s4-bare"])
def test_base_architecture_tells_the_stems_apart(stem, tmp_path):
    model = Marknet(stride=8, candidates=3, width=4, stem=stem).eval()
    path = tmp_path / "marknet.onnx"
    export_marknet(model, path, (128, 128), marknet_metadata(model, (128, 128), "tiny", "test", PostConfig()))
    arch = base_architecture(path)
    assert (arch["stem"], arch["width"], arch["candidates"], arch["fuse_kernel"]) == (stem, 4, 3, 3)


def test_base_architecture_tells_the_fusing_kernels_apart(tmp_path):
    model = Marknet(stride=8, candidates=3, width=4, stem="s4-bare", fuse_kernel=1).eval()
    path = tmp_path / "marknet.onnx"
    export_marknet(model, path, (128, 128), marknet_metadata(model, (128, 128), "tiny", "test", PostConfig()))
    assert base_architecture(path)["fuse_kernel"] == 1


def test_compact_frame_list():
    assert compact([20, 21, 22, 70, 72]) == "20-22, 70, 72"
    assert compact([]) == "none"
