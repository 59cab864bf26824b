"""What one Marknet view costs in ONNX Runtime on this CPU, and where: medians side by side in one run.

    cd train && ../.venv/bin/python scripts/network_cost.py ../data/models/marknet.onnx OTHER/marknet.onnx
        [--height 320 --width 416] [--runs 200] [--int8 DATA_ROOT] [--profile]

Per model: fp32 at 1 and 2 intra-op threads (graph optimisation "all", as `gelstereo-markers` sets it, no
spinning), per image at batch 2 and 4, and with `--int8 DATA_ROOT` a static int8 (QDQ, per-channel)
quantisation calibrated on 120 training images of that dataset; `--profile` lists the 8 costliest nodes
(share of kernel time, one thread). Random input of the reference sensor's auto layout (416 x 320).
"""

from __future__ import annotations

import argparse
import collections
import json
import random
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort


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


def quantised(path: Path, data_root: Path, h: int, w: int, out_dir: Path) -> Path:
    import cv2
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    files = sorted(data_root.glob("train/*/left/*.png")) + sorted(data_root.glob("train/*/right/*.png"))
    if not files:
        raise SystemExit(f"{data_root}/train/*/{{left,right}}/*.png: no calibration images")
    random.seed(0)
    files = random.sample(files, min(120, len(files)))

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter(files)

        def get_next(self):
            f = next(self.it, None)
            if f is None:
                return None
            img = cv2.resize(cv2.imread(str(f))[:, :, ::-1], (w, h), interpolation=cv2.INTER_LINEAR)
            return {"image": (img.astype(np.float32) / 255).transpose(2, 0, 1)[None].copy()}

    pre, out = out_dir / f"{path.stem}_pre.onnx", out_dir / f"{path.stem}_int8.onnx"
    quant_pre_process(str(path), str(pre), skip_symbolic_shape=True)  # dynamic input: no symbolic shapes
    quantize_static(str(pre), str(out), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                    activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("models", type=Path, nargs="+", help="marknet.onnx files")
    p.add_argument("--height", type=int, default=320)
    p.add_argument("--width", type=int, default=416)
    p.add_argument("--runs", type=int, default=200)
    p.add_argument("--int8", type=Path, default=None, metavar="DATA_ROOT", help="also time a static int8 build")
    p.add_argument("--profile", action="store_true", help="list the costliest nodes")
    args = p.parse_args(argv)
    rng = np.random.default_rng(0)
    x1 = rng.random((1, 3, args.height, args.width), dtype=np.float32)
    print(f"onnxruntime {ort.__version__}, input {args.width} x {args.height}, median of {args.runs} runs, ms per image")
    print("| model | fp32, 1 thread | fp32, 2 threads | batch 2 | batch 4 | int8, 1 thread |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.models:
            row = [median_ms(session(path, 1), x1, args.runs), median_ms(session(path, 2), x1, args.runs)]
            for n in (2, 4):
                xn = np.repeat(x1, n, axis=0)
                row.append(median_ms(session(path, 1), xn, args.runs // 2) / n)
            int8 = "-"
            if args.int8 is not None:
                q = quantised(path, args.int8, args.height, args.width, Path(tmp))
                int8 = f"{median_ms(session(q, 1), x1, args.runs):.2f}"
            print(f"| {path} | " + " | ".join(f"{v:.2f}" for v in row) + f" | {int8} |")
        if args.profile:
            for path in args.models:
                print(f"\ncostliest nodes of {path} (one thread):")
                for op, shape, share in costliest_nodes(path, x1, args.runs // 2, Path(tmp)):
                    print(f"  {share:5.1f} %  {op:14s} {shape}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
