#!/usr/bin/env bash
# Regenerates docs/benchmarks.md: the current speed and accuracy figures of gelstereo on the bundled
# sample recording, with the machine, the date and the command of each table. Small run counts keep it
# within a few minutes on a 2-core machine: the medians move by 10-20 % between runs on a busy machine,
# so compare the ratios within one report, not figures across reports.
#   scripts/bench-report.sh            # RUNS=50 timed runs per measurement
#   RUNS=200 scripts/bench-report.sh   # steadier medians
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
RUNS="${RUNS:-50}"
BIN="${GELSTEREO:-${CARGO_TARGET_DIR:-$ROOT/target}/release/gelstereo}"
if [ ! -x "$BIN" ]; then
  bash scripts/setup.sh
  cargo build --release --locked -p gelstereo-cli
fi
REC="data/sample/press-slide"
WORK="$(mktemp -d)"
trap 'rm -rf "$WORK"' EXIT
REPORT="$WORK/benchmarks.md"

# Paths of this checkout and of the scratch folder left out of the report.
tidy() { sed "s|$ROOT/||g; s|$WORK|OUT|g"; }

# One section: a heading, the command as a reader would type it, and the output of running the rest.
section() {
  local title="$1" shown="$2"; shift 2
  echo "running: $shown" >&2
  {
    printf '\n## %s\n\n' "$title"
    printf 'Command: `%s`\n\n```\n' "$shown"
    "$@" 2>&1 | tidy
    printf '```\n'
  } >>"$REPORT"
}

cpu="$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2- | sed 's/^ *//')"
{
  echo "# Benchmarks"
  echo
  echo "Current figures of gelstereo, written by \`scripts/bench-report.sh\` (RUNS=$RUNS timed runs per"
  echo "measurement; re-run it to refresh this page). Each section gives its command and the output."
  echo
  echo "| | |"
  echo "|---|---|"
  echo "| date (UTC) | $(date -u '+%Y-%m-%d %H:%M') |"
  echo "| machine | $(nproc) cores, ${cpu:-unknown CPU}, $(awk '/MemTotal/ {printf "%.0f GiB", $2 / 1048576}' /proc/meminfo) |"
  echo "| load average at start | $(cut -d' ' -f1-3 /proc/loadavg) |"
  echo "| gelstereo | $("$BIN" --version 2>&1 | tidy | tr '\n' ' ' | sed 's/ *$//') |"
  echo
  echo "Speed: medians of wall time, with CPU time beside them where the command measures it; ratios are"
  echo "measured side by side in one run. When the load average exceeds the number of cores, wall times"
  echo "measure the contention with other processes; the CPU times per frame are then the figures to compare. A shared"
  echo "machine's speed also moves between runs by up to 1.5x, CPU time included: the pipeline's decode stage runs"
  echo "OpenCV's PNG decoder, which gelstereo does not change, so its CPU time tells the machine's speed from one report"
  echo "to the next. Accuracy: the bundled simulated recording \`$REC\` (24 stereo"
  echo "frames, 640 x 480, 23 x 23 markers, press then slide); the figures on the whole simulated test"
  echo "split are in the guides ([localization](localization.md#accuracy),"
  echo "[matching](matching.md#accuracy), [tracking](tracking.md#accuracy))."
} >"$REPORT"

section "Localization: latency per view and per stereo pair" \
  "gelstereo bench --runs $RUNS --warmup 10 --pairs 8 $REC" \
  "$BIN" bench --runs "$RUNS" --warmup 10 --pairs 8 "$REC"
section "Pipeline: latency and throughput mode" \
  "gelstereo bench --pipeline --runs $RUNS --warmup 10 --repeats 5 $REC" \
  "$BIN" bench --pipeline --runs "$RUNS" --warmup 10 --repeats 5 "$REC"

track_end_to_end() {
  local start end
  start=$(date +%s.%N)
  "$BIN" track --quiet --out "$WORK/track" "$REC"
  end=$(date +%s.%N)
  awk -v s="$start" -v e="$end" 'BEGIN { printf "wall %.2f s for 24 frames from disk: %.1f stereo frames/s, default outputs (overlays, heat maps, PLY, plots)\n", e - s, 24 / (e - s) }'
}
section "End to end: gelstereo track with its default outputs, from disk" \
  "time gelstereo track --quiet --out OUT/track $REC" track_end_to_end

reconstruct_accuracy() {
  "$BIN" reconstruct --calib "$REC/calib.yaml" --out "$WORK/rec" --evaluate "$REC"
}
section "Reconstruction accuracy against the sample's ground truth" \
  "gelstereo reconstruct --calib $REC/calib.yaml --out OUT/rec --evaluate $REC" reconstruct_accuracy

tracking_accuracy() {
  python3 - "$WORK/track/frames.csv" "$REC/frames.csv" <<'PY'
import csv, sys
est = list(csv.DictReader(open(sys.argv[1])))
truth = list(csv.DictReader(open(sys.argv[2])))
same = sum(e["slip"] == t["slip"] for e, t in zip(est, truth))
deep = [(float(e["max_depth_mm"]), float(t["max_depth_mm"])) for e, t in zip(est, truth)
        if t["max_depth_mm"] and float(t["max_depth_mm"]) > 0.1 and e["max_depth_mm"]]
within = sum(abs(a - b) < 0.05 for a, b in deep)
print(f"slip state equal to the truth in {same} of {len(truth)} frames")
print(f"largest depth within 0.05 mm in {within} of {len(deep)} frames deeper than 0.1 mm")
print("largest depth error, mm: " + ", ".join(f"{a - b:+.3f}" for a, b in deep))
PY
}
section "Tracking, contact and slip against the sample's ground truth" \
  "OUT/track/frames.csv (from the end-to-end run) against $REC/frames.csv" tracking_accuracy

cp "$REPORT" docs/benchmarks.md
echo "wrote docs/benchmarks.md" >&2
