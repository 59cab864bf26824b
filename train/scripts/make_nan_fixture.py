"""Write broken models for the Rust tests, which check that a non-finite output is an error naming
the model and that ``gelstereo doctor`` reports it:

- ``marknet_nan.onnx``: ``marknet_tiny.onnx`` with every float weight NaN;
- ``marknet_inf.onnx``: ``marknet_tiny.onnx`` with every float weight +inf (its outputs are +inf,
  not NaN);
- ``mre_nan.onnx``: ``mre_tiny.onnx`` with every float weight NaN.

    cd train && ../.venv/bin/python scripts/make_nan_fixture.py [--dir ../data/fixtures/onnx]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper


def broken(source: Path, target: Path, value: float) -> None:
    """Saves ``source`` with every float32 initializer set to ``value`` as ``target``."""
    model = onnx.load(source)
    for init in model.graph.initializer:
        weights = numpy_helper.to_array(init)
        if weights.dtype == np.float32:
            init.CopyFrom(numpy_helper.from_array(np.full_like(weights, value), init.name))
    onnx.save(model, target)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dir", type=Path, default=Path(__file__).resolve().parents[2] / "data/fixtures/onnx")
    args = parser.parse_args(argv)
    broken(args.dir / "marknet_tiny.onnx", args.dir / "marknet_nan.onnx", np.nan)
    broken(args.dir / "marknet_tiny.onnx", args.dir / "marknet_inf.onnx", np.inf)
    broken(args.dir / "mre_tiny.onnx", args.dir / "mre_nan.onnx", np.nan)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
