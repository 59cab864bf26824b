"""What one Marknet view costs in ONNX Runtime on this CPU, and where: medians side by side in one run.

    cd train && ../.venv/bin/python scripts/network_cost.py ../data/models/marknet.onnx OTHER/marknet.onnx
        [--height 320 --width 416] [--runs 200] [--int8 DATA_ROOT] [--profile]

Per model: fp32 at 1 and 2 intra-op threads (graph optimisation "all", as `gelstereo-markers` sets it, no
spinning), per image at batch 2 and 4, and with `--int8 DATA_ROOT` the static int8 builds of
`gelstereo_train.quantize` calibrated on that dataset's train split: its recipe (stem and detection head
left in float), the recipe with the decoder (top-down path) in float too, and everything quantized, per image at batch 2 (a stereo pair) and one thread, with their
ratio to fp32's CPU time measured interleaved with it; `--profile` lists the 8
costliest nodes (share of kernel time, one thread). Random input of the reference sensor's auto layout
(416 x 320).
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gelstereo_train.quantize import quantize  # noqa: E402


def session(path: Path, threads: int, profile: Path | None = None) -> ort.InferenceSession:
    """A CPU session as `gelstereo-markers` opens one; `profile`: write a profile with this prefix."""
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if profile is not None:
        so.enable_profiling = True
        so.profile_file_prefix = str(profile)
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def median_ms(s: ort.InferenceSession, x: np.ndarray, runs: int) -> float:
    name = s.get_inputs()[0].name
    for _ in range(20):
        s.run(None, {name: x})
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        s.run(None, {name: x})
        times.append(time.perf_counter() - t)
    return float(np.median(times)) * 1e3


def interleaved_cpu_ms(sessions: list[ort.InferenceSession], x: np.ndarray, rounds: int) -> list[float]:
    """Median CPU time per run of each session, ms: rounds of 5 runs each, the sessions in turn, so that
    a shared machine's swings fall on all of them alike."""
    name = sessions[0].get_inputs()[0].name
    for s in sessions:
        for _ in range(5):
            s.run(None, {name: x})
    times: list[list[float]] = [[] for _ in sessions]
    for _ in range(rounds):
        for s, t in zip(sessions, times):
            start = time.process_time()
            for _ in range(5):
                s.run(None, {name: x})
            t.append((time.process_time() - start) / 5)
    return [float(np.median(t)) * 1e3 for t in times]


def costliest_nodes(path: Path, x: np.ndarray, runs: int, out_dir: Path, top: int = 8) -> list[tuple[str, str, float]]:
    s = session(path, 1, profile=out_dir / f"{path.stem}_profile")
    median_ms(s, x, runs)
    spent: collections.Counter = collections.Counter()
    what = {}
    for e in json.loads(Path(s.end_profiling()).read_text()):
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            spent[e["name"]] += e["dur"]
            what[e["name"]] = (e["args"].get("op_name"), str(e["args"].get("output_type_shape")))
    total = sum(spent.values()) or 1
    return [(what[k][0], what[k][1], 100.0 * v / total) for k, v in spent.most_common(top)]


# The parts each int8 build leaves in float (`gelstereo_train.quantize.PARTS`), one table column each.
INT8_BUILDS = (("stem", "head"), ("stem", "head", "decoder"), ())


def quantised(path: Path, data_root: Path, out_dir: Path, keep_float: tuple[str, ...]) -> Path:
    """`path` quantized by `gelstereo_train.quantize` (the model card's int8 recipe), `keep_float` parts
    left in float."""
    out = out_dir / f"{path.stem}_int8_{'_'.join(keep_float) or 'all'}.onnx"
    quantize(path, data_root, out, keep_float=keep_float)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("models", type=Path, nargs="+", help="marknet.onnx files")
    p.add_argument("--height", type=int, default=320)
    p.add_argument("--width", type=int, default=416)
    p.add_argument("--runs", type=int, default=200)
    p.add_argument("--int8", type=Path, default=None, metavar="DATA_ROOT",
                   help="also time gelstereo_train.quantize's int8 builds, calibrated on this dataset")
    p.add_argument("--profile", action="store_true", help="list the costliest nodes")
    args = p.parse_args(argv)
    rng = np.random.default_rng(0)
    x1 = rng.random((1, 3, args.height, args.width), dtype=np.float32)
    print(f"onnxruntime {ort.__version__}, input {args.width} x {args.height}, median of {args.runs} runs, ms per image")
    print("| model | fp32, 1 thread | fp32, 2 threads | batch 2 | batch 4 | int8, stem and head fp32 "
          "| int8, stem, head and decoder fp32 | int8, all |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.models:
            row = [median_ms(session(path, 1), x1, args.runs), median_ms(session(path, 2), x1, args.runs)]
            for n in (2, 4):
                xn = np.repeat(x1, n, axis=0)
                row.append(median_ms(session(path, 1), xn, args.runs // 2) / n)
            int8 = ["-"] * len(INT8_BUILDS)
            if args.int8 is not None:
                builds = [quantised(path, args.int8, Path(tmp), keep) for keep in INT8_BUILDS]
                x2 = np.repeat(x1, 2, axis=0)
                fp32, *quantized = interleaved_cpu_ms([session(m, 1) for m in [path, *builds]], x2, args.runs // 5)
                int8 = [f"{ms / 2:.2f} ({ms / fp32:.2f}x)" for ms in quantized]
            print(f"| {path} | " + " | ".join(f"{v:.2f}" for v in row) + f" | {' | '.join(int8)} |")
        if args.profile:
            for path in args.models:
                print(f"\ncostliest nodes of {path} (one thread):")
                for op, shape, share in costliest_nodes(path, x1, args.runs // 2, Path(tmp)):
                    print(f"  {share:5.1f} %  {op:14s} {shape}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
