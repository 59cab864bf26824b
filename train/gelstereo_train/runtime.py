"""ONNX Runtime sessions for the trainer's checks and evaluations (CPU provider, a fixed thread count)."""

from __future__ import annotations

from pathlib import Path


def ort_session(path: Path | str, threads: int = 2):
    """An onnxruntime InferenceSession on the CPU with `threads` intra-op threads and one inter-op thread
    (the graph runs sequentially)."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
