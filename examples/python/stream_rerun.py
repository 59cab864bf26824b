"""Streams a stereo recording tracked by gelstereo to rerun: the left image with the markers, the
3-D marker cloud coloured by depth with displacement arrows, the depth and the slip state.

    .venv/bin/python examples/python/stream_rerun.py data/sample/press-slide [--rrd out.rrd]

Sends to a rerun viewer listening on this machine (`rerun`, default port 9876); when none listens,
saves a recording to --rrd (default gelstereo.rrd) to open later with `rerun gelstereo.rrd`.
Needs rerun-sdk: `scripts/setup.sh --with-rerun` (or `pip install rerun-sdk`).
"""

import argparse
import socket
import sys
from pathlib import Path

import numpy as np

import gelstereo
from recording import stereo_frames

try:
    import rerun as rr
except ImportError:
    sys.exit(
        "rerun-sdk is not installed: run scripts/setup.sh --with-rerun "
        "(or .venv/bin/python -m pip install -r examples/python/requirements-rerun.txt)"
    )

VIEWER_PORT = 9876
SLIP_STATES = ["no_contact", "stick", "partial_slip", "gross_slip"]


def viewer_listening(port: int = VIEWER_PORT) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def log_frame(frame, left) -> None:
    """One tracked frame: image and 2-D markers, 3-D cloud and displacement, contact and slip."""
    m = frame.markers
    rr.log("camera/left", rr.Image(left, color_model="BGR"))
    seen = ~np.isnan(m["x_left"])
    rr.log("camera/left/markers", rr.Points2D(np.column_stack([m["x_left"], m["y_left"]])[seen], radii=2.0))
    xyz = np.column_stack([m["X_mm"], m["Y_mm"], m["Z_mm"]])
    displacement = np.column_stack([m["dX_mm"], m["dY_mm"], m["dZ_mm"]])
    in_3d = ~np.isnan(xyz).any(axis=1)
    depth = np.nan_to_num(m["dZ_mm"][in_3d])
    colours = np.column_stack([np.clip(depth / 0.5, 0, 1) * 255, np.full(depth.shape, 80), 200 - np.clip(depth / 0.5, 0, 1) * 150])
    rr.log("markers/cloud", rr.Points3D(xyz[in_3d], colors=colours.astype(np.uint8), radii=0.05))
    moved = in_3d & ~np.isnan(displacement).any(axis=1)
    rr.log("markers/displacement", rr.Arrows3D(origins=xyz[moved] - displacement[moved], vectors=displacement[moved]))
    rr.log("contact/max_depth_mm", rr.Scalars(frame.contact.max_depth_mm))
    rr.log("contact/area_mm2", rr.Scalars(frame.contact.area_mm2))
    if frame.slip is not None:  # None: a flagged frame, its contact unknown
        rr.log("slip/level", rr.Scalars(SLIP_STATES.index(frame.slip)))
        rr.log("slip/state", rr.TextLog(frame.slip))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", type=Path, help="stereo recording: a folder with left/ and right/")
    parser.add_argument("--calib", type=Path, help="stereo calibration (default: RECORDING/calib.yaml)")
    parser.add_argument("--fps", type=float, default=30.0, help="frame rate of the recording (default 30)")
    parser.add_argument("--rrd", type=Path, default=Path("gelstereo.rrd"), help="recording file when no viewer runs")
    args = parser.parse_args()

    rr.init("gelstereo")
    if viewer_listening():
        rr.connect_grpc()
        print(f"streaming to the rerun viewer on port {VIEWER_PORT}")
    else:
        rr.save(str(args.rrd))
        print(f"no rerun viewer listening on port {VIEWER_PORT}: saving to {args.rrd} (open with `rerun {args.rrd}`)")
    rr.log("markers", rr.ViewCoordinates.RDF, static=True)  # camera frame: x right, y down, z forward

    pipeline = gelstereo.Pipeline(calibration=str(args.calib or args.recording / "calib.yaml"))
    for k, left, right in stereo_frames(args.recording):
        frame = pipeline.process(left, right, timestamp=k / args.fps)
        rr.set_time("frame", sequence=k)
        rr.set_time("time", duration=frame.timestamp)
        log_frame(frame, left)
    rr.disconnect()
    print(f"{k + 1} frames logged")


if __name__ == "__main__":
    main()
