#!/usr/bin/env bash
# Leave one family out: Marknets of the default's shape trained from random weights side by side on
# the same widened-sensor data, one with every family (`with`) and one without each held-out family,
# then each scored on every family's test experiments (docs/experiments/localization-families.md, "Leave one family out").
#
#   train/scripts/leave_one_family_out.sh train OUT          # on a GPU machine with 16 cores, ~9 min
#   train/scripts/leave_one_family_out.sh score OUT VIEWS    # anywhere: export, evaluate, print the table
#
# train: simulates the train split of `--randomization wide` (EXPERIMENTS, 1,600; 4 frames, seed 141;
# the reference look `full` tags no families and has 1280x720 variants, so it is left out), then runs
# the five trainers at once, each with 2 batch makers and MINUTES (7.3) of training, writing
# OUT/NAME.pt and OUT/train.log. Without a gelstereo build it runs the simulator packed by
# scripts/pack_simulator.py (SIMULATOR, default .gpu/simulator.tar.xz). PY: the Python with PyTorch
# (default python3; the checkout's .venv where it exists); DEVICE (cuda).
# score: exports each OUT/NAME.pt to OUT/NAME/ with the default's MRE, runs `gelstereo eval` on the
# views of scripts/family_views.py (VIEWS: its --out for the test split of WIDE2) and prints the
# table (scripts/family_table.py).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
MODE="${1:?train or score}"
OUT="$(realpath -m "${2:?output folder}")"
NAMES=(with no_hue no_hex no_720 no_scan)
declare -A HELD_OUT=([no_hue]=marker:hue [no_hex]=lattice:hexagonal [no_720]=res:1280x720 [no_scan]=texture:scanlines)
# scripts/family_views.py names a family's view with `:` as `_`
VIEWS_SCORED=(marker_hue lattice_hexagonal res_1280x720 texture_scanlines all)
if [ -z "${PY:-}" ]; then
  PY=python3
  [ -x "$ROOT/.venv/bin/python" ] && PY="$ROOT/.venv/bin/python"
fi
GELSTEREO="${GELSTEREO:-${CARGO_TARGET_DIR:-$ROOT/target}/release/gelstereo}"
mkdir -p "$OUT"

simulate_train_split() {  # out experiments frames seed randomization
  if [ -x "$GELSTEREO" ]; then
    "$GELSTEREO" simulate --out "$1" --experiments "$2" --frames-per-experiment "$3" --seed "$4" \
      --randomization "$5" --split train --quiet
  else
    local packed="${SIMULATOR:-$ROOT/.gpu/simulator.tar.xz}" unpacked
    unpacked="$(dirname "$1")/simulator"
    mkdir -p "$unpacked" && tar -C "$unpacked" -xJf "$packed"
    LD_LIBRARY_PATH="$unpacked/lib" "$unpacked/simulate_split" "$1" "$2" "$3" "$4" "$5" train
  fi
}

train_all() {
  # global: the EXIT trap runs after this function's locals are gone
  SCRATCH="$(mktemp -d)"
  trap 'rm -rf "$SCRATCH"' EXIT
  local data="$SCRATCH/W"
  simulate_train_split "$data" "${EXPERIMENTS:-1600}" 4 141 wide
  cd "$ROOT/train"
  local common=(--data "$data" --minutes "${MINUTES:-7.3}" --device "${DEVICE:-cuda}" --augment-on device
    --batch 96 --threads 1 --workers 2 --seed 7 --stem s4 --canonical auto --p-contact 0.5
    --max-images 6000 --max-gb 12 --save-every-min 1)
  for name in "${NAMES[@]}"; do
    local exclude=()
    [ -n "${HELD_OUT[$name]:-}" ] && exclude=(--exclude-family "${HELD_OUT[$name]}")
    OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1 "$PY" -m gelstereo_train.train_marknet "${common[@]}" \
      --out "$OUT/$name.pt" "${exclude[@]}" 2>&1 | sed -u "s/^/[$name] /" >> "$OUT/train.log" &
  done
  wait
}

score_all() {
  local views="${1:?VIEWS folder of scripts/family_views.py}"
  export LD_LIBRARY_PATH="$ROOT/.deps/onnxruntime/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  cd "$ROOT/train"
  for name in "${NAMES[@]}"; do
    "$PY" -m gelstereo_train.export --marknet "$OUT/$name.pt" --out-dir "$OUT/$name" \
      --preferred-layout isotropic > "$OUT/$name.export.log" 2>&1
    cp "$ROOT/data/models/mre.onnx" "$OUT/$name/"
    for view in "${VIEWS_SCORED[@]}"; do
      "$GELSTEREO" eval --dataset "$views/$view" --methods marknet-mre --frame-step 4 --threads 1 \
        --models "$OUT/$name" --out "$OUT/eval/$name/$view" > /dev/null
    done
  done
  "$PY" scripts/family_table.py --eval "$OUT/eval" --models "${NAMES[@]}" --views "${VIEWS_SCORED[@]}"
}

case "$MODE" in
  train) train_all ;;
  score) score_all "${3:-}" ;;
  *) echo "unknown mode '$MODE': expected train or score" >&2; exit 2 ;;
esac
