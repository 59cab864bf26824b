"""Labels must follow the pixels through every geometric transform: check each crop label against the
intensity centroid of the dark dot around it in the crop."""

import numpy as np
import pytest
import torch

from gelstereo_train.augment import AugConfig, make_batch, photometric, sample_crops
from gelstereo_train.tinydata import grid_points, render_dots


def _centroid(img, u, v, r):
    """Darkness-weighted centroid over a disc of radius r around (u, v) (continuous coords)."""
    h, w = img.shape
    if u - r < 0 or v - r < 0 or u + r > w or v + r > h:
        return None
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    disc = (xx - u) ** 2 + (yy - v) ** 2 <= r * r
    wgt = np.clip(np.median(img) - img, 0, None) * disc
    s = wgt.sum()
    return (xx * wgt).sum() / s, (yy * wgt).sum() / s


def _label_errors(img, pts, pitch, cfg, rng, radius):
    """Distances between each crop label and the centroid of the dot around it (radius ``radius``),
    over 6 crops of ``img``."""
    errs = []
    for _ in range(6):
        x, labels = sample_crops([img], [pts], np.array([pitch]), np.array([0]), cfg, rng)
        grey = x[0].mean(0).numpy()
        for u, v in labels[0]:
            c = _centroid(grey, u, v, radius)
            if c is not None:
                errs.append(np.hypot(c[0] - u, c[1] - v))
    return errs


@pytest.mark.parametrize("canonical", [1.0, 0.0])
def test_crop_labels_sit_on_the_dots(canonical):
    rng = np.random.default_rng(3)
    pitch = 20.0
    pts, _, _ = grid_points(200, 260, pitch, 9, 12)
    img = render_dots(200, 260, pts, 5.0, rng)
    cfg = AugConfig(crop=(96, 96), input_size=(160, 160), p_canonical=canonical, rotate_deg=10.0,
                    pitch_in_px=(14.0, 24.0))
    errs = _label_errors(img, pts, pitch, cfg, rng, 6.5)
    assert len(errs) > 40
    # tolerance: centroid of a bilinearly resampled, anti-aliased dot; 0.25 input px
    assert np.median(errs) < 0.1 and np.max(errs) < 0.25


def test_photometric_keeps_range_and_shape_and_changes_pixels():
    rng = np.random.default_rng(0)
    x = torch.rand(8, 3, 64, 64)
    y = photometric(x.clone(), AugConfig(p_clean=0.0), rng)
    assert y.shape == x.shape and float(y.min()) >= 0 and float(y.max()) <= 1
    assert float((y - x).abs().mean()) > 0.01
    # 8-bit quantised like a real image
    assert torch.allclose(y * 255, torch.round(y * 255), atol=1e-3)


def test_make_batch_on_dataset(tiny_root):
    from gelstereo_train.data import list_samples, median_nn_distance

    s = list_samples(tiny_root, "train")
    imgs = [a.load() for a in s]
    pts = [a.points_px for a in s]
    x, labels = make_batch(imgs, pts, np.array([median_nn_distance(p) for p in pts]), 4,
                           AugConfig(crop=(64, 64)), np.random.default_rng(0))
    assert x.shape == (4, 3, 64, 64)
    for lab in labels:
        assert ((lab >= 0) & (lab < 64)).all()



@pytest.mark.parametrize("canonical", [1.0, 0.0])
def test_contact_crops_are_centred_near_the_focus(canonical):
    """With p_contact = 1 every crop holds the focus point (a marker in contact) within about a quarter
    crop of its centre; with p_contact = 0 crops fall anywhere and mostly miss it."""
    rng = np.random.default_rng(5)
    pitch = 20.0
    pts, _, _ = grid_points(300, 400, pitch, 14, 19)
    img = render_dots(300, 400, pts, 5.0, rng)
    focus = pts[[3 * 19 + 5]]  # an interior marker, off the image centre
    crop = 96

    def focus_in_crop(p_contact):
        cfg = AugConfig(crop=(crop, crop), input_size=(240, 320), p_canonical=canonical, p_contact=p_contact,
                        pitch_in_px=(14.0, 24.0))
        # The focus point is the only label, so labels[0] is where it lands in the crop (if inside).
        _, labels = sample_crops([img], [focus], np.array([pitch]), np.array([0]), cfg, rng, [focus])
        return labels[0]

    for _ in range(30):
        lab = focus_in_crop(1.0)
        assert len(lab) == 1
        # a quarter crop of jitter, widened by the rotation and anisotropy of jittered crops
        assert np.all(np.abs(lab[0] - crop / 2) <= 0.25 * crop * 1.6 + 1.0), lab
    hits = sum(len(focus_in_crop(0.0)) for _ in range(30))
    assert hits < 20


def test_contact_points_do_not_change_the_crops_of_a_recipe_without_contact_crops():
    """p_contact = 0 (the shipped recipes): passing the contact points draws nothing more, so a seed
    gives the crops it gave before the option existed."""
    pitch = 20.0
    pts, _, _ = grid_points(300, 400, pitch, 14, 19)
    img = render_dots(300, 400, pts, 5.0, np.random.default_rng(1))
    cfg = AugConfig(crop=(96, 96), input_size=(240, 320))
    idx = np.array([0, 1, 2])
    a = sample_crops([img] * 3, [pts] * 3, np.full(3, pitch), idx, cfg, np.random.default_rng(7))
    b = sample_crops([img] * 3, [pts] * 3, np.full(3, pitch), idx, cfg, np.random.default_rng(7), [pts[:5]] * 3)
    assert torch.equal(a[0], b[0])
    assert all(np.array_equal(x, y) for x, y in zip(a[1], b[1]))


def _reduced_config() -> AugConfig:
    """Jittered crops that reduce a source with a 45 px pitch to 9 px (scale 0.2, below the area
    averaging threshold), no rotation or flips."""
    return AugConfig(crop=(64, 64), input_size=(160, 160), p_canonical=0.0, rotate_deg=0.0, flip=False,
                     pitch_in_px=(9.0, 9.0), aspect=(1.0, 1.0))


def test_crops_reduced_a_lot_average_scan_lines_away_as_inference_does():
    # Scan lines (rows alternating between two grey levels) sampled bilinearly at 0.2 x alias into
    # stripes; averaged by area, as the inference preprocessing reduces such images, they are grey.
    img = np.empty((600, 800, 3), np.uint8)
    img[0::2], img[1::2] = 60, 200
    rng = np.random.default_rng(5)
    x, _ = sample_crops([img] * 4, [np.zeros((0, 2))] * 4, np.full(4, 45.0), np.arange(4), _reduced_config(), rng)
    assert float(x.std()) < 0.01
    assert abs(float(x.mean()) - 130 / 255) < 0.01


def test_labels_sit_on_the_dots_of_crops_reduced_by_area():
    rng = np.random.default_rng(7)
    pitch = 45.0
    pts, _, _ = grid_points(600, 800, pitch, 12, 16)
    img = render_dots(600, 800, pts, 11.0, rng)
    errs = _label_errors(img, pts, pitch, _reduced_config(), rng, 3.5)
    assert len(errs) > 40
    assert np.median(errs) < 0.1 and np.max(errs) < 0.25


def _flat_band(flat_lines):
    """How many lines from the start are flat."""
    return int(np.argmin(flat_lines)) if not flat_lines.all() else len(flat_lines)


def test_edge_crops_overhang_an_edge_filled_with_the_median_colour_as_at_inference():
    """p_edge = 1: every crop overhangs an image edge by at most half a pitch plus one input multiple
    (the auto layout's margin); the outside is the image's median colour, flat; the labels are the
    image's markers inside the crop and still sit on their dots."""
    from gelstereo_train.augment import EDGE_MULTIPLE_PX

    rng = np.random.default_rng(11)
    pitch = 20.0
    pts, _, _ = grid_points(200, 260, pitch, 9, 12)
    img = render_dots(200, 260, pts, 5.0, rng)
    median = np.median(img[::4, ::4].reshape(-1, 3).astype(np.float64), axis=0)
    crop = 96
    cfg = AugConfig(crop=(crop, crop), input_size=(160, 160), p_canonical=0.0, rotate_deg=0.0, flip=False,
                    aspect=(1.0, 1.0), pitch_in_px=(14.0, 24.0), p_edge=1.0)
    overhung = 0
    for _ in range(40):
        x, labels = sample_crops([img], [pts], np.array([pitch]), np.array([0]), cfg, rng)
        rgb = x[0].numpy() * 255.0
        flat = np.all(np.abs(rgb - median[:, None, None]) < 0.6, axis=0)
        # the outside: whole flat columns or rows at the crop's sides, no wider than the margin
        margin = max(_flat_band(flat.all(axis=0)), _flat_band(flat.all(axis=0)[::-1]),
                     _flat_band(flat.all(axis=1)), _flat_band(flat.all(axis=1)[::-1]))
        assert margin <= 0.5 * 24.0 + EDGE_MULTIPLE_PX + 1
        overhung += margin > 0
        for u, v in labels[0]:
            assert 0 <= u < crop and 0 <= v < crop
    assert overhung >= 30
    errs = _label_errors(img, pts, pitch, cfg, rng, 6.5)
    assert len(errs) > 20 and np.median(errs) < 0.1 and np.max(errs) < 0.25



def test_crops_then_photometric_are_the_batch_of_make_batch_up_to_8_bit_crops(tiny_root):
    """``--augment-on device`` splits ``make_batch`` in two: uint8 crops made by the batch makers,
    then ``photometric`` on the trainer's device from the trainer's stream. Fed one stream in that
    order, the two halves draw what ``make_batch`` draws: same labels, and pixels that differ by
    the crops' 8-bit quantisation carried through the augmentations (gains up to 1.4, contrast up
    to 1.5, gamma), never by a different draw."""
    from gelstereo_train.augment import make_crops
    from gelstereo_train.data import list_samples, median_nn_distance

    s = list_samples(tiny_root, "train")
    imgs = [a.load() for a in s]
    pts = [a.points_px for a in s]
    pitches = np.array([median_nn_distance(p) for p in pts])
    cfg = AugConfig(crop=(64, 64), p_clean=0.0, p_jpeg=0.0, p_noise=0.0)
    whole, whole_labels = make_batch(imgs, pts, pitches, 6, cfg, np.random.default_rng(4))
    rng = np.random.default_rng(4)
    crops, labels = make_crops(imgs, pts, pitches, 6, cfg, rng)
    assert crops.dtype == torch.uint8 and crops.shape == (6, 3, 64, 64)
    split = photometric(crops.float() / 255.0, cfg, rng)
    assert all(np.array_equal(a, b) for a, b in zip(labels, whole_labels))
    diff = (split - whole).abs()
    assert float(diff.mean()) < 1.0 / 255 and float(diff.max()) <= 6.0 / 255
