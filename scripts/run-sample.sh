#!/usr/bin/env bash
# README command 1: set up, build, and run the main job on the bundled data. Results go to out/sample/.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
bash scripts/setup.sh
cargo build --release --locked -p gelstereo-cli
# Where cargo put it (CARGO_TARGET_DIR when set).
BIN="${CARGO_TARGET_DIR:-$ROOT/target}/release/gelstereo"
OUT="$ROOT/out/sample"
mkdir -p "$OUT"
"$BIN" --version
"$BIN" doctor
# Tracking, contact geometry and slip on the sample press-then-slide recording (calibration: its calib.yaml).
"$BIN" track --out "$OUT/track" "$ROOT/data/sample/press-slide"
echo "results in $OUT/track: markers.csv, frames.csv, ply/, overlays/, plots/"
