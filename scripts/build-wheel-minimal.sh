#!/usr/bin/env bash
# The wheel of the Python package `gelstereo` against a minimal OpenCV linked statically, instead of
# Debian's shared OpenCV 4.6 (which brings GDAL, FFmpeg and ICU into the wheel):
#  1. OpenCV from the source inside the PyPI sdist of opencv-python-headless (pinned by version and
#     sha256), built once into the per-user cache: static libraries, only the modules gelstereo
#     uses (core, imgproc, imgcodecs, videoio, calib3d, features2d, flann), JPEG / PNG / zlib built
#     from OpenCV's bundled sources, video from V4L2 cameras only: no FFmpeg, so no MPEG-4 file
#     (the GelSight Mini's recordings) can be read by this wheel;
#  2. the extension built by maturin against it (the `opencv` crate told where it is through its
#     environment variables, in its own CARGO_TARGET_DIR so the default build is left alone), then
#     `auditwheel repair` as scripts/setup.sh does; the wheel goes to target/wheels-minimal.
# `--check` then runs scripts/check-wheel.sh's checks of the wheel on that wheel (size, tags, models,
# install into a fresh environment, the sample tracked from Python).
# Needs cmake, ninja and a C++ compiler besides what scripts/setup.sh installs.
set -euo pipefail

CHECK=0
for arg in "$@"; do
  case "$arg" in
    --check) CHECK=1 ;;
    *) echo "usage: scripts/build-wheel-minimal.sh [--check]" >&2; exit 2 ;;
  esac
done

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
CACHE="${GELSTEREO_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/gelstereo}"
OPENCV_SDIST_VERSION="4.10.0.84"
OPENCV_VERSION="${OPENCV_SDIST_VERSION%.*}"
OPENCV_SDIST="opencv-python-headless-${OPENCV_SDIST_VERSION}.tar.gz"
OPENCV_SDIST_URL="https://files.pythonhosted.org/packages/2f/7e/d20f68a5f1487adf19d74378d349932a386b1ece3be9be9915e5986db468/$OPENCV_SDIST"
OPENCV_SDIST_SHA256="f2017c6101d7c2ef8d7bc3b414c37ff7f54d64413a1847d89970b6b7069b4e1a"
PREFIX="$CACHE/opencv-min-$OPENCV_VERSION"
JOBS="${JOBS:-2}"
WHEELS="$ROOT/target/wheels-minimal"
export CARGO_TARGET_DIR="${MINIMAL_TARGET_DIR:-$ROOT/target/minimal-opencv}"

say() { printf '[build-wheel-minimal] %s\n' "$*"; }
for tool in cmake ninja c++; do
  command -v "$tool" >/dev/null || { echo "$tool is missing (apt-get install cmake ninja-build g++)" >&2; exit 1; }
done
venv="$(ls -d "$CACHE"/venv-* 2>/dev/null | head -n 1)"
[ -x "$venv/bin/maturin" ] && [ -x "$venv/bin/auditwheel" ] \
  || { echo "no maturin / auditwheel under $CACHE/venv-*: run scripts/setup.sh first" >&2; exit 1; }

# --- 1. the minimal static OpenCV -----------------------------------------------------------------
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
build_opencv() {
  local src
  if [ ! -f "$CACHE/$OPENCV_SDIST" ] || ! echo "$OPENCV_SDIST_SHA256  $CACHE/$OPENCV_SDIST" | sha256sum -c --status; then
    say "downloading $OPENCV_SDIST"
    curl -sSfL -o "$CACHE/$OPENCV_SDIST.part" "$OPENCV_SDIST_URL"
    mv "$CACHE/$OPENCV_SDIST.part" "$CACHE/$OPENCV_SDIST"
  fi
  echo "$OPENCV_SDIST_SHA256  $CACHE/$OPENCV_SDIST" | sha256sum -c --status \
    || { echo "sha256 mismatch for $CACHE/$OPENCV_SDIST" >&2; exit 1; }
  tar -xzf "$CACHE/$OPENCV_SDIST" -C "$work" --wildcards "opencv-python-headless-$OPENCV_SDIST_VERSION/opencv/*"
  src="$work/opencv-python-headless-$OPENCV_SDIST_VERSION/opencv"
  say "building OpenCV $OPENCV_VERSION (static, minimal) into $PREFIX with $JOBS jobs"
  rm -rf "$PREFIX"
  cmake -S "$src" -B "$work/build" -G Ninja -DCMAKE_BUILD_TYPE=Release -DCMAKE_INSTALL_PREFIX="$PREFIX" \
    -DBUILD_SHARED_LIBS=OFF -DCMAKE_POSITION_INDEPENDENT_CODE=ON -DENABLE_PIC=ON \
    -DBUILD_LIST=core,imgproc,imgcodecs,videoio,calib3d,features2d,flann \
    -DBUILD_PNG=ON -DBUILD_JPEG=ON -DBUILD_ZLIB=ON -DWITH_PNG=ON -DWITH_JPEG=ON \
    -DWITH_TIFF=OFF -DWITH_WEBP=OFF -DWITH_OPENJPEG=OFF -DWITH_JASPER=OFF -DWITH_OPENEXR=OFF \
    -DWITH_GDAL=OFF -DWITH_GDCM=OFF -DWITH_AVIF=OFF -DWITH_SPNG=OFF -DWITH_IMGCODEC_GIF=OFF \
    -DWITH_FFMPEG=OFF -DWITH_GSTREAMER=OFF -DWITH_V4L=ON -DWITH_1394=OFF -DWITH_MSMF=OFF \
    -DWITH_OBSENSOR=OFF -DWITH_GPHOTO2=OFF -DWITH_ARAVIS=OFF -DWITH_XIMEA=OFF -DWITH_OPENNI2=OFF \
    -DWITH_IPP=OFF -DWITH_TBB=OFF -DWITH_OPENMP=OFF -DWITH_OPENCL=OFF -DWITH_CUDA=OFF -DWITH_VA=OFF \
    -DWITH_VA_INTEL=OFF -DWITH_ITT=OFF -DBUILD_ITT=OFF -DWITH_LAPACK=OFF -DWITH_EIGEN=OFF \
    -DWITH_PROTOBUF=OFF -DWITH_QUIRC=OFF -DWITH_FLATBUFFERS=OFF -DWITH_ADE=OFF -DWITH_GTK=OFF \
    -DWITH_QT=OFF -DWITH_VTK=OFF -DWITH_OPENGL=OFF -DWITH_CAROTENE=OFF -DWITH_KLEIDICV=OFF \
    -DWITH_VULKAN=OFF -DWITH_WAYLAND=OFF \
    -DBUILD_TESTS=OFF -DBUILD_PERF_TESTS=OFF -DBUILD_EXAMPLES=OFF -DBUILD_opencv_apps=OFF \
    -DBUILD_DOCS=OFF -DBUILD_JAVA=OFF -DBUILD_opencv_python2=OFF -DBUILD_opencv_python3=OFF \
    -DBUILD_opencv_js=OFF -DINSTALL_C_EXAMPLES=OFF -DINSTALL_PYTHON_EXAMPLES=OFF -DOPENCV_GENERATE_PKGCONFIG=ON \
    >"$work/cmake.log" 2>&1 \
    || { tail -n 40 "$work/cmake.log" >&2; exit 1; }
  ninja -C "$work/build" -j "$JOBS" install >"$work/ninja.log" 2>&1 || { tail -n 40 "$work/ninja.log" >&2; exit 1; }
  touch "$PREFIX/.complete"
}
if [ -f "$PREFIX/.complete" ]; then
  say "OpenCV $OPENCV_VERSION present ($PREFIX)"
else
  build_opencv
fi

# --- 2. the wheel -------------------------------------------------------------------------------
# Static archives go from the most dependent module to the least, then the codecs they call; the
# crate drops one "lib" from each name, so OpenCV's own liblibjpeg-turbo.a is named with both.
export OPENCV_DISABLE_PROBES="pkg_config,cmake,vcpkg_cmake,vcpkg"
export OPENCV_INCLUDE_PATHS="$PREFIX/include/opencv4"
export OPENCV_LINK_PATHS="$PREFIX/lib,$PREFIX/lib/opencv4/3rdparty"
export OPENCV_LINK_LIBS="static=opencv_calib3d,static=opencv_features2d,static=opencv_flann,static=opencv_videoio,static=opencv_imgcodecs,static=opencv_imgproc,static=opencv_core,static=liblibjpeg-turbo,static=liblibpng,static=zlib"
say "building the wheel (maturin, CARGO_TARGET_DIR=$CARGO_TARGET_DIR)"
rm -rf "$WHEELS"
mkdir -p "$WHEELS/linux"
log="$WHEELS/maturin.log"
"$venv/bin/maturin" build --release --locked --compatibility linux -m "$ROOT/crates/gelstereo-py/Cargo.toml" \
  -i "$ROOT/.venv/bin/python" --out "$WHEELS/linux" >"$log" 2>&1 || { tail -n 40 "$log" >&2; exit 1; }
PATH="$venv/bin:$PATH" "$venv/bin/auditwheel" repair --wheel-dir "$WHEELS" "$WHEELS"/linux/gelstereo-*.whl \
  >>"$log" 2>&1 || { tail -n 20 "$log" >&2; exit 1; }
rm -rf "$WHEELS/linux"
wheel="$(ls "$WHEELS"/gelstereo-*.whl)"
say "built $wheel ($(du -m "$wheel" | cut -f1) MB)"

if ((CHECK)); then
  GELSTEREO_WHEEL="$wheel" MAX_WHEEL_MB=60 bash "$ROOT/scripts/check-wheel.sh"
fi
