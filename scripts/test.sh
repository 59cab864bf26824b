#!/usr/bin/env bash
# README command 2 and CI: set up, then every check CI runs. Fails on the first problem.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

bash scripts/setup.sh

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
