"""gelstereo.postprocess: the localizer's layout, decoding and post-processing for the trainer's own
networks, and its passes up to the post-processing."""

from pathlib import Path

import cv2
import numpy as np
import pytest

import gelstereo
from gelstereo import postprocess as pp

FIX = Path(__file__).resolve().parents[3] / "data" / "fixtures" / "onnx"


class Fit:
    nominal_hw = (64, 64)
    multiple = 32
    pitch_range_px = (9.0, 24.0)
    pitch_target_px = 12.0
    prefer_stretch = False


class Post:
    def __init__(self, **kw):
        self.__dict__.update(pp.default_post() | kw)


def test_the_passes_give_candidates_in_the_image_and_the_layout_they_ran_under():
    net = pp.Marknet(str(FIX / "marknet_tiny_auto.onnx"), post=Post(lattice=False, dedup_radius_frac=0.6))
    assert (net.stride, net.input_width, net.input_height) == (8, 64, 64)
    image = cv2.imread(str(FIX / "dots_160x120.png"), cv2.IMREAD_COLOR)
    [(found, layout, looked)] = net.fitted([image])
    assert found.shape[1] == 3 and (found[:, 2] > 0.1).all() and looked is None
    assert ((found[:, 0] >= -0.5) & (found[:, 0] <= 159.5) & (found[:, 1] >= -0.5) & (found[:, 1] <= 119.5)).all()
    # the same network run by hand under that layout decodes to the same candidates
    import onnxruntime as ort

    sess = ort.InferenceSession(str(FIX / "marknet_tiny_auto.onnx"), providers=["CPUExecutionProvider"])
    raw = sess.run(["raw"], {"image": pp.network_input(image, layout)})[0][0]
    mine = pp.decode(raw, net.stride, 160, 120, layout)
    np.testing.assert_allclose(mine[mine[:, 2] > 0.1], found, atol=1e-4)
    assert pp.fit_layout(160, 120, None, Fit())[0] % 32 == 0


def test_the_mre_decides_the_uncertain_candidates_and_bad_input_is_refused():
    g = np.stack(np.meshgrid(np.arange(6) * 10.0, np.arange(6) * 10.0), -1).reshape(-1, 2)
    rows = np.c_[g, np.full(len(g), 0.9)]
    rows[0, 2] = 0.3
    out = pp.postprocess(rows, Post(), mre=lambda f: [1.0] * len(f))
    assert len(out["marknet_mre"]) == 36 and out["mre_features"].shape == (1, pp.MRE_FEATURES)
    assert len(pp.postprocess(rows, Post(), mre=lambda f: [0.0] * len(f))["marknet_mre"]) == 35
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        pp.postprocess(rows[:, :2].copy(), Post())
    with pytest.raises(gelstereo.GelstereoError):
        pp.Marknet(str(FIX / "mre_tiny.onnx"))
