#!/usr/bin/env bash
# The README's demo, recorded: `extranerf demo` with its defaults (or the flags given) into
# runs/demo, then its table, summary (settings, device, seconds per part) and picture into
# results/demo_lavapipe/ (the README shows its picture, outside_views.png).
#
# Usage: [EXTRANERF_BIN=...] tools/demo.sh [demo flags]
set -euo pipefail
cd "$(dirname "$0")/.."
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
mkdir -p runs
"$bin" demo --out runs/demo "$@" 2>&1 | tee runs/demo.log
out=results/demo_lavapipe
rm -rf "$out"; mkdir -p "$out"
cp runs/demo/demo.json runs/demo/extranerf/eval.md runs/demo/extranerf/eval.json \
    runs/demo/extranerf/outside_views.png "$out/"
echo "wrote $out" >&2
