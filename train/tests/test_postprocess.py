import numpy as np
import pytest
import torch

from gelstereo_train.model import Marknet, decode
from gelstereo_train.postprocess import (
    CLOSE_LOOK_MARGIN_PITCH,
    CLOSE_LOOK_ZOOM,
    MISSING_DISTANCE,
    LatticeCheck,
    PostConfig,
    close_look_zoom,
    decode_to_original,
    dedup,
    keep_the_lattice,
    merge_close_look,
    mre_features,
    postprocess,
    preprocess,
    squeezed_region,
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
    img = np.zeros((8, 8), np.uint8)
    img[:, 4:] = 255
    x = preprocess(img, (4, 4))
    assert x.shape == (1, 3, 4, 4)
    assert x[0, 0, 0].tolist() == pytest.approx([0, 0, 1, 1])


def test_dedup_keeps_the_most_confident_of_close_pairs():
    c = np.array([[0, 0, 0.5], [0.5, 0, 0.9], [10, 0, 0.3], [10.2, 0.1, 0.3]])
    kept = dedup(c, 1.0)
    assert kept.tolist() == [1, 2]  # ties: lower index first


def test_mre_features_sorted_scaled_and_padded():
    kept = np.array([[0, 0, 0.9], [3, 0, 0.8], [0, 4, 0.3]])
    f = mre_features(kept, 2.0, np.array([2]))
    assert f.shape == (1, 11)
    assert f[0, :2].tolist() == pytest.approx([2.0, 2.5])
    assert (f[0, 2:10] == MISSING_DISTANCE).all() and f[0, 10] == pytest.approx(0.3)


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


def test_auto_layout_brings_the_pitch_into_range_and_decodes_back():
    from gelstereo_train.postprocess import FitConfig, decode_layout, fit_layout, preprocess_layout, probe_layout

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
    probe = probe_layout(800, 600, FitConfig())
    assert (probe.scaled_w, probe.scaled_h) == (832, 624) and 9.0 <= 11.0 * probe.scaled_w / 800 <= 24.0
    assert probe_layout(100000, 50, FitConfig()).input_w <= 2048
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
    """The Python twin of gelstereo_markers::lattice: a square and a hexagonal lattice are all members,
    uniform random points are not a lattice, a lattice finer than 8 px at the input is none."""
    from gelstereo_train.postprocess import LatticeCheck, keep_the_lattice, lattice_fit

    square = np.array([(10 + 20.0 * c, 10 + 20.0 * r) for r in range(8) for c in range(10)])
    member, on, pitch, ok = lattice_fit(square, LatticeCheck(), 1.0)
    assert member.all() and ok and pitch == 20.0
    hexagonal = np.array([(20.0 * c + 10.0 * (r % 2), 20.0 * r * np.sqrt(3) / 2) for r in range(10) for c in range(12)])
    assert lattice_fit(hexagonal, LatticeCheck(), 1.0)[0].all()
    scatter = np.random.default_rng(3).uniform(0, 640, (2000, 2))
    assert lattice_fit(scatter, LatticeCheck(), 1.0)[0].sum() <= 20
    assert not lattice_fit(square, LatticeCheck(), 0.3)[3]
    rows = np.column_stack([np.vstack([square, [[300.0, 45.0]]]), np.full(81, 0.9)])
    kept = keep_the_lattice(rows, LatticeCheck(), 1.0)
    assert len(kept) == 80 and not (kept[:, 0] == 300.0).any()


def test_the_lattice_check_moves_up_unsure_candidates_at_empty_sites_and_drops_texture_patches():
    """The Python twin of the Rust lattice tests: an unsure candidate at an empty interior or edge site
    joins the markers, one at a taken site, past the edge or at a cell centre does not; a patch lined up
    at a finer spacing beside the lattice is no member."""
    from gelstereo_train.postprocess import LatticeCheck, keep_the_lattice, lattice_fit

    holes = {(90.0, 70.0), (190.0, 70.0)}
    lattice = np.array([(10 + 20.0 * c, 10 + 20.0 * r) for r in range(8) for c in range(10)
                        if (10 + 20.0 * c, 10 + 20.0 * r) not in holes])
    rows = np.column_stack([lattice, np.full(len(lattice), 0.99)])
    unsure = np.array([[91.0, 69.0, 0.3], [189.0, 71.0, 0.3], [88.0, 71.0, 0.2], [52.0, 50.0, 0.35],
                       [210.0, 50.0, 0.3], [100.0, 80.0, 0.3]])
    kept = keep_the_lattice(rows, LatticeCheck(), 1.0, unsure=unsure)
    assert len(kept) == len(lattice) + 2
    for x, y in [(91.0, 69.0), (189.0, 71.0)]:
        assert ((kept[:, 0] == x) & (kept[:, 1] == y)).any()

    markers = np.array([(10 + 16.0 * c, 10 + 16.0 * r) for r in range(10) for c in range(12)])
    speckle = np.array([(310 + 7.0 * c, 210 + 7.0 * r) for r in range(5) for c in range(5)])
    member = lattice_fit(np.vstack([markers, speckle]), LatticeCheck(), 1.0)[0]
    assert member[:120].all() and not member[120:].any()


def test_unsure_dots_the_image_border_cuts_the_lattice_at_join_and_those_past_its_end_do_not():
    """The Python twin of the Rust test of the same name: unsure dots of the top row (the corner and two
    side by side), each the end of its lines, join when the next site up lies outside the image; unsure
    finds one pitch past the lattice's last row and column, inside the image, do not."""
    from gelstereo_train.postprocess import LatticeCheck, keep_the_lattice

    grid = [(6 + 20.0 * c, 6 + 20.0 * r) for r in range(8) for c in range(10)]
    missed = {(6.0, 6.0), (66.0, 6.0), (86.0, 6.0)}
    found = np.array([p for p in grid if p not in missed])
    rows = np.column_stack([found, np.full(len(found), 0.99)])
    unsure = np.array([[x + 0.5, y - 0.5, 0.3] for x, y in sorted(missed)])
    assert len(keep_the_lattice(rows, LatticeCheck(), 1.0, unsure=unsure, image_wh=(200, 170))) == 80
    assert len(keep_the_lattice(rows, LatticeCheck(), 1.0, unsure=unsure)) == len(found)
    every = np.column_stack([np.array(grid), np.full(len(grid), 0.99)])
    past = np.array([[6 + 20.0 * c, 166.0, 0.3] for c in range(10)]
                    + [[206.0, 6 + 20.0 * r, 0.3] for r in range(1, 7)])
    assert len(keep_the_lattice(every, LatticeCheck(), 1.0, unsure=past, image_wh=(260, 200))) == 80


def test_a_sure_find_one_step_past_the_lattice_joins_inside_the_image_and_no_further():
    """The Python twin of the Rust test of the same name: a sure find one step past the last column (the
    end of its row) joins in a roomy image; an unsure one there, a sure one two steps past or between four
    markers do not; within half a pitch of the border, or without the image's size, none joins."""
    from gelstereo_train.postprocess import LatticeCheck, keep_the_lattice

    lattice = np.array([(10 + 20.0 * c, 10 + 20.0 * r) for r in range(8) for c in range(10)])
    rows = np.column_stack([lattice, np.full(len(lattice), 0.99)])
    second = np.array([[210.5, 70.0, 0.8], [209.5, 90.0, 0.3], [230.0, 110.0, 0.9], [100.0, 80.0, 0.9]])
    kept = keep_the_lattice(rows, LatticeCheck(), 1.0, unsure=second, image_wh=(300, 200))
    assert len(kept) == 81 and ((kept[:, 0] == 210.5) & (kept[:, 1] == 70.0)).any()
    assert len(keep_the_lattice(rows, LatticeCheck(), 1.0, unsure=second, image_wh=(218, 200))) == 80
    assert len(keep_the_lattice(rows, LatticeCheck(), 1.0, unsure=second)) == 80


def test_an_irregular_lattice_the_network_is_sure_of_is_kept_and_doubtful_spacing_is_not():
    """The Python twin of the Rust test: hand-placed dots (a 12 x 10 lattice of pitch 20, each moved up
    to a quarter pitch per axis) are a lattice by their spacing when the network is sure of them; the
    same places with a doubtful confidence are not (a blurred texture's extrema keep a spacing too)."""
    from gelstereo_train.postprocess import LatticeCheck, lattice_fit

    rng = np.random.default_rng(1)
    for _ in range(5):
        pts = np.array([(10 + 20.0 * c, 10 + 20.0 * r) for r in range(10) for c in range(12)])
        pts = pts + rng.uniform(-5.0, 5.0, pts.shape)
        member, _, pitch, ok = lattice_fit(pts, LatticeCheck(), 1.0, np.full(len(pts), 0.99))
        assert ok and member.sum() >= 108 and 15.0 < pitch < 21.0
        assert lattice_fit(pts, LatticeCheck(), 1.0, np.full(len(pts), 0.6))[0].sum() < 60


def test_large_reductions_average_areas_and_mild_ones_stay_bilinear():
    """Rust twin: marknet::write_layout. Below AREA_BELOW_SCALE the scaled image is the 8-bit area
    average (cv2.INTER_AREA) / 255; at a mild reduction it is the bilinear resize of rgb / 255."""
    import cv2
    import torch.nn.functional as F
    from gelstereo_train.postprocess import AREA_BELOW_SCALE, Layout, preprocess_layout

    rgb = np.zeros((300, 400, 3), dtype=np.uint8)
    rgb[::4] = 200  # scan lines: every 4th row bright
    rgb[1::4] = 200
    small = Layout(64, 64, 40, 30, 12, 17)  # 0.1 x
    assert 40 / 400 < AREA_BELOW_SCALE
    x = preprocess_layout(rgb, small)[0, :, 17:47, 12:52].numpy()
    area = cv2.resize(rgb, (40, 30), interpolation=cv2.INTER_AREA).transpose(2, 0, 1) / 255.0
    assert np.allclose(x, area, atol=1e-6)
    assert 90 < x.mean() * 255 < 110  # the banding averages to its mean; bilinear sampling would alias
    mild = Layout(224, 160, 200, 150, 12, 5)  # 0.5 x
    x = preprocess_layout(rgb, mild)[0, :, 5:155, 12:212]
    t = torch.from_numpy(rgb).permute(2, 0, 1).float()[None] / 255.0
    bilinear = F.interpolate(t, size=(150, 200), mode="bilinear", align_corners=False, antialias=False)[0]
    assert torch.allclose(x, bilinear, atol=1e-6)


def test_markers_reported_at_the_very_edge_are_dropped_as_in_rust():
    from gelstereo_train.postprocess import inside_the_edge

    # Pitch 25 px: the margin is 0.5 px (the Rust test's points).
    near = np.array([[0.3, 100.0, 1.0], [150.0, -0.2, 1.0], [318.6, 50.0, 1.0], [60.0, 238.7, 1.0]])
    far = np.array([[0.6, 100.0, 1.0], [150.0, 0.5, 1.0], [318.4, 50.0, 1.0], [60.0, 238.4, 1.0]])
    kept = inside_the_edge(np.vstack([near, far]), (320, 240), 25.0)
    assert np.array_equal(kept, far)
    assert np.array_equal(inside_the_edge(near, (320, 240), float("nan")), near)


def test_a_cut_dot_goes_where_the_lattice_puts_its_centre_outside_as_in_rust():
    from gelstereo_train.postprocess import inside_the_edge

    def lattice(x0, y0):  # 12 x 9 at pitch 25 (the Rust test's)
        return np.array([[x0 + 25.0 * c, y0 + 25.0 * r, 1.0] for r in range(9) for c in range(12)])

    # Its row puts the dot reported 2 px inside the left edge 1.5 px beyond the pixel centres: it goes;
    # 0.3 px beyond them (inside the image's half pixel) or on them: it stays.
    for x0, stays in ((23.5, False), (24.7, True), (25.0, True)):
        inner = lattice(x0, 12.0)
        found = np.vstack([inner, [[2.0, 112.0, 1.0]]])
        assert len(inside_the_edge(found, (320, 240), 25.0)) == len(inner) + stays
    # Right and bottom: centres 0.3 px inside stay though reported within the margin; 2 px outside go.
    inner = lattice(18.7, 13.7)
    found = np.vstack([inner, [[318.9, 113.7, 1.0], [118.7, 238.9, 1.0]]])
    assert len(inside_the_edge(found, (320, 240), 25.0)) == len(inner) + 2
    inner = lattice(21.0, 16.0)
    found = np.vstack([inner, [[318.5, 116.0, 1.0], [121.0, 238.5, 1.0]]])
    assert np.array_equal(inside_the_edge(found, (320, 240), 25.0), inner)


def _lattice(pitch: float, conf: float = 0.6) -> np.ndarray:
    return np.array([[30.0 + (k % 20) * pitch, 30.0 + (k // 20) * pitch, conf] for k in range(300)])


def test_close_look_region_around_unsure_squeezed_candidates_as_in_rust():
    """Rust: close_look::tests (squeezed_dots_give_their_box_with_the_margin_inside_the_image)."""
    pitch = 20.0
    assert squeezed_region(_lattice(pitch), pitch, (640, 480)) is None
    pressed = _lattice(pitch)
    pressed[126, 0] -= 0.5 * pitch  # half a pitch from dot 125 (130, 150)
    m = CLOSE_LOOK_MARGIN_PITCH * pitch
    assert squeezed_region(pressed, pitch, (640, 480)) == pytest.approx((130 - m, 150 - m, 140 + m, 150 + m))
    sure = pressed.copy()
    sure[[125, 126], 2] = 0.95
    assert squeezed_region(sure, pitch, (640, 480)) is None
    # the same squeeze in an image the lattice fills: more than half of it is no squeeze
    pairs = _lattice(pitch)
    for k in (0, 18, 280, 298):
        pairs[k + 1, 0] = pairs[k, 0] + 0.5 * pitch
    assert squeezed_region(pairs, pitch, (440, 340)) is None


def test_close_look_zoom_stays_in_the_networks_range_and_merge_replaces_inside_only():
    assert close_look_zoom(12.0) == CLOSE_LOOK_ZOOM
    assert close_look_zoom(16.0) == pytest.approx(20.0 / 16.0)
    assert close_look_zoom(18.0) is None
    first = np.array([[50.0, 50, 0.9], [150, 150, 0.5], [250, 150, 0.9]])
    closer = np.array([[140.0, 150, 0.8], [160, 150, 0.8], [260, 150, 0.9]])
    merged = merge_close_look(first, closer, (100.0, 100.0, 200.0, 200.0))
    assert merged[:, 0].tolist() == [50.0, 250.0, 140.0, 160.0]


def test_unsure_squeezed_markers_are_kept_inside_a_looked_region_only():
    """Rust: lattice::tests::unsure_squeezed_markers_are_kept_inside_a_looked_region_only."""
    pts = np.array([[c * 20.0, r * 20.0, 0.99] for r in range(8) for c in range(10)])
    a, b = 3 * 10 + 4, 3 * 10 + 5
    pts[a, :3] = [85.0, 63.0, 0.6]
    pts[b, :3] = [95.0, 57.0, 0.6]

    def kept(looked):
        out = keep_the_lattice(pts, LatticeCheck(), 1.0, looked=looked)
        return {tuple(r[:2]) for r in out}

    squeezed = {(85.0, 63.0), (95.0, 57.0)}
    assert not squeezed & kept(None)
    assert squeezed <= kept((60.0, 40.0, 120.0, 80.0))
    assert not squeezed & kept((140.0, 100.0, 180.0, 140.0))


def test_a_missed_dash_beside_a_squeezed_marker_is_found_as_in_rust():
    import cv2

    from gelstereo_train.postprocess import BLOB_CONFIDENCE, squeezed_blobs

    img = np.full((240, 320, 3), (210, 205, 200), np.uint8)
    truth = []
    for r in range(11):
        for c in range(15):
            x, y = 20 + 20 * c, 20 + 20 * r
            if y in (120, 140) and x in (140, 160):  # squeezed into vertical dashes 10 px apart
                x = 145 if x == 140 else 155
                cv2.ellipse(img, (x, y), (2, 5), 0, 0, 360, (40, 40, 40), -1, cv2.LINE_AA)
            else:
                cv2.circle(img, (x, y), 4, (40, 40, 40), -1, cv2.LINE_AA)
            truth.append((x, y, 1.0))
    truth = np.array(truth, float)
    found = truth[~((truth[:, 0] == 155) & (truth[:, 1] == 140))]
    added = squeezed_blobs(img, found, 20.0)
    assert len(added) == 1 and np.hypot(added[0, 0] - 155, added[0, 1] - 140) < 0.5, added
    assert added[0, 2] == BLOB_CONFIDENCE
    assert len(squeezed_blobs(img, truth, 20.0)) == 0


def test_dots_at_a_hole_and_at_the_border_are_found_and_nothing_past_the_lattice_as_in_rust():
    """The Python twin of the Rust site_blobs tests: faint dots (30 grey levels below the gel) every 20 px,
    the top row 6 px below the image's top; a dot missing inside the lattice and one of the top row
    are found where they are, nothing is added with every dot found, and a spot one pitch past a
    lattice that ends inside the image is not taken."""
    import cv2

    from gelstereo_train.postprocess import BLOB_CONFIDENCE, site_blobs

    def gel(columns: int):
        img = np.full((240, 320, 3), (160, 155, 150), np.uint8)
        dots = []
        for r in range(12):
            for c in range(columns):
                x, y = 20 + 20 * c, 6 + 20 * r
                cv2.circle(img, (x, y), 4, (125, 125, 125), -1, cv2.LINE_AA)
                dots.append((x, y, 1.0))
        return img, np.array(dots, float)

    img, dots = gel(15)
    missing = [(160.0, 106.0), (100.0, 6.0)]
    found = dots[[(x, y) not in missing for x, y, _ in dots]]
    added = site_blobs(img, found, 20.0)
    assert len(added) == 2, added
    for x, y in missing:
        assert np.hypot(added[:, 0] - x, added[:, 1] - y).min() < 0.5, added
    assert (added[:, 2] == BLOB_CONFIDENCE).all()
    assert len(site_blobs(img, dots, 20.0)) == 0
    img, dots = gel(12)
    cv2.circle(img, (260, 106), 4, (125, 125, 125), -1, cv2.LINE_AA)
    assert len(site_blobs(img, dots, 20.0)) == 0
