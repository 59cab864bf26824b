#!/usr/bin/env bash
# Makes data/sample/press-slide: the bundled sample stereo recording of the main job
# (scripts/run-sample.sh). A simulated fingertip pressed, slid (partial then gross slip) and lifted,
# 40 stereo frames of the reference sensor (640x480, reference look), written by `gelstereo simulate`
# and re-encoded as JPEG (quality 85) to keep the checkout small; markers.csv / frames.csv are the
# simulator's exact ground truth. Needs a release build and the Python env of scripts/setup.sh.
#
#   data/sample/make-sample.sh          (from the repository root)
set -euo pipefail
root="$(cd "$(dirname "$0")/../.." && pwd)"
bin="$root/target/release/gelstereo"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"$bin" simulate --out "$tmp/sim" --experiments 1 --frames-per-experiment 40 --seed 3 --randomization off --quiet
src="$(ls -d "$tmp"/sim/*/exp_0000)"
dst="$root/data/sample/press-slide"
rm -rf "$dst"
mkdir -p "$dst/left" "$dst/right"
cp "$src"/calib.yaml "$src"/left.cameramodel "$src"/right.cameramodel "$src"/meta.json "$src"/markers.csv "$src"/frames.csv "$dst/"
"$root/.venv/bin/python" - "$src" "$dst" <<'PY'
import glob, os, sys
import cv2
src, dst = sys.argv[1], sys.argv[2]
for side in ("left", "right"):
    for p in sorted(glob.glob(os.path.join(src, side, "*.png"))):
        name = os.path.splitext(os.path.basename(p))[0] + ".jpg"
        cv2.imwrite(os.path.join(dst, side, name), cv2.imread(p), [cv2.IMWRITE_JPEG_QUALITY, 85])
PY
du -sh "$dst"
