"""examples/python/batch_dask.py on a local Dask cluster of 2 workers: its tables are byte for byte
those of `gelstereo track` on each recording, a failing recording is a row and an exit status, and a
re-run reuses finished outputs without touching them or a folder gelstereo did not write; recordings
are found at any depth, not inside a recording, the output or a link cycle.

    GELSTEREO=target/debug/gelstereo .venv/bin/python -m pytest -q examples/python/test_batch_dask.py

GELSTEREO is the binary the batch and the direct runs share (default: `gelstereo` on PATH).
"""

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
SAMPLE = HERE.parent.parent / "data" / "sample" / "press-slide"
BATCH = HERE / "batch_dask.py"
# Small outputs keep the run short; the batch passes them to every `gelstereo track`.
TRACK_ARGS = ["--no-ply", "--overlay-every", "0"]


@pytest.fixture(scope="module")
def gelstereo() -> str:
    exe = shutil.which(os.environ.get("GELSTEREO", "gelstereo"))
    if exe is None:
        pytest.fail("no gelstereo binary: set GELSTEREO=PATH (scripts/test.sh uses cargo's build)")
    return os.path.abspath(exe)


@pytest.fixture(scope="module")
def root(tmp_path_factory, gelstereo) -> Path:
    """Two links to the sample at different depths, a nested simulated recording, a recording whose
    images are corrupt, and a folder that is no recording."""
    base = tmp_path_factory.mktemp("batch")
    root = base / "root"
    (root / "lab" / "day1").mkdir(parents=True)
    (root / "press-slide").symlink_to(SAMPLE)
    (root / "lab" / "day1" / "press-slide").symlink_to(SAMPLE)
    subprocess.run([gelstereo, "simulate", "--out", str(base / "sim"), "--experiments", "1",
                    "--frames-per-experiment", "15", "--seed", "5", "--randomization", "off", "--quiet"], check=True)
    (root / "sim").symlink_to(base / "sim" / "train")
    broken = root / "broken"
    for side in ("left", "right"):
        (broken / side).mkdir(parents=True)
        (broken / side / "000000.png").write_bytes(b"not an image")
    shutil.copy(SAMPLE / "calib.yaml", broken)
    (root / "notes").mkdir()
    (root / "notes" / "readme.txt").write_text("no recording here\n")
    return root


def run_batch(gelstereo: str, root: Path, out: Path, *options: str) -> subprocess.CompletedProcess:
    command = [sys.executable, str(BATCH), str(root), "--out", str(out), "--workers", "2",
               "--gelstereo", gelstereo, *options, "--", *TRACK_ARGS]
    return subprocess.run(command, capture_output=True, text=True, timeout=600)


def summary(out: Path) -> dict:
    with open(out / "summary.csv", newline="") as f:
        return {row["recording"]: row for row in csv.DictReader(f)}


@pytest.fixture(scope="module")
def batch(tmp_path_factory, gelstereo, root):
    out = tmp_path_factory.mktemp("out")
    result = run_batch(gelstereo, root, out)
    return out, result


EXPECTED = {"broken", "lab/day1/press-slide", "press-slide", "sim/exp_0000"}
TRACKED = sorted(EXPECTED - {"broken"})


def test_every_recording_has_a_row_and_a_failure_sets_the_exit_status(batch):
    out, result = batch
    assert result.returncode == 1, result.stdout + result.stderr
    rows = summary(out)
    assert set(rows) == EXPECTED
    assert [rows[name]["status"] for name in TRACKED] == ["tracked"] * 3
    assert rows["broken"]["status"] == "failed"
    assert "cannot decode as an image" in rows["broken"]["error"]
    assert "broken: FAILED" in result.stdout


@pytest.mark.parametrize("name", ["press-slide", "sim/exp_0000"])
def test_tables_are_those_of_gelstereo_track(batch, root, gelstereo, tmp_path, name):
    out, _ = batch
    direct = tmp_path / "direct"
    subprocess.run([gelstereo, "track", str(root / name), "--out", str(direct), "--quiet", *TRACK_ARGS], check=True)
    for table in ("frames.csv", "markers.csv"):
        assert (out / name / table).read_bytes() == (direct / table).read_bytes(), f"{name}/{table}"


def test_summary_row_is_read_from_the_recordings_frames_csv(batch):
    out, _ = batch
    rows = summary(out)
    for name in TRACKED:
        with open(out / name / "frames.csv", newline="") as f:
            frames = list(csv.DictReader(f))
        row = rows[name]
        assert int(row["frames"]) == len(frames)
        assert int(row["measured_frames"]) == sum(1 for r in frames if r["contact"])
        assert float(row["peak_force_N"]) == max(float(r["force_N"]) for r in frames if r["force_N"])
        assert float(row["max_depth_mm"]) == max(float(r["max_depth_mm"]) for r in frames if r["max_depth_mm"])
        gross = [r for r in frames if r["slip"] == "gross_slip"]
        assert row["first_gross_slip_frame"] == (gross[0]["frame"] if gross else "")
    # The sample presses, then slides: its gross slip starts after the first frame.
    assert int(rows["press-slide"]["first_gross_slip_frame"]) > 0
    assert rows["press-slide"]["first_gross_slip_t_s"]


def test_a_rerun_reuses_finished_outputs_and_force_tracks_again(batch, root, gelstereo):
    out, _ = batch
    tables = out / "press-slide" / "frames.csv"
    before = tables.stat().st_mtime_ns
    again = run_batch(gelstereo, root, out)
    assert again.returncode == 1, again.stdout + again.stderr
    rows = summary(out)
    assert [rows[name]["status"] for name in TRACKED] == ["reused"] * 3
    assert rows["broken"]["status"] == "failed", "a failed recording is tried again"
    assert tables.stat().st_mtime_ns == before

    # ROOT a recording itself: its own name; --force tracks it again into the same folder.
    forced = run_batch(gelstereo, root / "press-slide", out, "--force")
    assert forced.returncode == 0, forced.stdout + forced.stderr
    assert summary(out)["press-slide"]["status"] == "tracked"
    assert tables.stat().st_mtime_ns != before


def test_a_folder_gelstereo_did_not_write_is_left_alone(root, gelstereo, tmp_path):
    mine = tmp_path / "out" / "press-slide" / "my-notes.txt"
    mine.parent.mkdir(parents=True)
    mine.write_text("keep me\n")
    result = run_batch(gelstereo, root / "press-slide", tmp_path / "out", "--force")
    assert result.returncode == 1, result.stdout + result.stderr
    assert "no gelstereo manifest" in summary(tmp_path / "out")["press-slide"]["error"]
    assert sorted(p.name for p in mine.parent.iterdir()) == ["my-notes.txt"]
    assert mine.read_text() == "keep me\n"


def test_recordings_are_found_at_any_depth_but_not_inside_the_output_or_a_link_cycle(tmp_path):
    sys.path.insert(0, str(HERE))
    try:
        import batch_dask
    finally:
        sys.path.remove(str(HERE))
    root = tmp_path / "root"
    # b/extra lies inside a recording, .hidden/c in a hidden folder, out/d in the output folder.
    for rec in ("a", "deep/er/b", "deep/er/b/extra", ".hidden/c", "out/d"):
        for side in ("left", "right"):
            (root / rec / side).mkdir(parents=True, exist_ok=True)
    (root / "deep" / "loop").symlink_to(root)
    (root / "deep" / "clip.MP4").write_bytes(b"")
    names = [r.name for r in batch_dask.find_recordings(root, root / "out", videos=False)]
    assert names == ["a", "deep/er/b"]
    names = [r.name for r in batch_dask.find_recordings(root, root / "out", videos=True)]
    assert names == ["a", "deep/clip.MP4", "deep/er/b"]
    assert [r.name for r in batch_dask.find_recordings(root / "a", root / "out", videos=False)] == ["a"]
