#!/usr/bin/env bash
# Retrain the shipped models from scratch: simulate -> train Marknet -> MRE -> export -> evaluate.
#
#   train/retrain.sh [DATA_DIR] [RUN_DIR]
#
# DATA_DIR (default train/runs/sim-v1, git-ignored) is simulated first when it has no dataset.json.
# Relative paths are taken from the current folder (the script changes folder later).
# RUN_DIR (default train/runs/<date>) receives checkpoints, logs and reports; the ONNX files go to
# MODELS_DIR (default data/models). Knobs (environment): MINUTES (Marknet wall-clock budget, 48: the shipped run),
# THREADS (2), STEM (s4: the shipped architecture, one stride-4 stem convolution; s2: a stride-2 stage),
# CANONICAL (auto: canonical crops in the isotropic auto layout, as the shipped model; stretch), INIT (a Marknet checkpoint or exported .onnx to warm-start from, same architecture), LR (peak
# learning rate, the trainer's 3e-3), P_CONTACT (share of crops centred near a contact, 0), SEED (0), SIM_ARGS (arguments of `gelstereo simulate` besides --out), REAL_VIDEO (zero-shot check).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
DATA="$(realpath -m "${1:-$ROOT/train/runs/sim-v1}")"
RUN="$(realpath -m "${2:-$ROOT/train/runs/$(date -u +%Y%m%dT%H%M%SZ)}")"
MODELS="$(realpath -m "${MODELS_DIR:-$ROOT/data/models}")"
MINUTES="${MINUTES:-48}"
THREADS="${THREADS:-2}"
SIM_ARGS="${SIM_ARGS:---experiments 60 --frames-per-experiment 50 --seed 1 --randomization full --quiet}"
REAL_VIDEO="${REAL_VIDEO:-$ROOT/../shared/real/gelsight-mini-press/mini_example.avi}"
PY="$ROOT/.venv/bin/python"
export OMP_NUM_THREADS="$THREADS"

"$PY" -c "import torch" 2>/dev/null || bash "$ROOT/scripts/setup.sh" --with-train
mkdir -p "$RUN"
say() { printf '[retrain %s] %s\n' "$(date -u +%H:%M:%S)" "$*" | tee -a "$RUN/retrain.log"; }

if [ ! -f "$DATA/dataset.json" ]; then
  say "simulating into $DATA ($SIM_ARGS)"
  (cd "$ROOT" && cargo build --release -p gelstereo-cli)
  # shellcheck disable=SC2086
  "$ROOT/target/release/gelstereo" simulate --out "$DATA" $SIM_ARGS
fi

cd "$ROOT/train"
say "training Marknet for $MINUTES min on $DATA"
"$PY" -m gelstereo_train.train_marknet --data "$DATA" --out "$RUN/marknet.pt" --minutes "$MINUTES" \
  --threads "$THREADS" --stem "${STEM:-s4}" --canonical "${CANONICAL:-auto}" --seed "${SEED:-0}" \
  ${INIT:+--init "$INIT"} ${LR:+--lr "$LR"} ${P_CONTACT:+--p-contact "$P_CONTACT"} 2>&1 | tee "$RUN/train_marknet.log"
say "building the MRE set from the validation split and training the MRE"
"$PY" -m gelstereo_train.train_mre --data "$DATA" --marknet "$RUN/marknet.pt" --out "$RUN/mre.pt" \
  --threads "$THREADS" 2>&1 | tee "$RUN/train_mre.log"
say "exporting ONNX into $MODELS"
"$PY" -m gelstereo_train.export --marknet "$RUN/marknet.pt" --mre "$RUN/mre.pt" --out-dir "$MODELS" \
  2>&1 | grep -v -i warn | tee "$RUN/export.log"
say "evaluating the exported models on the test split"
"$PY" -m gelstereo_train.evaluate --data "$DATA" --split test --marknet "$MODELS/marknet.onnx" \
  --mre "$MODELS/mre.onnx" --out "$RUN/eval_test.json" --threads "$THREADS" | tee "$RUN/eval_test.md"
if [ -f "$REAL_VIDEO" ]; then
  say "zero-shot check on $REAL_VIDEO (frames 0-55, 80 markers expected)"
  "$PY" -m gelstereo_train.real_check --video "$REAL_VIDEO" --marknet "$MODELS/marknet.onnx" \
    --mre "$MODELS/mre.onnx" --frames 0-55 --expect 80 --out "$RUN/real_check.json" | tee "$RUN/real_check.txt"
fi
say "done: $RUN"
