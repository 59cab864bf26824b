#!/usr/bin/env bash
# Tables II (S = 13 / 26 / 52, m = 5) and III (m = 1..5, S = 52) of the paper on our data: short runs
# of EQUAL budget (the same number of optimiser steps and batch size for every configuration), each
# evaluated Marknet-only (c > 0.2) on the same random subset of the test split. Images held in memory:
# MAX_GB (1.0 GB of the training split, random subset).
#
#   train/scripts/ablation.sh DATA_DIR OUT_DIR [STEPS] [TEST_IMAGES]
#
# STEM (default s2) and FIT (default stretch) pin Tables II and III of docs/training.md, which were run with the
# first model's stride-2 stem and the whole-image stretch; STEM=s4 FIT=auto gives the shipped design.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
DATA="$1"
OUT="$2"
STEPS="${3:-600}"
NTEST="${4:-200}"
PY="$ROOT/.venv/bin/python"
mkdir -p "$OUT"
cd "$ROOT/train"
for cfg in "52 5" "26 5" "13 5" "52 1" "52 2" "52 3" "52 4"; do
  set -- $cfg
  name="S$1_m$2"
  if [ ! -f "$OUT/$name.json" ]; then
    "$PY" -m gelstereo_train.train_marknet --data "$DATA" --out "$OUT/$name.pt" --grid "$1" --candidates "$2" \
      --stem "${STEM:-s2}" --steps "$STEPS" --max-gb "${MAX_GB:-1.0}" --log-every-s 120 > "$OUT/$name.train.log" 2>&1
    "$PY" -m gelstereo_train.evaluate --data "$DATA" --split test --max-images "$NTEST" \
      --fit "${FIT:-stretch}" --marknet "$OUT/$name.pt" --out "$OUT/$name.json" > "$OUT/$name.eval.md" 2>&1
  fi
done
"$PY" scripts/ablation_tables.py "$OUT" "$STEPS" "$NTEST" | tee "$OUT/tables.md"
