import json

import numpy as np

from gelstereo_train.blob import PARAMS_PATH, BlobDetector, load_params
from gelstereo_train.metrics import match
from gelstereo_train.tinydata import grid_points, render_dots


def test_params_file_has_the_tuned_values():
    p = load_params()
    assert (p["minThreshold"], p["maxThreshold"], p["thresholdStep"]) == (80, 160, 20)
    assert (p["minArea"], p["maxArea"], p["minCircularity"], p["minInertiaRatio"]) == (15, 200, 0.6, 0.3)
    assert p["filterByConvexity"] is False and p["blobColor"] == 0
    assert "_comment" in json.loads(PARAMS_PATH.read_text())


def test_blob_detector_finds_dark_dots_at_pixel_centres():
    pts, _, _ = grid_points(120, 160, 16.0, 6, 8)
    pts = pts + np.array([0.3, -0.2])
    img = render_dots(120, 160, pts, 4.0, np.random.default_rng(0))
    found = BlobDetector().detect(img)
    pi, gi, d = match(found, pts, 2.0)
    assert len(gi) == len(pts) and d.max() < 0.5
