#!/usr/bin/env bash
# Plane-sweep MVS on fern's 6 extrapolation training views (issue 4): depth maps, confidence,
# and agreement with the COLMAP sparse points, at two settings (half resolution with 64 planes,
# the default; full resolution with 128 planes). The EXR depth maps stay out of the repository.
# Usage: tools/mvs_fern.sh [OUT]
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-results/mvs_fern_lavapipe}
DATA=${EXTRANERF_DATA:-../shared/data}
BIN=target/release/extranerf
cargo build --release -p extranerf
mkdir -p "$OUT"
"$BIN" mvs --scene "$DATA/llff/fern" --split extrapolation --out "$OUT/half_64" 2>&1 | tee "$OUT/half_64.log"
"$BIN" mvs --scene "$DATA/llff/fern" --split extrapolation --downscale 1 --planes 128 --out "$OUT/full_128" 2>&1 \
    | tee "$OUT/full_128.log"
rm -f "$OUT"/*/*.exr "$OUT"/full_128/*.png
