#!/usr/bin/env bash
# Soak test of `gelstereo track` (docs/reliability.md; not run in CI): a long recording made by
# repeating the bundled sample's 24 frames (hard links, no extra disk), tracked once while its peak
# resident memory is sampled every second. Memory must stay flat: the peak after N frames about the
# same as after N/10.
#
#   scripts/soak.sh [FRAMES=10000] [extra track options...]
#   GELSTEREO_BIN=target/debug/gelstereo scripts/soak.sh 2000 --method blob
#
# Prints the RSS samples (MB) every 10 % of the run and the peak; exits 1 when the peak in the last
# half of the run exceeds the peak in the first half by more than 10 %.
set -euo pipefail
frames=${1:-10000}
shift || true
root=$(cd "$(dirname "$0")/.." && pwd)
sample="$root/data/sample/press-slide"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
rec="$work/long"
mkdir -p "$rec/left" "$rec/right"
for side in left right; do
    for ((k = 0; k < frames; k++)); do
        src=$(printf '%06d.jpg' $((k % 24)))
        ln "$sample/$side/$src" "$rec/$side/$(printf '%06d.jpg' "$k")"
    done
done
cp "$sample/calib.yaml" "$rec/calib.yaml"
# GELSTEREO_BIN: an already built binary (default: a release build made here).
bin=${GELSTEREO_BIN:-}
if [[ -z "$bin" ]]; then
    cargo build --release -q -p gelstereo-cli --manifest-path "$root/Cargo.toml"
    bin="${CARGO_TARGET_DIR:-$root/target}/release/gelstereo"
fi
start=$(date +%s)
"$bin" track --quiet --no-ply --overlay-every 0 --out "$work/out" "$@" "$rec" &
pid=$!
samples="$work/rss.txt"
while kill -0 "$pid" 2>/dev/null; do
    awk '/VmRSS/ {print $2}' "/proc/$pid/status" 2>/dev/null >>"$samples" || true
    sleep 1
done
wait "$pid"
secs=$(($(date +%s) - start))
rows=$(($(wc -l <"$work/out/frames.csv") - 1))
echo "tracked $rows frames in ${secs} s"
awk -v n="$(wc -l <"$samples")" '
    { rss[NR] = $1 / 1024 }
    END {
        for (i = 1; i <= n; i++) {
            if (i <= n / 2 && rss[i] > first) first = rss[i]
            if (i > n / 2 && rss[i] > last) last = rss[i]
            if (n >= 10 && i % int(n / 10) == 0) printf "  %3d%%  RSS %.0f MB\n", 100 * i / n, rss[i]
        }
        printf "peak RSS first half %.0f MB, second half %.0f MB\n", first, last
        exit (last > 1.1 * first) ? 1 : 0
    }' "$samples"
