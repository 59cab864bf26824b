"""The committed Rust fixtures (data/fixtures/onnx, made by scripts/make_onnx_fixtures.py) must agree
with what onnxruntime computes from the committed files, through the post-processing this package
calls (the Rust localizer's, gelstereo.postprocess)."""

import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from gelstereo_train.data import load_rgb
from gelstereo_train.postprocess import PostConfig, decode_to_original, postprocess, preprocess

FIX = Path(__file__).resolve().parents[2] / "data" / "fixtures" / "onnx"


@pytest.fixture(scope="module")
def expected():
    return json.loads((FIX / "expected.json").read_text())


MINE = ("marknet_tiny.onnx", "mre_tiny.onnx", "dots_64x64.png", "dots_80x60.png", "expected.json", "README.md")


def test_fixture_files_are_small():
    assert sum((FIX / f).stat().st_size for f in MINE) < 200 * 1024


def test_marknet_fixture_matches_expected(expected):
    sess = ort.InferenceSession(str(FIX / "marknet_tiny.onnx"), providers=["CPUExecutionProvider"])
    props = {p.key: p.value for p in onnx.load(str(FIX / "marknet_tiny.onnx")).metadata_props}
    assert props == expected["marknet_metadata"]
    hw = (int(props["input_height"]), int(props["input_width"]))
    mre = ort.InferenceSession(str(FIX / "mre_tiny.onnx"), providers=["CPUExecutionProvider"])
    post = PostConfig(**expected["post"])
    for name, e in expected["images"].items():
        img = load_rgb(FIX / name)
        raw = sess.run(["raw"], {"image": preprocess(img, hw).numpy()})[0][0]
        assert list(raw.shape) == e["raw_shape"]
        # the fixture's tolerances: without a resize, ONNX Runtime vs the PyTorch that wrote the file; with
        # one, also the localizer's resize of the 8-bit image against PyTorch's of the float one
        resized = (img.shape[1], img.shape[0]) != hw[::-1]
        logit, px, conf = (0.05, 0.05, 0.01) if resized else (1e-4, 1e-4, 1e-4)
        assert np.abs(raw.reshape(-1) - np.array(e["raw"])).max() < logit
        dec = decode_to_original(raw, int(props["stride"]), (img.shape[1], img.shape[0]), hw[::-1])
        assert np.abs(dec[:, :2] - np.array(e["decoded"])[:, :2]).max() < px
        assert np.abs(dec[:, 2] - np.array(e["decoded"])[:, 2]).max() < conf
        det = postprocess(dec, post, lambda f: mre.run(["score"], {"features": f})[0][:, 0])
        assert det.pitch_px == pytest.approx(e["pitch_px"], abs=px)
        assert len(det.marknet) == len(e["marknet"]) and len(det.marknet_mre) == len(e["marknet_mre"])
        assert len(det.candidates) == len(e["kept"]) and len(det.mre_index) == len(e["mre_features"])
        # the Rust outputs are sorted by y, then x; the fixture's rows by descending confidence
        got, want = (a[np.lexsort((a[:, 0], a[:, 1]))] for a in (det.marknet_mre, np.array(e["marknet_mre"]).reshape(-1, 3)))
        assert np.abs(got[:, :2] - want[:, :2]).max() < px and np.abs(got[:, 2] - want[:, 2]).max() < conf


def test_mre_fixture_rows(expected):
    mre = ort.InferenceSession(str(FIX / "mre_tiny.onnx"), providers=["CPUExecutionProvider"])
    f = np.array(expected["mre_rows"]["features"], np.float32)
    got = mre.run(["score"], {"features": f})[0][:, 0]
    assert np.abs(got - np.array(expected["mre_rows"]["scores"])).max() < 1e-5
