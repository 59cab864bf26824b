#!/usr/bin/env bash
# The inference-only install, checked as a user meets it (scripts/test.sh runs it, so CI does):
#  1. the wheel scripts/setup.sh builds (target/wheels): abi3, tagged manylinux, at most 120 MB, its
#     models inside, no path of the build tree in its extension module;
#  2. `pip install` of that wheel into a fresh virtual environment (nothing but pip) pulls no
#     PyTorch; from a folder outside the checkout, `gelstereo.Pipeline` tracks the bundled sample
#     recording with the package's own models and the `onnxruntime` package's library, as
#     `gelstereo track` does (tests/data/press-slide-frames.csv);
#  3. `cargo install --path crates/gelstereo-cli`: the binary, run outside the checkout with an empty
#     project home (GELSTEREO_HOME) and ONNX Runtime from that pip package (ORT_DYLIB_PATH), passes
#     `gelstereo doctor` and tracks the sample as the snapshot says; pointed at a missing ONNX
#     Runtime, doctor and track say what is missing and how to fix it.
# The release build of the binary reuses CARGO_TARGET_DIR, as CI's does: only what changed is rebuilt.
# GELSTEREO_WHEEL=PATH checks that wheel instead (steps 1 and 2; scripts/build-wheel-minimal.sh uses
# it), MAX_WHEEL_MB=N holds it to another bound.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
# Debian's OpenCV 4.6 links GDAL, FFmpeg, ICU and their own libraries, which `auditwheel repair`
# vendors: about 105 MB. A smaller wheel needs an OpenCV built with only the modules and codecs
# gelstereo uses; this bound catches growth beyond that.
MAX_WHEEL_MB="${MAX_WHEEL_MB:-120}"

step() { printf '\n=== check-wheel: %s\n' "$*"; }
fail() { echo "check-wheel: $*" >&2; exit 1; }

work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

if [ -n "${GELSTEREO_WHEEL:-}" ]; then
  step "the wheel $GELSTEREO_WHEEL"
  wheel="$(cd "$(dirname "$GELSTEREO_WHEEL")" && pwd)/$(basename "$GELSTEREO_WHEEL")"
  [ -f "$wheel" ] || fail "no wheel $GELSTEREO_WHEEL"
else
  bash scripts/setup.sh >/dev/null
  step "the wheel scripts/setup.sh built"
  shopt -s nullglob
  wheels=(target/wheels/gelstereo-*.whl)
  ((${#wheels[@]} == 1)) || fail "expected one wheel in target/wheels, found ${#wheels[@]}"
  wheel="$ROOT/${wheels[0]}"
fi
name="$(basename "$wheel")"
size_mb=$(( ($(stat -c %s "$wheel") + 1048575) / 1048576 ))
echo "$name: $size_mb MB"
[[ "$name" == *-cp310-abi3-*manylinux_* ]] || fail "$name is not an abi3 manylinux wheel"
((size_mb <= MAX_WHEEL_MB)) || fail "$name is $size_mb MB, more than $MAX_WHEEL_MB MB"
"$ROOT/.venv/bin/python" - "$wheel" "$work/unpacked" <<'PY'
import sys, zipfile
with zipfile.ZipFile(sys.argv[1]) as z:
    names = z.namelist()
    for model in ("marknet.onnx", "mre.onnx", "yolo.onnx"):
        assert f"gelstereo/models/{model}" in names, f"the wheel lacks gelstereo/models/{model}"
    z.extractall(sys.argv[2])
PY
extension="$(echo "$work"/unpacked/gelstereo/_gelstereo*.so)"
[ -f "$extension" ] || fail "no extension module in $name"
for tree in "$ROOT" "$(cd "${CARGO_TARGET_DIR:-$ROOT/target}" && pwd -P)"; do
  if strings "$extension" | grep -F -- "$tree"; then
    fail "the extension module holds paths of the build tree ($tree), above"
  fi
done
echo "models inside; no path of $ROOT or the target folder in the extension module"

step "pip install into a fresh virtual environment"
python3 -m venv "$work/venv"
"$work/venv/bin/python" -m pip install --quiet --disable-pip-version-check "$wheel"
"$work/venv/bin/python" -m pip list --format=freeze --disable-pip-version-check >"$work/installed.txt"
tr '\n' ' ' <"$work/installed.txt"; echo
if grep -iE '^(torch|nvidia-)' "$work/installed.txt"; then fail "the wheel pulled in PyTorch"; fi

step "gelstereo.Pipeline on the sample recording, from a folder outside the checkout"
# The fresh environment has no image decoder: the checkout's environment decodes the frames.
"$ROOT/.venv/bin/python" - "$ROOT/data/sample/press-slide" "$work/frames.npz" <<'PY'
import sys
from pathlib import Path
import cv2
import numpy as np
sample = Path(sys.argv[1])
names = sorted(p.name for p in (sample / "left").glob("*.jpg"))
read = lambda side: np.stack([cv2.imread(str(sample / side / n), cv2.IMREAD_COLOR) for n in names])
np.savez(sys.argv[2], left=read("left"), right=read("right"))
PY
mkdir -p "$work/outside"
cp data/sample/press-slide/calib.yaml "$work/outside/calib.yaml"
cp tests/data/press-slide-frames.csv "$work/outside/expected.csv"
(cd "$work/outside" && env -u ORT_DYLIB_PATH -u GELSTEREO_HOME SAMPLE="$ROOT/data/sample/press-slide" "$work/venv/bin/python" - <<'PY'
import csv, math, os
from pathlib import Path
import numpy as np
import gelstereo

package = Path(gelstereo.__file__).parent
assert "site-packages" in str(package), package
library = os.environ.get("ORT_DYLIB_PATH", "")
assert "onnxruntime/capi/libonnxruntime.so" in library, library
frames = np.load("../frames.npz")
pipeline = gelstereo.Pipeline(calibration="calib.yaml")
assert pipeline.method == "marknet-mre", pipeline.method
expected = list(csv.DictReader(open("expected.csv")))
assert len(expected) == len(frames["left"]) == 40
pressed = 0
for left, right, want in zip(frames["left"], frames["right"], expected):
    out = pipeline.process(left, right)
    k = out.frame
    found = int(np.sum(out.markers["status"] == "tracked"))
    assert found >= 400, f"frame {k}: {found} markers tracked"
    assert out.slip == want["slip"], (k, out.slip, want["slip"])
    for got, column in ((out.contact.area_mm2, "contact_area_mm2"), (out.contact.max_depth_mm, "max_depth_mm")):
        assert math.isclose(got, float(want[column]), abs_tol=2e-6), (k, column, got, want[column])
    if out.contact.in_contact:
        assert math.isfinite(out.contact.area_mm2) and out.contact.area_mm2 > 0, (k, out.contact.area_mm2)
        pressed += 1
assert pressed >= 10, f"only {pressed} frames in contact"
# gelstereo.open reads the bundled recording frame by frame with the wheel's own decoder: the
# same pixels as OpenCV's in the checkout, and the same tracking.
opened = gelstereo.open(os.environ["SAMPLE"])
assert opened.is_stereo and opened.frames == 40, (opened.is_stereo, opened.frames)
again = gelstereo.Pipeline(calibration="calib.yaml")
for f, left, right, want in zip(opened, frames["left"], frames["right"], expected):
    assert f.error is None and np.array_equal(f.left, left) and np.array_equal(f.right, right), f.index
    assert again.process(f.left, f.right, f.timestamp).slip == want["slip"], f.index
print(f"{len(expected)} frames as gelstereo track tracks them ({pressed} in contact, area finite); "
      f"models from {package / 'models'}, ONNX Runtime {library}")
PY
)
ort_library="$(echo "$work"/venv/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so.*)"
if [ -n "${GELSTEREO_WHEEL:-}" ]; then
  echo "check-wheel: the wheel's checks passed"
  exit 0
fi

step "cargo install --path crates/gelstereo-cli, run outside the checkout"
cargo install --quiet --locked --path crates/gelstereo-cli --root "$work/cargo"
mkdir -p "$work/home" "$work/cache"
installed() {
  (cd "$work/outside" && GELSTEREO_HOME="$work/home" XDG_CACHE_HOME="$work/cache" "$work/cargo/bin/gelstereo" "$@")
}
ORT_DYLIB_PATH="$ort_library" installed doctor
ORT_DYLIB_PATH="$ort_library" installed track --quiet --no-ply --overlay-every 0 --out "$work/track" \
  "$ROOT/data/sample/press-slide"
# The tables `gelstereo track` gives in the checkout (tests/track_outputs.rs holds it to them).
want="$(awk '$2 == "marknet-mre" && NF == 2 { print $1 }' tests/data/press-slide-markers.sha256)"
[ "$(sha256sum <"$work/track/markers.csv" | cut -d' ' -f1)" = "$want" ] \
  || fail "the installed binary's markers.csv differs from tests/data/press-slide-markers.sha256"
columns="$(head -n 1 tests/data/press-slide-frames.csv | tr ',' '\n' | wc -l)"
cut -d, -f"1-$columns" "$work/track/frames.csv" | cmp - tests/data/press-slide-frames.csv \
  || fail "the installed binary's frames.csv differs from tests/data/press-slide-frames.csv"
ls "$work"/cache/gelstereo/models-*/marknet.onnx >/dev/null || fail "the embedded models were not unpacked"
echo "doctor passes; track gives the sample's snapshot tables with the embedded models"
if ORT_DYLIB_PATH="$work/missing.so" installed doctor >"$work/doctor.txt" 2>&1; then
  fail "doctor passed without ONNX Runtime"
fi
grep -q "MISSING.*ONNX Runtime" "$work/doctor.txt" && grep -q "pip install onnxruntime" "$work/doctor.txt" \
  || { cat "$work/doctor.txt"; fail "doctor does not explain the missing ONNX Runtime"; }
if ORT_DYLIB_PATH="$work/missing.so" installed track --quiet --out "$work/no-ort" \
  "$ROOT/data/sample/press-slide" 2>"$work/track-err.txt"; then
  fail "track ran without ONNX Runtime"
fi
grep -q "ORT_DYLIB_PATH" "$work/track-err.txt" || { cat "$work/track-err.txt"; fail "track does not say what is missing"; }
echo "without ONNX Runtime: doctor and track say what is missing ($(tail -n 1 "$work/track-err.txt"))"
echo "check-wheel: all checks passed"
