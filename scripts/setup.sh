#!/usr/bin/env bash
# One idempotent setup for a fresh machine, used by both README commands and by CI.
#  1. Debian packages for the `opencv` crate (OpenCV 4.6 from libopencv-dev, clang for its bindings)
#     and for the figures (`plotters` renders text through fontconfig / freetype with DejaVu fonts).
#  2. ONNX Runtime: the shared library shipped inside the PyPI `onnxruntime` wheel (ort's own binary
#     download cannot reach its CDN here), pinned by version and sha256, unpacked into .deps/onnxruntime/lib.
#  3. The Python environment for train/ (.venv, pinned train/requirements.txt), kept in a per-user cache
#     keyed by the requirements' hash so a fresh clone on the same machine does not reinstall PyTorch.
# Re-running it does only what is missing.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
CACHE="${GELSTEREO_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/gelstereo}"
ORT_VERSION="1.31.1"
ORT_WHEEL="onnxruntime-${ORT_VERSION}-cp311-cp311-manylinux_2_28_x86_64.whl"
ORT_SHA256="5752bd508126ae7c49894d3b9d2e83f0c3d487319246d04c444b393308d7ad7f"
ORT_DIR="$ROOT/.deps/onnxruntime/lib"
PYTHON="${PYTHON:-python3}"

say() { printf '[setup] %s\n' "$*"; }
mkdir -p "$CACHE"

# --- 1. Debian packages ------------------------------------------------------------------------
need_apt=()
for pkg in libopencv-dev clang libclang-dev libfontconfig1-dev libfreetype-dev fonts-dejavu-core; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || need_apt+=("$pkg")
done
if ((${#need_apt[@]})); then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  say "installing Debian packages: ${need_apt[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_apt[@]}" >/dev/null
else
  say "Debian packages present (libopencv-dev $(dpkg-query -W -f='${Version}' libopencv-dev))"
fi

# --- 2. ONNX Runtime from the PyPI wheel -------------------------------------------------------
if [ ! -e "$ORT_DIR/libonnxruntime.so.${ORT_VERSION}" ]; then
  wheel="$CACHE/$ORT_WHEEL"
  if [ ! -f "$wheel" ] || ! echo "$ORT_SHA256  $wheel" | sha256sum -c --status; then
    say "downloading $ORT_WHEEL"
    tmp="$(mktemp -d)"
    "$PYTHON" -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.11 \
      --platform manylinux_2_28_x86_64 -d "$tmp" "onnxruntime==${ORT_VERSION}"
    mv "$tmp/$ORT_WHEEL" "$wheel.part" && mv "$wheel.part" "$wheel"
    rm -rf "$tmp"
  fi
  echo "$ORT_SHA256  $wheel" | sha256sum -c --status || { echo "sha256 mismatch for $wheel" >&2; exit 1; }
  mkdir -p "$ORT_DIR"
  "$PYTHON" - "$wheel" "$ORT_DIR" "$ORT_VERSION" <<'PY'
import sys, zipfile, os
wheel, out, ver = sys.argv[1:4]
with zipfile.ZipFile(wheel) as z:
    for name in (f"onnxruntime/capi/libonnxruntime.so.{ver}", "onnxruntime/capi/libonnxruntime_providers_shared.so"):
        dst = os.path.join(out, os.path.basename(name))
        with z.open(name) as src, open(dst + ".part", "wb") as f:
            f.write(src.read())
        os.replace(dst + ".part", dst)
PY
  ln -sf "libonnxruntime.so.${ORT_VERSION}" "$ORT_DIR/libonnxruntime.so.1"
  ln -sf "libonnxruntime.so.1" "$ORT_DIR/libonnxruntime.so"
  say "ONNX Runtime ${ORT_VERSION} unpacked into $ORT_DIR"
else
  say "ONNX Runtime ${ORT_VERSION} present in $ORT_DIR"
fi

# --- 3. Python environment for train/ ----------------------------------------------------------
req="$ROOT/train/requirements.txt"
req_hash="$(sha256sum "$req" | cut -c1-16)"
venv="$CACHE/venv-$req_hash"
if [ ! -x "$venv/bin/python" ] || [ ! -f "$venv/.complete" ]; then
  say "creating Python environment $venv (PyTorch is a large download, ~1-2 min)"
  rm -rf "$venv"
  "$PYTHON" -m venv "$venv"
  "$venv/bin/python" -m pip install --quiet --upgrade pip
  "$venv/bin/python" -m pip install --quiet -r "$req"
  touch "$venv/.complete"
else
  say "Python environment present ($venv)"
fi
ln -sfn "$venv" "$ROOT/.venv"
say "done"
