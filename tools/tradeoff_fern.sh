#!/usr/bin/env bash
# Speed against accuracy on fern 8x (issue 6): `extranerf bench tradeoff` trains one model per
# sweep point (one knob changed from the base at a time, plus the auto-config's choice), scores
# the 8 held-out extrapolation views at half resolution, and writes tradeoff.{csv,json,svg}.
# Do not compile or run other work meanwhile: the times are the point.
# Usage: tools/tradeoff_fern.sh [OUT]
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-results/tradeoff_fern_lavapipe}
DATA=${EXTRANERF_DATA:-../shared/data}
cargo build --release -p extranerf
mkdir -p "$OUT"
target/release/extranerf bench tradeoff --scene "$DATA/llff/fern" --steps 800 --rays 128 \
    --samples 32 --log2-table 17 --eval-downscale 2 --out "$OUT" 2>&1 | tee "$OUT/tradeoff.log"
