#!/usr/bin/env bash
# Regenerates the README's pictures (docs/images/) from the bundled sample recording: the overlay of
# both views at frame 16 (gross slip), the 3-D contact surface at the deepest frame and the slip state
# over time, as `gelstereo track` draws them.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
BIN="${GELSTEREO:-${CARGO_TARGET_DIR:-$ROOT/target}/release/gelstereo}"
[ -x "$BIN" ] || { bash scripts/setup.sh; cargo build --release --locked -p gelstereo-cli; }
OUT="$(mktemp -d)"
trap 'rm -rf "$OUT"' EXIT
"$BIN" track --quiet --no-ply --overlay-every 16 --out "$OUT" data/sample/press-slide
mkdir -p docs/images
cp "$OUT/overlays/000016.png" docs/images/overlay.png
cp "$OUT/plots/contact_surface.png" docs/images/contact_surface.png
cp "$OUT/plots/slip.png" docs/images/slip.png
cp "$OUT/plots/max_depth.svg" docs/images/max_depth.svg
echo "docs/images: overlay.png contact_surface.png slip.png max_depth.svg"
