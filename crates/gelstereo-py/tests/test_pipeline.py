"""gelstereo.Pipeline: agreement with `gelstereo track`, conversion of every output, grey and BGR
input, re-zeroing, flagged frames, errors, the GIL."""

import csv
import math
import subprocess
from collections import Counter, defaultdict

import cv2
import numpy as np
import pytest

import gelstereo
from gil import main_thread_share_while

MARKER_KEYS = ["row", "col", "status", "x_left", "y_left", "x_right", "y_right",
               "X_mm", "Y_mm", "Z_mm", "dX_mm", "dY_mm", "dZ_mm", "pressure_kPa", "in_contact",
               "slipping", "X_gel_mm", "Y_gel_mm", "Z_gel_mm", "dX_gel_mm", "dY_gel_mm", "dZ_gel_mm"]
SLIP_STATES = {"no_contact", "stick", "partial_slip", "gross_slip"}


def pairs(sample):
    for left in sorted((sample / "left").glob("*.jpg")):
        yield cv2.imread(str(left)), cv2.imread(str(sample / "right" / left.name))


@pytest.fixture(scope="module")
def tracked(sample):
    """The sample recording through the Python pipeline, every frame's output."""
    pipeline = gelstereo.Pipeline(calibration=sample / "calib.yaml")
    return [pipeline.process(left, right) for left, right in pairs(sample)]


@pytest.fixture(scope="module")
def tables(sample, gelstereo_bin, tmp_path_factory):
    """`gelstereo track` on the sample recording, with every default: (markers rows, frames rows)."""
    out = tmp_path_factory.mktemp("track")
    subprocess.run([str(gelstereo_bin), "track", "--quiet", "--no-ply", "--overlay-every", "0",
                    "--out", str(out), str(sample)], check=True)
    with open(out / "markers.csv") as m, open(out / "frames.csv") as f:
        return list(csv.DictReader(m)), list(csv.DictReader(f))


def test_python_tracks_the_sample_as_gelstereo_track_does(tracked, tables):
    markers, frames = tables
    assert len(tracked) == len(frames) == 40
    by_frame = defaultdict(list)
    for row in markers:
        by_frame[int(row["frame"])].append(row)
    for out, summary in zip(tracked, frames):
        k = out.frame
        assert k == int(summary["frame"])
        assert out.slip == summary["slip"], k
        rows = by_frame[k]
        assert len(out.markers["row"]) == len(rows), k
        assert Counter(out.markers["status"]) == Counter(r["status"] for r in rows), k
        assert out.contact.max_depth_mm == pytest.approx(float(summary["max_depth_mm"]), abs=1e-6)
        assert out.contact.area_mm2 == pytest.approx(float(summary["contact_area_mm2"]), abs=1e-6)
        # The contact mechanics' figures: the same force, shear, torque and pressures.
        assert out.contact.force_n == pytest.approx(float(summary["force_N"]), abs=1e-6)
        assert out.contact.shear_n == pytest.approx(
            (float(summary["shear_x_N"]), float(summary["shear_y_N"])), abs=1e-6)
        assert out.contact.torque_nmm == pytest.approx(float(summary["torque_Nmm"]), abs=1e-6)
        table_p = np.array([float(r["pressure_kPa"]) for r in rows])
        np.testing.assert_allclose(out.markers["pressure_kPa"], table_p, atol=1e-6)
        np.testing.assert_array_equal(out.markers["in_contact"], [r["in_contact"] == "1" for r in rows])
        # Same ids in the same order, same 3-D positions (the tables print 6 decimals).
        np.testing.assert_array_equal(out.markers["row"], [int(r["row"]) for r in rows])
        np.testing.assert_array_equal(out.markers["col"], [int(r["col"]) for r in rows])
        for column in ("Z_mm", "Z_gel_mm", "dZ_gel_mm"):
            table = np.array([float(r[column]) if r[column] else np.nan for r in rows])
            np.testing.assert_allclose(out.markers[column], table, atol=1e-6, equal_nan=True)
    # The sample presses, then slides: the tracker sees contact and slip.
    assert {f.slip for f in tracked} >= {"no_contact", "stick"}


def test_frames_convert_every_output(tracked):
    reference, pressed = tracked[0], max(tracked, key=lambda f: f.contact.max_depth_mm)
    for frame in (reference, pressed):
        assert list(frame.markers) == MARKER_KEYS
        lengths = {len(a) for a in frame.markers.values()}
        assert lengths == {529}
        assert frame.markers["row"].dtype == np.int64
        assert frame.markers["X_mm"].dtype == np.float64
        assert set(frame.markers["status"]) <= {"tracked", "predicted", "lost"}
        assert frame.slip in SLIP_STATES and frame.note is None
    assert reference.contact.centroid_mm is None and not reference.contact.in_contact
    assert reference.contact.region.shape == (0, 2)
    np.testing.assert_array_equal(reference.markers["dZ_mm"][~np.isnan(reference.markers["dZ_mm"])], 0.0)
    assert "indexed" in reference.log[0]
    assert pressed.contact.in_contact and pressed.contact.max_depth_mm > 0.5
    assert len(pressed.contact.centroid_mm) == 2 and pressed.contact.region.shape[1] == 2
    # Pressed markers move towards the cameras (z forward), into the gel along its normal as deep
    # as the contact.
    assert np.nanmin(pressed.markers["dZ_mm"]) < -0.3
    assert np.nanmin(pressed.markers["dZ_gel_mm"]) < -0.9 * pressed.contact.max_depth_mm
    # Timestamps: frame number / 30 Hz when none is given.
    assert [f.timestamp for f in tracked[:3]] == pytest.approx([0.0, 1 / 30, 2 / 30])


def test_keywords_match_the_command_line_flags(sample, gelstereo_bin, tmp_path):
    """`method`, `pitch_mm`, `threads` and `mono` do what `track`'s flags of the same names do."""
    out = tmp_path / "mono"
    subprocess.run([str(gelstereo_bin), "track", "--quiet", "--no-ply", "--overlay-every", "0", "--mono",
                    "--method", "blob", "--pitch-mm", "0.8", "--threads", "1", "--out", str(out), str(sample)],
                   check=True)
    with open(out / "frames.csv") as f:
        rows = list(csv.DictReader(f))
    pipeline = gelstereo.Pipeline(method="blob", pitch_mm=0.8, threads=1, mono=True)
    frames = [pipeline.process(left, right) for left, right in pairs(sample)]
    assert not pipeline.is_stereo
    areas = [f.contact.area_mm2 for f in frames]
    assert all(math.isfinite(a) for a in areas) and max(areas) > 10.0
    assert areas == pytest.approx([float(r["contact_area_mm2"]) for r in rows], abs=1e-6)
    assert [f.slip for f in frames] == [r["slip"] for r in rows]
    # Without the pitch a mono sensor's area is unknown, as the command line leaves it empty.
    left, _ = next(pairs(sample))
    assert math.isnan(gelstereo.Pipeline(method="blob").process(left).contact.area_mm2)


@pytest.mark.parametrize(
    "kwargs, words",
    [({"method": "sift"}, ["sift"]), ({"threads": 100000}, ["threads", "256"]), ({"pitch_mm": -1.0}, ["pitch_mm"])],
)
def test_bad_keywords_are_refused_by_name(kwargs, words):
    with pytest.raises((ValueError, gelstereo.GelstereoError)) as caught:
        gelstereo.Pipeline(**kwargs)
    assert all(w in str(caught.value) for w in words), caught.value


def test_grey_and_bgr_give_the_same_mono_tracking(sample):
    bgr = [left for left, _ in pairs(sample)][:6]
    from_bgr, from_grey = gelstereo.Pipeline(), gelstereo.Pipeline()
    assert not from_bgr.is_stereo
    for k, image in enumerate(bgr):
        a = from_bgr.process(image, timestamp=10.0 + k)
        b = from_grey.process(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), timestamp=10.0 + k)
        assert a.slip == b.slip and a.timestamp == pytest.approx(k)
        # The network sees colour or grey: positions agree to a fraction of a pixel (pitch ~18 px).
        np.testing.assert_allclose(a.markers["x_left"], b.markers["x_left"], atol=0.5, equal_nan=True)
        # Mono: no right view, no 3-D.
        assert np.isnan(a.markers["x_right"]).all() and np.isnan(a.markers["Z_mm"]).all()
        assert (a.markers["status"] == "tracked").sum() > 400


def test_rezero_makes_the_current_shape_the_reference(sample):
    pipeline = gelstereo.Pipeline(calibration=str(sample / "calib.yaml"))
    frames = list(pairs(sample))
    for left, right in frames[:12]:
        pressed = pipeline.process(left, right)
    assert pressed.contact.max_depth_mm > 0.5
    pipeline.rezero()
    again = pipeline.process(*frames[11])
    # The same images against themselves: no displacement, no contact.
    assert np.nanmax(np.abs(again.markers["dZ_mm"])) < 0.01
    assert again.slip == "no_contact"


def test_a_frame_of_another_size_comes_back_flagged(sample):
    pipeline = gelstereo.Pipeline(calibration=sample / "calib.yaml")
    left, right = next(pairs(sample))
    pipeline.process(left, right)
    small = pipeline.process(left[:240, :320], right[:240, :320])
    assert small.note and "size" in small.note
    assert set(small.markers["status"]) == {"lost"}
    # Its contact is unknown, not "no contact".
    assert small.slip is None and math.isnan(small.contact.area_mm2)


@pytest.mark.parametrize(
    "kwargs, error, words",
    [
        ({"calibration": "missing/calib.yaml"}, gelstereo.GelstereoError, ["missing/calib.yaml"]),
        ({"grid": "23by23"}, gelstereo.GelstereoError, ["grid", "ROWSxCOLS"]),
        ({"grid": (1, 5)}, gelstereo.GelstereoError, ["at least 2x2"]),
        ({"grid": 23.5}, TypeError, ["ROWSxCOLS"]),
        ({"models": "no-such-models"}, gelstereo.GelstereoError, ["no-such-models"]),
        ({"sensor": "no-sensor.json"}, gelstereo.GelstereoError, ["no-sensor.json"]),
        ({"poisson": 0.5}, gelstereo.GelstereoError, ["poisson", "[0, 0.5)"]),
        ({"gel_modulus_kpa": float("nan")}, gelstereo.GelstereoError, ["modulus_kpa"]),
        ({"gel": "no-gel.json"}, gelstereo.GelstereoError, ["no-gel.json"]),
    ],
)
def test_unusable_settings_raise_with_the_rust_message(kwargs, error, words):
    with pytest.raises(error) as caught:
        gelstereo.Pipeline(**kwargs)
    for word in words:
        assert word in str(caught.value)


def test_unusable_images_raise(sample):
    pipeline = gelstereo.Pipeline(calibration=sample / "calib.yaml")
    left, right = next(pairs(sample))
    with pytest.raises(TypeError, match="right: .*float64"):
        pipeline.process(left, right.astype(np.float64))
    with pytest.raises(ValueError, match="left: .*shape"):
        pipeline.process(left[:, :, :2], right)


def test_timestamps_must_be_finite_and_increase(sample):
    pipeline = gelstereo.Pipeline()
    left, _ = next(pairs(sample))
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="timestamp=.*finite"):
            pipeline.process(left, timestamp=bad)
    assert pipeline.process(left, timestamp=5.0).timestamp == pytest.approx(0.0)
    for earlier in (5.0, 4.0):
        with pytest.raises(ValueError, match="after the previous frame's 5"):
            pipeline.process(left, timestamp=earlier)
    assert pipeline.process(left, timestamp=5.5).timestamp == pytest.approx(0.5)


def test_thread_counts_from_the_environment_are_bounded(monkeypatch):
    monkeypatch.setenv("RAYON_NUM_THREADS", "100000")
    with pytest.raises(ValueError, match="RAYON_NUM_THREADS='100000'.*to 256"):
        gelstereo.Pipeline()


def test_processing_releases_the_gil(sample):
    pipeline = gelstereo.Pipeline(calibration=sample / "calib.yaml")
    left, right = next(pairs(sample))
    pipeline.process(left, right)  # reference frame
    assert main_thread_share_while(lambda: pipeline.process(left, right)) > 0.05


def test_the_pipeline_finds_and_places_dots_cut_by_the_border():
    """A mono gel whose lattice (pitch 29 px, dots of radius 5.5) the border cuts: its left column
    centred 1.5 px inside the image, its top row 2 px inside, a column past the right edge centred
    1.5 px outside. With every default the 9 x 11 dots centred inside are tracked, the cut ones
    within 0.5 px of their centres, and the column outside is not."""
    pitch, x0, y0 = 29.0, 1.5, 2.0
    image = np.full((240, 320, 3), (190, 180, 170), np.uint8)
    for r in range(9):
        for c in range(12):
            centre = (round((x0 + pitch * c) * 16), round((y0 + pitch * r) * 16))
            cv2.circle(image, centre, 88, (45, 45, 45), -1, cv2.LINE_AA, 4)
    out = gelstereo.Pipeline(grid=(9, 11)).process(image)
    m = out.markers
    tracked = m["status"] == "tracked"
    assert tracked.sum() == 99
    rows, cols = m["row"][tracked], m["col"][tracked]
    truth_x, truth_y = x0 + pitch * cols, y0 + pitch * rows
    err = np.hypot(m["x_left"][tracked] - truth_x, m["y_left"][tracked] - truth_y)
    cut = (truth_x < 5.5) | (truth_y < 5.5)
    assert cut.sum() == 19 and err[cut].max() <= 0.5, err[cut]
    assert (m["x_left"][tracked] < 318.0).all()


def test_the_stream_reads_back_as_the_frames_process_returns(tracked, sample, gelstereo_bin, tmp_path):
    stream = tmp_path / "stream.jsonl"
    subprocess.run([str(gelstereo_bin), "track", "--quiet", "--jsonl", str(stream), str(sample)], check=True)
    read = list(gelstereo.read_stream(stream))
    assert len(read) == len(tracked) == 40
    lines = stream.read_text().splitlines()
    for k, (back, live) in enumerate(zip(read, tracked)):
        assert (back.frame, back.slip, back.note) == (live.frame, live.slip, live.note), k
        assert back.timestamp == pytest.approx(live.timestamp, abs=1e-6)
        assert back.contact.force_n == pytest.approx(live.contact.force_n, abs=1e-4)
        assert back.contact.area_mm2 == pytest.approx(live.contact.area_mm2, abs=1e-3)
        np.testing.assert_array_equal(back.contact.region, live.contact.region)
        assert list(back.markers) == MARKER_KEYS
        for key in ("row", "col", "status", "in_contact", "slipping"):
            np.testing.assert_array_equal(back.markers[key], live.markers[key], err_msg=f"{k} {key}")
        # The stream's precision: px to 0.005, gel-frame mm to half a micrometre, camera-frame mm
        # (through the line's gel frame) to a micrometre.
        for key, tolerance in (("x_left", 0.005), ("y_right", 0.005), ("X_gel_mm", 5e-4),
                               ("dZ_gel_mm", 5e-4), ("Z_mm", 1e-3), ("dX_mm", 1e-3), ("pressure_kPa", 0.005)):
            np.testing.assert_allclose(back.markers[key], live.markers[key], atol=tolerance + 1e-9,
                                       equal_nan=True, err_msg=f"{k} {key}")
        np.testing.assert_allclose(back.camera_from_gel, live.camera_from_gel, atol=1e-4)
        assert gelstereo.parse_frame(lines[k]).frame == k
    # The transform maps the gel-frame positions onto the camera-frame ones.
    live = tracked[-1]
    gel = np.stack([live.markers[c] for c in ("X_gel_mm", "Y_gel_mm", "Z_gel_mm", )] + [np.ones(529)])
    camera = (live.camera_from_gel @ gel)[:3]
    np.testing.assert_allclose(camera, np.stack([live.markers[c] for c in ("X_mm", "Y_mm", "Z_mm")]),
                               atol=1e-9, equal_nan=True)


def test_a_bad_stream_line_names_the_file_line_and_field(tmp_path):
    stream = tmp_path / "bad.jsonl"
    stream.write_text('{"schema": "gelstereo-frame/1", "frame": -1}\n')
    with pytest.raises(ValueError, match="bad.jsonl:1"):
        list(gelstereo.read_stream(stream))
    with pytest.raises(ValueError, match="schema"):
        gelstereo.parse_frame('{"schema": "other/2"}')
    with pytest.raises(gelstereo.GelstereoError, match="missing.jsonl"):
        gelstereo.read_stream(tmp_path / "missing.jsonl")


def test_open_reads_a_recording_as_process_wants_it(sample, tracked):
    reader = gelstereo.open(sample)
    assert reader.is_stereo and reader.frames == 40
    frames = list(reader)
    assert [f.index for f in frames] == list(range(40))
    first = frames[0]
    assert first.error is None and first.timestamp == 0.0 and frames[3].timestamp == pytest.approx(0.1)
    np.testing.assert_array_equal(first.left, cv2.imread(str(sample / "left" / "000000.jpg")))
    np.testing.assert_array_equal(first.right, cv2.imread(str(sample / "right" / "000000.jpg")))
    pipeline = gelstereo.Pipeline(calibration=sample / "calib.yaml")
    for f, live in zip(frames[:12], tracked):
        out = pipeline.process(f.left, f.right, f.timestamp)
        assert out.slip == live.slip
        np.testing.assert_array_equal(out.markers["Z_mm"], live.markers["Z_mm"])
    left_only = list(gelstereo.open(str(sample), mono=True))
    assert len(left_only) == 40 and left_only[0].right is None
    np.testing.assert_array_equal(left_only[5].left, frames[5].left)


def test_open_reads_videos_side_by_side_and_says_what_it_cannot_open(sample, tmp_path):
    video = tmp_path / "both.avi"
    left = cv2.imread(str(sample / "left" / "000000.jpg"))
    right = cv2.imread(str(sample / "right" / "000000.jpg"))
    h, w = left.shape[:2]
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (2 * w, h))
    for _ in range(3):
        writer.write(np.hstack([left, right]))
    writer.release()
    frames = list(gelstereo.open(video, side_by_side=True))
    assert len(frames) == 3 and frames[1].timestamp == pytest.approx(0.1)
    assert frames[0].left.shape == left.shape == frames[0].right.shape
    mono = list(gelstereo.open(video))
    assert mono[0].right is None and mono[0].left.shape == (h, 2 * w, 3)
    with pytest.raises(gelstereo.GelstereoError, match="missing"):
        gelstereo.open(tmp_path / "missing")
    with pytest.raises(TypeError, match="source"):
        gelstereo.open(1.5)


def test_open_warns_where_frame_names_do_not_settle_the_order(left_bgr, tmp_path):
    for name in ("1.png", "01.png", "2.png", "10.png"):
        cv2.imwrite(str(tmp_path / name), left_bgr)
    with pytest.warns(UserWarning, match="1.png and 01.png"):
        reader = gelstereo.open(tmp_path)
    assert reader.frames == 4 and not reader.is_stereo


def test_pad_border_is_accepted_and_ignored_as_on_the_command_line(sample, left_bgr):
    with pytest.warns(DeprecationWarning, match="pad_border=8 is ignored"):
        padded = gelstereo.Pipeline(grid="23x23", pad_border=8, mono=True)
    plain = gelstereo.Pipeline(grid="23x23", mono=True)
    np.testing.assert_array_equal(padded.process(left_bgr).markers["x_left"], plain.process(left_bgr).markers["x_left"])
