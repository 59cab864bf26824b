"""Tracks a stereo recording with gelstereo and plots the largest indentation depth and the slip
state over time.

    .venv/bin/python examples/python/track_and_plot.py data/sample/press-slide --out depth-slip.png

The calibration is the recording's calib.yaml unless --calib names another; frames are read by
`gelstereo.open`, with their times (the recording's frame rate, else 30 Hz).
"""

import argparse
import sys
from pathlib import Path

import numpy as np

import gelstereo

try:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:
    sys.exit("matplotlib is missing: run scripts/setup.sh (it installs examples/python/requirements.txt)")

SLIP_STATES = ["no_contact", "stick", "partial_slip", "gross_slip"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", type=Path, help="stereo recording: a folder with left/ and right/")
    parser.add_argument("--calib", type=Path, help="stereo calibration (default: RECORDING/calib.yaml)")
    parser.add_argument("--out", type=Path, default=Path("depth-slip.png"), help="plot file (PNG, SVG, PDF)")
    args = parser.parse_args()

    pipeline = gelstereo.Pipeline(calibration=str(args.calib or args.recording / "calib.yaml"))
    times_s, depth_mm, slip = [], [], []
    for source in gelstereo.open(args.recording):
        if source.error is not None:
            print(f"frame {source.index}: {source.error}")
            continue
        frame = pipeline.process(source.left, source.right, source.timestamp)
        times_s.append(frame.timestamp)
        depth_mm.append(frame.contact.max_depth_mm)
        # A flagged frame (unreadable, no usable markers) knows no slip state: a gap in the plot.
        slip.append(np.nan if frame.slip is None else SLIP_STATES.index(frame.slip))
        tracked = int((frame.markers["status"] == "tracked").sum())
        print(f"t = {frame.timestamp:6.3f} s  depth {frame.contact.max_depth_mm:5.3f} mm  "
              f"{frame.slip or 'unknown':<12}  {tracked} markers tracked")

    figure, (depth_axes, slip_axes) = plt.subplots(2, 1, sharex=True, figsize=(7, 5), constrained_layout=True)
    depth_axes.plot(times_s, depth_mm, color="tab:blue")
    depth_axes.set_ylabel("largest indentation depth (mm)")
    depth_axes.set_title(f"{args.recording.name}: contact over time")
    depth_axes.grid(alpha=0.3)
    slip_axes.step(times_s, slip, where="post", color="tab:red")
    slip_axes.set_yticks(range(len(SLIP_STATES)), SLIP_STATES)
    slip_axes.set_ylim(-0.5, len(SLIP_STATES) - 0.5)
    slip_axes.set_xlabel("time (s)")
    slip_axes.set_ylabel("slip state")
    slip_axes.grid(alpha=0.3)
    figure.savefig(args.out, dpi=120)
    print(f"plot written to {args.out}")


if __name__ == "__main__":
    main()
