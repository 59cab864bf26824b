"""The Python package gelstereo: the Rust extension module `gelstereo._gelstereo`, with the package's
own models and the ONNX Runtime of the `onnxruntime` package it depends on.

Before the extension starts ONNX Runtime, `ORT_DYLIB_PATH` is pointed at the library inside the
installed `onnxruntime` package (unless it is set already: an explicit choice wins). The models
shipped in this package's `models/` folder are the default of `Pipeline` and `detect`.
"""

import importlib.util
import os
from pathlib import Path


def _onnxruntime_library() -> None:
    """Points ONNX Runtime's loader at the `onnxruntime` package's library, without importing it."""
    if os.environ.get("ORT_DYLIB_PATH"):
        return
    spec = importlib.util.find_spec("onnxruntime")
    if spec is None or not spec.submodule_search_locations:
        return
    for folder in spec.submodule_search_locations:
        # The versioned file (libonnxruntime.so.1.31.1): the package ships no unversioned link.
        found = sorted(Path(folder, "capi").glob("libonnxruntime.so*"))
        if found:
            os.environ["ORT_DYLIB_PATH"] = str(found[-1])
            return


_onnxruntime_library()

from . import _gelstereo  # noqa: E402
from ._gelstereo import *  # noqa: E402,F401,F403
from ._gelstereo import __version__  # noqa: E402,F401

__doc__ = _gelstereo.__doc__
_gelstereo._use_package_models(str(Path(__file__).resolve().parent / "models"))
