"""A live view of gelstereo on rerun: both camera views with their markers, the 3-D marker surface
in the gel frame coloured by indentation depth and by pressure, and force, area, depth and the slip
state over time.

    python -m gelstereo.view SOURCE [--calib FILE] [--rrd FILE] [--spawn]

SOURCE is what `gelstereo.open` takes: a stereo recording folder, a folder of images, a video
(`--side-by-side` for both views in one frame) or a camera index ("0", or "0,1" for two). Frames go
to a rerun viewer listening on this machine (`rerun`, port 9876), to a new one with `--spawn`, or,
when neither, into `--rrd FILE` (default gelstereo.rrd; open it later with `rerun FILE`).
Needs rerun-sdk: `pip install "gelstereo[view]"`.
"""

import argparse
import socket
import sys
from pathlib import Path
from typing import Optional

import numpy as np

import gelstereo

VIEWER_PORT = 9876
SLIP_STATES = ["no_contact", "stick", "partial_slip", "gross_slip"]
# Colours of the markers' status in the camera views (RGB).
STATUS_COLOURS = {"tracked": (40, 200, 80), "predicted": (240, 180, 30), "lost": (220, 40, 40)}
# Depth (mm) and pressure (kPa) at the top of their colour scales.
FULL_DEPTH_MM = 1.0
FULL_PRESSURE_KPA = 100.0


def viewer_listening(port: int = VIEWER_PORT) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def ramp(values: np.ndarray, full: float) -> np.ndarray:
    """Blue (0) to red (`full` and above) as RGB uint8 rows; grey where a value is unknown."""
    t = np.clip(np.nan_to_num(values, nan=0.0) / full, 0.0, 1.0)
    colours = np.column_stack([255 * t, 60 + 80 * (1 - np.abs(2 * t - 1)), 255 * (1 - t)])
    colours[np.isnan(values)] = 128
    return colours.astype(np.uint8)


def log_view(rr, name: str, image: np.ndarray, x: np.ndarray, y: np.ndarray, status: np.ndarray) -> None:
    rr.log(f"camera/{name}", rr.Image(image, color_model="BGR" if image.ndim == 3 else "L"))
    seen = ~np.isnan(x)
    colours = np.array([STATUS_COLOURS.get(s, (128, 128, 128)) for s in status], dtype=np.uint8).reshape(-1, 3)
    rr.log(f"camera/{name}/markers", rr.Points2D(np.column_stack([x, y])[seen], colors=colours[seen], radii=2.0))


def log_frame(rr, frame, left: np.ndarray, right: Optional[np.ndarray]) -> None:
    """One processed frame: views and markers, the 3-D surface, the contact figures and slip."""
    m = frame.markers
    log_view(rr, "left", left, m["x_left"], m["y_left"], m["status"])
    if right is not None:
        log_view(rr, "right", right, m["x_right"], m["y_right"], m["status"])
    gel = np.column_stack([m["X_gel_mm"], m["Y_gel_mm"], m["Z_gel_mm"]])
    in_3d = ~np.isnan(gel).any(axis=1)
    if in_3d.any():
        depth = -m["dZ_gel_mm"][in_3d]  # pressed in: the gel frame's z points out of the gel
        rr.log("gel/depth", rr.Points3D(gel[in_3d], colors=ramp(depth, FULL_DEPTH_MM), radii=0.08))
        pressure = m["pressure_kPa"][in_3d]
        rr.log("gel/pressure", rr.Points3D(gel[in_3d], colors=ramp(pressure, FULL_PRESSURE_KPA), radii=0.08))
        moved = np.column_stack([m["dX_gel_mm"], m["dY_gel_mm"], m["dZ_gel_mm"]])[in_3d]
        rr.log("gel/displacement", rr.Arrows3D(origins=gel[in_3d] - moved, vectors=moved))
    for name, value in (("force_N", frame.contact.force_n), ("area_mm2", frame.contact.area_mm2),
                        ("max_depth_mm", frame.contact.max_depth_mm)):
        if np.isfinite(value):
            rr.log(f"contact/{name}", rr.Scalars(value))
    if frame.slip is not None:  # None: a flagged frame, its contact unknown
        rr.log("slip/level", rr.Scalars(SLIP_STATES.index(frame.slip)))
        rr.log("slip/state", rr.TextLog(frame.slip))
    if frame.note:
        rr.log("slip/state", rr.TextLog(f"frame {frame.frame}: {frame.note}", level="WARN"))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m gelstereo.view", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", help="recording folder, folder of images, video, or camera index (N or L,R)")
    parser.add_argument("--calib", type=Path, help="stereo calibration (default: SOURCE/calib.yaml if present)")
    parser.add_argument("--grid", help="marker lattice ROWSxCOLS (default: the recording's, else 23x23)")
    parser.add_argument("--pitch-mm", type=float, help="a mono sensor's marker pitch, mm")
    parser.add_argument("--side-by-side", action="store_true", help="video or camera with both views side by side")
    parser.add_argument("--mono", action="store_true", help="track the left view only")
    parser.add_argument("--rrd", type=Path, default=Path("gelstereo.rrd"), help="file to record into when no viewer listens")
    parser.add_argument("--spawn", action="store_true", help="start a rerun viewer")
    parser.add_argument("--max-frames", type=int, help="stop after this many frames")
    args = parser.parse_args(argv)
    try:
        import rerun as rr
    except ImportError:
        print('rerun-sdk is not installed: pip install "gelstereo[view]"', file=sys.stderr)
        return 2

    calib = args.calib
    if calib is None and (Path(args.source) / "calib.yaml").is_file():
        calib = Path(args.source) / "calib.yaml"
    # gelstereo.open reads a path, or camera numbers as text ("0", "0,1").
    frames = gelstereo.open(args.source, side_by_side=args.side_by_side, mono=args.mono)
    stereo = frames.is_stereo and not args.mono and calib is not None
    pipeline = gelstereo.Pipeline(calibration=calib if stereo else None, grid=args.grid,
                                  pitch_mm=args.pitch_mm, mono=not stereo)

    rr.init("gelstereo", spawn=args.spawn)
    if not args.spawn:
        if viewer_listening():
            rr.connect_grpc()
            print(f"streaming to the rerun viewer on port {VIEWER_PORT}")
        else:
            rr.save(str(args.rrd))
            print(f"no rerun viewer on port {VIEWER_PORT}: recording into {args.rrd} (open it with `rerun {args.rrd}`)")
    rr.log("gel", rr.ViewCoordinates.RFU, static=True)  # gel frame: x, y along the lattice, z out of the gel
    count = 0
    for f in frames:
        if args.max_frames is not None and count >= args.max_frames:
            break
        rr.set_time("frame", sequence=f.index)
        rr.set_time("time", duration=f.timestamp)
        if f.error is not None:
            rr.log("slip/state", rr.TextLog(f"frame {f.index}: {f.error}", level="WARN"))
            continue
        right = f.right if stereo else None
        out = pipeline.process(f.left, right, f.timestamp)
        log_frame(rr, out, f.left, right)
        count += 1
    rr.disconnect()
    print(f"{count} frames shown")
    return 0


if __name__ == "__main__":
    sys.exit(main())
