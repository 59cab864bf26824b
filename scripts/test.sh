#!/usr/bin/env bash
# README command 2 and CI: set up, then every check CI runs. Fails on the first problem.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

bash scripts/setup.sh --with-train --with-rerun --with-ros

step() { printf '\n=== %s\n' "$*"; }
step "cargo fmt --check"
cargo fmt --all -- --check
step "cargo clippy (warnings are errors)"
cargo clippy --workspace --all-targets --locked -- -D warnings
step "cargo test"
cargo test --workspace --locked
step "examples: the Rust robot loop on the sample recording"
cargo run -q --locked -p robot-loop -- data/sample/press-slide | tail -n 3
step "pytest train/"
(cd train && "$ROOT/.venv/bin/python" -m pytest -q)
step "pytest crates/gelstereo-py (the Python package)"
"$ROOT/.venv/bin/python" -m pytest -q crates/gelstereo-py/tests
step "examples/python on the sample recording"
examples_out="$(mktemp -d)"
trap 'rm -rf "$examples_out"' EXIT
"$ROOT/.venv/bin/python" examples/python/track_and_plot.py data/sample/press-slide --out "$examples_out/depth-slip.png"
test -s "$examples_out/depth-slip.png"
"$ROOT/.venv/bin/python" -m gelstereo.view data/sample/press-slide --rrd "$examples_out/sample.rrd"
test -s "$examples_out/sample.rrd"
step "examples/python/batch_dask.py: recordings on a local Dask cluster, tables as gelstereo track's"
# The CLI binary `cargo test` built above for crates/gelstereo-cli/tests.
GELSTEREO="${CARGO_TARGET_DIR:-target}/debug/gelstereo" \
  "$ROOT/.venv/bin/python" -m pytest -q examples/python/test_batch_dask.py
step "examples/ros2: the ROS 2 node on the sample recording, against gelstereo track"
"$ROOT/.venv-ros/bin/python" -m pytest -q -W ignore::DeprecationWarning examples/ros2
step "the inference-only install: the wheel in a fresh virtual environment, cargo install, both outside the checkout"
bash scripts/check-wheel.sh
