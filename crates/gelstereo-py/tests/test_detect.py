"""gelstereo.detect: numpy conversion, agreement with `gelstereo detect`, errors."""

import csv
import subprocess

import cv2
import numpy as np
import pytest

import gelstereo

from gil import main_thread_share_while


def test_detect_agrees_with_the_command_line(left_bgr, sample, gelstereo_bin, tmp_path):
    found = gelstereo.detect(left_bgr)
    assert found.dtype == np.float64 and found.ndim == 2 and found.shape[1] == 3
    out = tmp_path / "found.csv"
    # `detect` runs every image on the whole network input; the command line, given a stream, runs a
    # view's frames on a window around its lattice (the same markers to a fraction of a pixel).
    subprocess.run(
        [str(gelstereo_bin), "detect", "--whole-input", "--out", str(out), str(sample / "left" / "000000.jpg")],
        check=True,
    )
    with open(out) as f:
        rows = [(float(r["x"]), float(r["y"]), float(r["confidence"])) for r in csv.DictReader(f)]
    # The sample's reference sensor shows most of its 23 x 23 markers in the left view.
    assert len(found) == len(rows) > 400
    # The CSV rounds to its printed decimals.
    np.testing.assert_allclose(found, np.array(rows), atol=1e-3)


def test_grey_bgr_and_strided_views_give_the_same_markers(left_bgr):
    grey = cv2.cvtColor(left_bgr, cv2.COLOR_BGR2GRAY)
    from_grey = gelstereo.detect(grey)
    # Grey is replicated to three channels by the localizer, so the stacked image is the same input.
    np.testing.assert_array_equal(from_grey, gelstereo.detect(np.dstack([grey] * 3)))
    np.testing.assert_array_equal(from_grey, gelstereo.detect(grey[:, :, None]))
    # A non-contiguous view (channels reversed, a negative stride) is copied in the right order.
    rgb_view = left_bgr[:, :, ::-1]
    assert not rgb_view.flags.c_contiguous
    np.testing.assert_array_equal(gelstereo.detect(rgb_view), gelstereo.detect(rgb_view.copy()))
    assert len(from_grey) > 400


def test_blob_method_gives_confidence_one(left_bgr):
    found = gelstereo.detect(left_bgr, method="blob")
    assert len(found) > 300
    assert np.all(found[:, 2] == 1.0)


@pytest.mark.parametrize(
    "image, error, words",
    [
        (np.zeros((64, 64), np.float32), TypeError, ["uint8", "float32"]),
        ([[0, 1], [2, 3]], TypeError, ["numpy uint8", "list"]),
        (np.zeros((64, 64, 2), np.uint8), ValueError, ["HxWx3", "[64, 64, 2]"]),
        (np.zeros(64, np.uint8), ValueError, ["[64]"]),
        (np.zeros((8, 640, 3), np.uint8), gelstereo.GelstereoError, ["640x8", "at least 16x16"]),
    ],
)
def test_unusable_images_raise_with_the_reason(image, error, words):
    with pytest.raises(error) as caught:
        gelstereo.detect(image)
    for word in words:
        assert word in str(caught.value)


def test_unknown_method_is_named():
    with pytest.raises(ValueError, match="'ssd'.*marknet-mre"):
        gelstereo.detect(np.zeros((64, 64), np.uint8), method="ssd")


def test_detection_releases_the_gil(left_bgr):
    """The main thread keeps running Python while another thread detects."""
    gelstereo.detect(left_bgr)  # models loaded
    assert main_thread_share_while(lambda: gelstereo.detect(left_bgr)) > 0.05
