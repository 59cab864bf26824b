"""The installed package stands alone: its own copy of the shipped models, and ONNX Runtime from the
`onnxruntime` package it depends on unless `ORT_DYLIB_PATH` says otherwise (scripts/check-wheel.sh
checks the same from a fresh environment)."""

import os
import subprocess
import sys
from pathlib import Path

import gelstereo

ROOT = Path(__file__).resolve().parents[3]
MINI_PIPELINE = "import os, gelstereo; p = gelstereo.Pipeline(grid='8x10', pitch_mm=1.6); print(p.method)"


def run_fresh(code, cwd, **env):
    """`code` in a fresh interpreter in `cwd`, with neither the project's home nor an ONNX Runtime
    library named unless `env` names them."""
    clean = {k: v for k, v in os.environ.items() if k not in ("ORT_DYLIB_PATH", "GELSTEREO_HOME")}
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env={**clean, **env},
                          capture_output=True, text=True)


def test_the_installed_package_carries_the_shipped_models():
    package = Path(gelstereo.__file__).resolve().parent
    assert package.parent.name == "site-packages", package
    for name in ("marknet.onnx", "mre.onnx", "yolo.onnx"):
        assert (package / "models" / name).read_bytes() == (ROOT / "data" / "models" / name).read_bytes()


def test_onnx_runtime_comes_from_the_onnxruntime_package(tmp_path):
    done = run_fresh(MINI_PIPELINE + "; print(os.environ['ORT_DYLIB_PATH'])", tmp_path)
    assert done.returncode == 0, done.stderr
    method, library = done.stdout.split()
    assert method == "marknet-mre"
    assert "/onnxruntime/capi/libonnxruntime.so" in library and Path(library).is_file()


def test_an_explicit_onnx_runtime_library_wins(tmp_path):
    missing = tmp_path / "libonnxruntime.so"
    done = run_fresh(MINI_PIPELINE, tmp_path, ORT_DYLIB_PATH=str(missing))
    assert done.returncode != 0
    assert "GelstereoError" in done.stderr and f"ORT_DYLIB_PATH={missing} does not exist" in done.stderr
