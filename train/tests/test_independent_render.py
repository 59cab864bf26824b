"""`scripts/independent_render.py`: the independent renderer's output is a dataset `gelstereo eval`
reads, and its truth says where each dot was drawn."""

import csv
import json

import cv2
import numpy as np


def test_the_renderer_writes_the_simulators_layout_with_visible_flags_from_the_centres(tmp_path, script):
    render = script("independent_render")
    assert render.main(["--out", str(tmp_path / "a"), "--experiments", "2", "--seed", "3"]) == 0
    manifest = json.loads((tmp_path / "a" / "dataset.json").read_text())
    assert manifest["counts"]["test"] == {"experiments": 2, "frames": 2 * render.FRAMES}
    for e in manifest["experiments"]:
        exp = tmp_path / "a" / e["path"]
        rows = list(csv.DictReader(open(exp / "markers.csv")))
        assert list(rows[0]) == render.COLUMNS
        w, h = e["image_width"], e["image_height"]
        for r in rows:
            inside = 0 <= float(r["x_left"]) <= w - 1 and 0 <= float(r["y_left"]) <= h - 1
            assert int(r["visible_left"]) == int(inside)
        # The rest frame has no contact; a dot drawn at a visible centre is darker (or lighter) there
        # than the gel half a pitch away.
        assert all(r["in_contact"] == "0" for r in rows if r["frame"] == "0")
        image = cv2.imread(str(exp / "left" / "000000.png"), cv2.IMREAD_GRAYSCALE)
        assert image.shape == (h, w)
        dots = [(float(r["x_left"]), float(r["y_left"])) for r in rows if r["frame"] == "0" and r["visible_left"] == "1"]
        p = e["pitch_px"]
        contrast = [abs(int(image[int(y), int(x)]) - int(image[int(y), min(int(x + p / 2), w - 1)])) for x, y in dots
                    if x + p / 2 < w - 1]
        assert np.median(contrast) > 40
    again = tmp_path / "b"
    render.main(["--out", str(again), "--experiments", "2", "--seed", "3"])
    first = (tmp_path / "a" / "test" / "exp_0001" / "markers.csv").read_text()
    assert (again / "test" / "exp_0001" / "markers.csv").read_text() == first


def test_the_reference_layout_is_a_23_by_23_lattice_inside_the_view(tmp_path, script):
    render = script("independent_render")
    assert render.main(["--out", str(tmp_path), "--experiments", "1", "--seed", "2", "--sensor", "reference"]) == 0
    e = json.loads((tmp_path / "dataset.json").read_text())["experiments"][0]
    assert (e["image_width"], e["image_height"], e["lattice"]) == (640, 480, "square") and not e["light_dots"]
    rest = [r for r in csv.DictReader(open(tmp_path / e["path"] / "markers.csv")) if r["frame"] == "0"]
    assert len(rest) == 23 * 23
    assert all(r["visible_left"] == "1" and r["visible_right"] == "1" for r in rest)
    assert 16.0 <= e["pitch_px"] <= 18.0


def test_the_squeeze_report_measures_contact_frames_in_pitches(tmp_path, script):
    render = script("independent_render")
    render.main(["--out", str(tmp_path), "--experiments", "1", "--seed", "2", "--sensor", "reference"])
    report = script("squeeze_report")
    d = report.squeeze(tmp_path, 1)
    rows = list(csv.DictReader(open(tmp_path / "test" / "exp_0000" / "markers.csv")))
    contact_frames = {r["frame"] for r in rows if r["in_contact"] == "1"}
    # Every visible marker of each contact frame (the rest frame has none), in pitches: most at about one.
    assert "0" not in contact_frames and contact_frames
    assert len(d) == sum(1 for r in rows if r["frame"] in contact_frames and r["visible_left"] == "1")
    assert 0.9 < np.median(d) < 1.1 and d.min() > 0
