"""CPU time of Marknet shapes with random weights, side by side: what a shape would cost before it is trained.

    cd train && ../.venv/bin/python scripts/shape_cost.py s4:8:3 s4-bare:8:1 s4-bare:10:1 [--height 288 --width 320]

Each SHAPE is STEM:WIDTH:FUSE_KERNEL (`train_marknet --stem --width --fuse-kernel`; stride 8, m = 5).
Every shape is exported to ONNX by `gelstereo_train.export` (dynamic height and width, as shipped) and
timed on one stereo pair (batch 2) of a random input at one intra-op thread, as the localizer's
throughput workers run it: process CPU time per run, the shapes in turn within each round so that a
shared machine's swings fall on all alike, median over the rounds; printed per round and overall.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from gelstereo_train.export import export_marknet  # noqa: E402
from gelstereo_train.model import FUSE_KERNELS, STEMS, Marknet  # noqa: E402
from network_cost import interleaved_cpu_ms, session  # noqa: E402


def parse_shape(text: str) -> dict:
    """STEM:WIDTH:FUSE_KERNEL as Marknet's arguments; ValueError naming what was expected."""
    parts = text.split(":")
    if (len(parts) != 3 or parts[0] not in STEMS or not parts[1].isdigit() or int(parts[1]) < 1
            or not parts[2].isdigit() or int(parts[2]) not in FUSE_KERNELS):
        raise ValueError(f"shape {text!r}: expected STEM:WIDTH:FUSE_KERNEL, STEM one of {', '.join(STEMS)}, "
                         f"WIDTH a positive integer, FUSE_KERNEL one of {FUSE_KERNELS} (e.g. s4-bare:8:1)")
    return {"stem": parts[0], "width": int(parts[1]), "fuse_kernel": int(parts[2])}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("shapes", nargs="+", help="STEM:WIDTH:FUSE_KERNEL, e.g. s4-bare:8:1")
    p.add_argument("--height", type=int, default=288)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--runs", type=int, default=40, help="runs of 5 per shape and round")
    args = p.parse_args(argv)
    try:
        shapes = [parse_shape(t) for t in args.shapes]
    except ValueError as e:
        p.error(str(e))
    torch.manual_seed(0)
    x = np.random.default_rng(0).random((2, 3, args.height, args.width), dtype=np.float32)
    print(f"one stereo pair, 2 x 3 x {args.height} x {args.width}, one thread, CPU ms per run")
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for i, (shape, arch) in enumerate(zip(args.shapes, shapes)):
            model = Marknet(stride=8, candidates=5, **arch).eval()
            path = Path(tmp) / f"shape{i}.onnx"
            export_marknet(model, path, (args.height, args.width), {})
            params = sum(q.numel() for q in model.parameters())
            print(f"{shape}: {params} parameters")
            paths.append(path)
        rounds = []
        for r in range(args.rounds):
            ms = interleaved_cpu_ms([session(q, 1) for q in paths], x, args.runs)
            rounds.append(ms)
            print(f"round {r + 1}: " + ", ".join(f"{s} {v:.2f}" for s, v in zip(args.shapes, ms)))
        median = np.median(np.array(rounds), axis=0)
        print("median: " + ", ".join(f"{s} {v:.2f} ({v / median[0]:.2f}x the first)" for s, v in zip(args.shapes, median)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
