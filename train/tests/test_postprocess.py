import numpy as np
import pytest
import torch

from gelstereo_train.model import Marknet, decode
from gelstereo_train.postprocess import (
    MISSING_DISTANCE,
    PostConfig,
    decode_to_original,
    lattice_fit,
    postprocess,
    preprocess,
)


def test_decode_maps_input_to_original_pixels():
    raw = np.zeros((2, 3, 1, 3))  # sigmoid(0) = 0.5: cell centres
    out = decode_to_original(raw, 8, (48, 32), (24, 16))  # image 48x32, input 24x16: scale 2
    # cell (gy=1, gx=2): x_in = 2.5 * 8 = 20 -> x_orig = 20 * 2 - 0.5
    k = (1 * 3 + 2) * 1
    assert out[k].tolist() == pytest.approx([39.5, 12 * 2 - 0.5, 0.5])
    t = decode(torch.zeros(1, 2, 3, 1, 3), 8)
    assert t[0, 1, 2, 0].tolist() == pytest.approx([20.0, 12.0, 0.5])


def test_model_output_layout_and_shape():
    m = Marknet(stride=8, candidates=3, width=4).eval()
    y = m(torch.rand(2, 3, 64, 96))
    assert y.shape == (2, 8, 12, 3, 3)


def test_preprocess_resize_geometry_matches_half_pixel_convention():
    img = np.zeros((32, 32), np.uint8)
    img[:, 16:] = 255
    x = preprocess(img, (16, 16))
    assert x.shape == (1, 3, 16, 16)
    assert x[0, 0, 0].tolist() == pytest.approx([0] * 8 + [1] * 8)
    with pytest.raises(Exception, match="at least 16x16 px"):
        preprocess(img[:8, :8], (16, 16))


def test_postprocess_thresholds_and_mre_acceptance():
    g = np.stack(np.meshgrid(np.arange(6) * 10.0, np.arange(6) * 10.0), -1).reshape(-1, 2)
    conf = np.full(len(g), 0.9)
    conf[:3] = [0.3, 0.15, 0.05]
    dec = np.c_[g, conf]
    dec = np.r_[dec, [[10.5, 10.0, 0.35]]]  # a duplicate of a confident marker
    det = postprocess(dec, PostConfig(), mre_fn=lambda f: (f[:, 0] > 0.5).astype(float))
    assert det.pitch_px == pytest.approx(10.0)
    assert len(det.candidates) == 35  # 0.05 under conf_low, duplicate removed
    assert len(det.marknet) == 34  # 0.15 under conf_marknet_only
    assert len(det.marknet_mre) == 35  # both uncertain ones accepted by the toy MRE
    det2 = postprocess(dec, PostConfig(), mre_fn=lambda f: np.zeros(len(f)))
    assert len(det2.marknet_mre) == 33
    # The uncertain ones went to the MRE with their 10 nearest distances in pitches, then c.
    f = det.mre_features[np.isclose(det.candidates[det.mre_index, 2], 0.3)][0]
    assert f[:2].tolist() == pytest.approx([1.0, 1.0]) and f[10] == pytest.approx(0.3)
    assert np.isnan(postprocess(dec, PostConfig()).mre_scores).all()
    sparse = postprocess(np.array([[0.0, 0.0, 0.3], [30.0, 0.0, 0.9]]), PostConfig())
    assert (sparse.mre_features[0, 1:10] == MISSING_DISTANCE).all()


def test_the_defaults_and_constants_are_the_rust_localizers():
    from gelstereo.postprocess import default_post

    assert PostConfig().__dict__ == default_post()
    assert (PostConfig().conf_low, PostConfig().conf_keep, PostConfig().accept) == pytest.approx((0.1, 0.4, 0.99))


def test_bad_arrays_are_refused_with_the_expected_shape():
    with pytest.raises(ValueError, match="raw: expected shape"):
        decode_to_original(np.zeros((3, 3, 1, 3)), 8, (48, 32), (24, 16))
    with pytest.raises(ValueError, match="expected 1 scores, found 0"):
        postprocess(np.array([[0.0, 0.0, 0.3], [30.0, 0.0, 0.9]]), PostConfig(), mre_fn=lambda f: np.zeros(0))


def test_auto_layout_brings_the_pitch_into_range_and_decodes_back():
    from gelstereo.postprocess import probe_layout
    from gelstereo_train.postprocess import FitConfig, Layout, decode_layout, fit_layout, preprocess_layout

    # Reference sensor: 640x480, 16 px pitch -> inside the nominal 416 with a pitch of margin.
    lay = fit_layout(640, 480, 16.0)
    assert (lay.input_w, lay.input_h) == (416, 320) and 9.0 <= 16.0 * lay.scaled_w / 640 <= 24.0
    # A fine pitch is enlarged to the target, a coarse one shrunk; unknown pitch: no margin.
    assert fit_layout(800, 600, 10.0).scaled_w == round(800 * 1.2)
    assert fit_layout(320, 240, 31.0).scaled_w == round(320 * 12 / 31)
    assert (fit_layout(640, 480, None).scaled_w, fit_layout(640, 480, None).scaled_h) == (416, 312)
    assert fit_layout(100000, 50, 10.0, FitConfig()).input_w <= 2048
    # The probe doubles the nominal fit's scale: an 800x600 sensor whose 11 px pitch is 5.6 px at the
    # nominal 416x320 is looked at with 11.4 px, inside the trained range.
    probe = Layout(*probe_layout(800, 600, FitConfig()))
    assert (probe.scaled_w, probe.scaled_h) == (832, 624) and 9.0 <= 11.0 * probe.scaled_w / 800 <= 24.0
    assert probe_layout(100000, 50, FitConfig())[0] <= 2048
    # A marker whose centre is drawn at a known place comes back there through the layout.
    img = np.zeros((60, 80, 3), np.uint8)
    lay = fit_layout(80, 60, 13.0, FitConfig(nominal_hw=(64, 64)))
    x = preprocess_layout(img, lay)
    assert x.shape == (1, 3, lay.input_h, lay.input_w)
    stride, gx, gy = 8, 3, 2
    raw = np.full((lay.input_h // stride, lay.input_w // stride, 1, 3), -20.0)
    raw[gy, gx, 0] = [0.0, 0.0, 20.0]  # centre of cell (2, 3), confident
    out = decode_layout(raw, stride, (80, 60), lay)
    sx, sy = 80 / lay.scaled_w, 60 / lay.scaled_h
    want = [((gx + 0.5) * stride - lay.ox) * sx - 0.5, ((gy + 0.5) * stride - lay.oy) * sy - 0.5]
    hit = out[out[:, 2] > 0.5]
    assert len(hit) == 1 and hit[0, :2].tolist() == pytest.approx(want)
    # Nothing decoded in the mirrored border.
    assert ((out[:, 0] >= -0.5) & (out[:, 0] <= 79.5) & (out[:, 1] >= -0.5) & (out[:, 1] <= 59.5)).all()


def test_lattice_check_keeps_a_lattice_and_drops_scatter():
    """A square and a hexagonal lattice are all members, uniform random points are not a lattice, a
    lattice finer than 8 px at the input is none; the post-processing keeps a lattice's markers and
    drops a confident outlier off it."""
    square = np.array([(10 + 20.0 * c, 10 + 20.0 * r) for r in range(8) for c in range(10)])
    member, on, pitch, ok = lattice_fit(square, 1.0)
    assert member.all() and on.all() and ok and pitch == 20.0
    hexagonal = np.array([(20.0 * c + 10.0 * (r % 2), 20.0 * r * np.sqrt(3) / 2) for r in range(10) for c in range(12)])
    assert lattice_fit(hexagonal, 1.0)[0].all()
    scatter = np.random.default_rng(3).uniform(0, 640, (2000, 2))
    assert lattice_fit(scatter, 1.0)[0].sum() <= 20
    assert not lattice_fit(square, 0.3)[3]
    rows = np.column_stack([np.vstack([square, [[300.0, 45.0]]]), np.full(81, 0.9)])
    det = postprocess(rows, PostConfig(), input_per_px=1.0, image_wh=(220, 180))
    assert len(det.marknet) == 80 and not (det.marknet[:, 0] == 300.0).any()
    assert len(postprocess(rows, PostConfig(lattice=None), input_per_px=1.0).marknet) == 81
