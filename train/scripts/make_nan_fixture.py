"""Write ``marknet_nan.onnx``: ``marknet_tiny.onnx`` with every float weight set to NaN (a broken
model: the Rust tests check that its NaN output is an error and that ``gelstereo doctor`` reports it).

    cd train && ../.venv/bin/python scripts/make_nan_fixture.py [--dir ../data/fixtures/onnx]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dir", type=Path, default=Path(__file__).resolve().parents[2] / "data/fixtures/onnx")
    args = parser.parse_args(argv)
    model = onnx.load(args.dir / "marknet_tiny.onnx")
    for init in model.graph.initializer:
        weights = numpy_helper.to_array(init)
        if weights.dtype == np.float32:
            init.CopyFrom(numpy_helper.from_array(np.full_like(weights, np.nan), init.name))
    onnx.save(model, args.dir / "marknet_nan.onnx")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
