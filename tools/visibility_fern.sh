#!/usr/bin/env bash
# Visibility on fern (issue 4): maps for the 8 extrapolation test views and for 8 outward
# virtual cameras, the pseudo-disocclusion masks of the 6 training views, and the cost per pixel
# against the number of training cameras (march vs transmittance volumes).
# Needs a trained run (default runs/fern_lavapipe from tools/basenerf_fern.sh).
# Usage: tools/visibility_fern.sh [RUN] [OUT]
set -euo pipefail
cd "$(dirname "$0")/.."
RUN=${1:-runs/fern_lavapipe}
OUT=${2:-results/visibility_fern_lavapipe}
DATA=${EXTRANERF_DATA:-../shared/data}
BIN=target/release/extranerf
cargo build --release -p extranerf
mkdir -p "$OUT"
"$BIN" cameras --scene "$DATA/llff/fern" --split extrapolation --trajectory outward --count 8 --range 1.5 \
    --out "$OUT/outward_cameras.json"
"$BIN" visibility "$RUN" --views test --cameras "$OUT/outward_cameras.json" --training-masks \
    --downscale 4 --complete-depth 400 --out "$OUT/maps" 2>&1 | tee "$OUT/visibility.log"
"$BIN" bench visibility "$RUN" --downscale 8 --json "$OUT/bench_visibility.json" \
    | tee "$OUT/bench_visibility_lavapipe.txt"
