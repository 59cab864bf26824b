"""Tracks every recording under a folder in parallel on Dask, one `gelstereo track` per recording,
and writes one output folder per recording and a summary table.

    .venv/bin/python examples/python/batch_dask.py ROOT --out OUT [--workers N | --scheduler ADDRESS]
        [--gelstereo PATH] [--videos] [--force] [-- TRACK ARGS]

A recording is a folder with left/ and right/ (a stereo recording, tracked with its calib.yaml unless
the TRACK ARGS give --calib); with --videos a video file is one too. ROOT may itself be one. Each
recording is one Dask task that runs the real CLI, `gelstereo track REC --out OUT/NAME TRACK ARGS`,
NAME being the recording's path below ROOT (ROOT's own name when ROOT is the recording), so nested
recordings keep their folders and no two share an output. OUT/summary.csv has one row per recording.

Without --scheduler the tasks run on a local cluster of --workers processes; with it, on a running
Dask cluster, whose workers must see ROOT and OUT at the same paths and find `gelstereo` on their
PATH (or at --gelstereo PATH). A recording that fails is a row with its error; the others go on.
Exit status: 0 when every recording has its tables, 1 when one or more failed, 2 for a usage error.

Re-running skips a recording whose OUT/NAME/batch.json records a finished run of the same recording
and TRACK ARGS (another binary's outputs are not noticed: give --force). --force tracks it again.
An OUT/NAME that gelstereo did not write is refused, as `gelstereo track` refuses it (that recording
fails; `-- --force` passes track's own --force).
"""

import argparse
import contextlib
import csv
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Dict, Iterator, List, Optional, Sequence, Tuple

try:
    from dask.distributed import Client, LocalCluster, as_completed
except ImportError:
    sys.exit("dask.distributed is missing: run scripts/setup.sh (it installs examples/python/requirements-batch.txt)")

SUMMARY = "summary.csv"
DONE = "batch.json"
# As gelstereo_io::video::VIDEO_EXTENSIONS: the files `gelstereo track` reads as videos.
VIDEO_SUFFIXES = {".avi", ".mp4", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg"}
COLUMNS = [
    "recording", "status", "frames", "measured_frames", "peak_force_N", "max_depth_mm",
    "max_contact_area_mm2", "first_gross_slip_frame", "first_gross_slip_t_s", "track_s", "source", "error",
]


@dataclass(frozen=True)
class Recording:
    name: str  # the output folder below OUT, '/'-separated
    source: str  # absolute path given to `gelstereo track`


def is_stereo_recording(folder: Path) -> bool:
    return (folder / "left").is_dir() and (folder / "right").is_dir()


def find_recordings(root: Path, out: Path, videos: bool) -> List[Recording]:
    """The recordings under `root` by name, not looking inside a recording, hidden folders or `out`.
    Folder links are followed (a folder of links to recordings is a batch), link cycles are not."""
    if is_stereo_recording(root):
        source = os.path.abspath(root)
        return [Recording(os.path.basename(source), source)]
    found: List[Recording] = []
    walk(root, PurePosixPath(), frozenset({root.resolve()}), out.resolve(), videos, found)
    return sorted(found, key=lambda r: r.name)


def walk(folder: Path, rel: PurePosixPath, ancestors: frozenset, out: Path, videos: bool, found: list) -> None:
    try:
        entries = sorted(os.scandir(folder), key=lambda e: e.name)
    except OSError as e:
        print(f"warning: {folder}: cannot list ({e.strerror}); its recordings are left out", file=sys.stderr)
        return
    for entry in entries:
        path = Path(entry.path)
        if entry.name.startswith("."):
            continue
        if entry.is_dir():
            real = path.resolve()
            if real == out or real in ancestors:
                continue
            if is_stereo_recording(path):
                found.append(Recording(str(rel / entry.name), os.path.abspath(path)))
            else:
                walk(path, rel / entry.name, ancestors | {real}, out, videos, found)
        elif videos and entry.is_file() and path.suffix.lower() in VIDEO_SUFFIXES:
            found.append(Recording(str(rel / entry.name), os.path.abspath(path)))


# --- One task: runs on a Dask worker -------------------------------------------------------------


def track_one(rec: Recording, out_dir: str, track_args: List[str], gelstereo: str, force: bool) -> Dict[str, str]:
    """Tracks `rec` into `out_dir` (unless an earlier run of the same command finished there) and
    returns its summary row. Never raises for a failing recording: the row says why."""
    row = {"recording": rec.name, "source": rec.source}
    out = Path(out_dir)
    done = {"recording": rec.source, "track_args": track_args}
    try:
        if not force:
            recorded = finished_before(out, done)
            if recorded is not None:
                summary = summarise(out / "frames.csv")
                return {**row, "status": "reused", "track_s": recorded.get("track_s", ""), **summary}
        exe = shutil.which(gelstereo)
        if exe is None:
            error = f"{gelstereo}: not found on this worker (put gelstereo on its PATH or give --gelstereo PATH)"
            return {**row, "status": "failed", "error": error}
        if (out / ".gelstereo-manifest").is_file():  # a folder gelstereo wrote: its batch.json is ours
            with contextlib.suppress(FileNotFoundError):
                (out / DONE).unlink()  # an interrupted re-run must not look finished
        start = time.monotonic()
        error = run_track(exe, rec.source, out, track_args)
        seconds = f"{time.monotonic() - start:.1f}"
        if error:
            return {**row, "status": "failed", "track_s": seconds, "error": error}
        summary = summarise(out / "frames.csv")
        write_done(out, {**done, "track_s": seconds})
        return {**row, "status": "tracked", "track_s": seconds, **summary}
    except (OSError, ValueError, KeyError) as e:
        return {**row, "status": "failed", "error": f"{type(e).__name__}: {e}"}


def finished_before(out: Path, done: dict) -> Optional[dict]:
    """The batch.json of an earlier run that finished the same command into `out`, else None."""
    try:
        recorded = json.loads((out / DONE).read_text())
    except (OSError, ValueError):
        return None
    same = isinstance(recorded, dict) and all(recorded.get(k) == v for k, v in done.items())
    tables = (out / "frames.csv").is_file() and (out / "markers.csv").is_file()
    return recorded if same and tables else None


def write_done(out: Path, done: dict) -> None:
    partial = out / f".partial-{DONE}"
    partial.write_text(json.dumps(done, indent=1) + "\n")
    partial.replace(out / DONE)


def run_track(exe: str, source: str, out: Path, track_args: List[str]) -> Optional[str]:
    """Runs `gelstereo track`; the error it printed when it failed, else None."""
    quiet = [] if "--quiet" in track_args else ["--quiet"]
    command = [exe, "track", source, "--out", str(out), *quiet, *track_args]
    result = subprocess.run(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, errors="replace")
    if result.returncode == 0:
        return None
    lines = [line.strip() for line in result.stderr.splitlines() if line.strip()]
    if not lines:
        return f"gelstereo track exited with status {result.returncode}"
    return lines[-1].removeprefix("error: ")


def summarise(frames_csv: Path) -> Dict[str, str]:
    """A recording's row from its frames.csv; the figures are the table's own cells, empty where the
    sensor gives none (a mono sensor's force and depth)."""
    with open(frames_csv, newline="") as f:
        rows = list(csv.DictReader(f))
    gross = next((r for r in rows if r.get("slip") == "gross_slip"), {})
    return {
        "frames": str(len(rows)),
        "measured_frames": str(sum(1 for r in rows if r.get("contact"))),
        "peak_force_N": largest(rows, "force_N"),
        "max_depth_mm": largest(rows, "max_depth_mm"),
        "max_contact_area_mm2": largest(rows, "contact_area_mm2"),
        "first_gross_slip_frame": gross.get("frame", ""),
        "first_gross_slip_t_s": gross.get("t_s") or "",
    }


def largest(rows: List[Dict[str, str]], column: str) -> str:
    return max((r[column] for r in rows if r.get(column)), key=float, default="")


# --- The client: finds the recordings, submits them, writes the summary -------------------------


def parse_args(argv: Sequence[str]) -> Tuple[argparse.Namespace, List[str]]:
    own, track_args = split_track_args(list(argv))
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", type=Path, help="a recording, or a folder with recordings at any depth")
    parser.add_argument("--out", type=Path, required=True,
                        help="output folder: OUT/NAME per recording, OUT/summary.csv")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--scheduler", metavar="ADDRESS", help="a running Dask scheduler, e.g. tcp://host:8786")
    where.add_argument("--workers", type=int, default=2, metavar="N",
                       help="worker processes of the local cluster (default 2); each track uses every core unless "
                            "the TRACK ARGS say `--workers 1 --threads 1`")
    parser.add_argument("--gelstereo", default="gelstereo", metavar="PATH",
                        help="the gelstereo binary as the workers find it (default: `gelstereo` on their PATH)")
    parser.add_argument("--videos", action="store_true", help="video files under ROOT are recordings too")
    parser.add_argument("--force", action="store_true", help="track again recordings whose outputs are complete")
    args = parser.parse_args(own)
    if not args.root.exists():
        parser.error(f"{args.root}: no such file or folder")
    if args.workers < 1:
        parser.error("--workers: at least 1")
    if any(a == "--out" or a.startswith("--out=") for a in track_args):
        parser.error("--out is set per recording (OUT/NAME); leave it out of the TRACK ARGS")
    if os.sep in args.gelstereo and os.path.exists(args.gelstereo):
        args.gelstereo = os.path.abspath(args.gelstereo)
    return args, track_args


def split_track_args(argv: List[str]) -> Tuple[List[str], List[str]]:
    if "--" in argv:
        cut = argv.index("--")
        return argv[:cut], argv[cut + 1:]
    return argv, []


@contextlib.contextmanager
def dask_client(args: argparse.Namespace) -> Iterator[Client]:
    if args.scheduler:
        with Client(args.scheduler) as client:
            yield client
        return
    # One thread per worker process: a task is a subprocess that uses its own threads.
    with LocalCluster(n_workers=args.workers, threads_per_worker=1, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        yield client


def run_all(client: Client, recordings: List[Recording], args: argparse.Namespace,
            track_args: List[str]) -> List[Dict[str, str]]:
    out = args.out.resolve()
    futures = {
        client.submit(track_one, rec, str(out / rec.name), track_args, args.gelstereo, args.force, pure=False): rec
        for rec in recordings
    }
    rows = []
    for k, future in enumerate(as_completed(futures), start=1):
        rec = futures[future]
        try:
            row = future.result()
        except Exception as e:  # the task itself was lost (a worker died each time it ran it)
            row = {"recording": rec.name, "source": rec.source, "status": "failed", "error": f"dask: {e}"}
        rows.append(row)
        print(f"[{k}/{len(recordings)}] {progress_line(row)}", flush=True)
    return sorted(rows, key=lambda r: r["recording"])


def progress_line(row: Dict[str, str]) -> str:
    if row["status"] == "failed":
        return f"{row['recording']}: FAILED: {row['error']}"
    took = f" in {row['track_s']} s" if row.get("track_s") else ""
    return (f"{row['recording']}: {row['status']}{took}, {row['frames']} frames, "
            f"max depth {row['max_depth_mm'] or '-'} mm, peak force {row['peak_force_N'] or '-'} N")


def write_summary(path: Path, rows: List[Dict[str, str]]) -> None:
    partial = path.with_name(f".partial-{path.name}")
    with open(partial, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS, restval="", lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    partial.replace(path)


def main(argv: Sequence[str]) -> int:
    args, track_args = parse_args(argv)
    recordings = find_recordings(args.root, args.out, args.videos)
    if not recordings:
        kinds = "folders with left/ and right/" + (" or video files" if args.videos else "")
        print(f"error: {args.root}: no recordings found ({kinds})", file=sys.stderr)
        return 2
    if any(PurePosixPath(r.name).parts[0] == SUMMARY for r in recordings):
        print(f"error: a recording named {SUMMARY} at the top of {args.root} would take the summary's place; "
              "move it into a folder", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    with dask_client(args) as client:
        rows = run_all(client, recordings, args, track_args)
    write_summary(args.out / SUMMARY, rows)
    failed = sum(1 for r in rows if r["status"] == "failed")
    print(f"{len(rows)} recordings, {failed} failed: {args.out / SUMMARY}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
