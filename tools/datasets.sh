#!/usr/bin/env bash
# Reproduces results/datasets_<NAME>/: the standard data sets at their real size.
#  1. nerf_synthetic_800: the generated turntable scene in NeRF-synthetic's layout at its real
#     size (100 training views of 800x800 RGBA, 20 test views): `train` for STEPS800 steps
#     (default 300) prints its device memory and samples/s; `eval` scores 4 of the test
#     split's views over white at 800x800 (PSNR, SSIM, LPIPS-alex).
#  2. turntable_100: the same scene at 100x100 (100 + 20 views) trained for --budget BUDGET
#     seconds (default 300), evaluated on its 20 test views over white (the exact renders): the
#     held-out PSNR the README quotes.
#  3. fern_4x_all: fern at 4x (20 views of 1008x756, --split all) for STEPS_FERN steps (default
#     100): its memory line and samples/s.
# Usage: tools/datasets.sh [NAME]; about 25 minutes on two cores with lavapipe.
# EXTRANERF_BIN=path runs that binary instead of building the release one (the kernels' speed is
# the driver's either way; the binary used is recorded in info.txt).
set -euo pipefail
cd "$(dirname "$0")/.."
name="${1:-lavapipe}"
out="results/datasets_${name}"
runs="runs/datasets_${name}"
data="${EXTRANERF_DATA:-../shared/data}"
if [ -n "${EXTRANERF_BIN:-}" ]; then
    bin="$EXTRANERF_BIN"
else
    cargo build --release -p extranerf
    bin=./target/release/extranerf
fi
rm -rf "$runs" "$out"
mkdir -p "$runs" "$out"
{ echo "binary: $bin"; $bin info; } > "$out/info.txt"

# 1. 100 views at 800x800.
$bin turntable --out "$runs/synthetic800" --size 800 --train 100 --test 20 2>&1 | tee "$out/nerf_synthetic_800.txt"
$bin train --scene "$runs/synthetic800" --out "$runs/synthetic800_run" --steps "${STEPS800:-300}" \
    --log-every 50 2>&1 | tee -a "$out/nerf_synthetic_800.txt"
$bin eval "$runs/synthetic800_run" --views 100,105,110,115 --lpips-nets alex \
    --out "$out/nerf_synthetic_800_metrics.json" 2>&1 | tail -1 \
    | tee -a "$out/nerf_synthetic_800.txt"

# 2. The turntable at 100x100 against its exact renders.
$bin turntable --out "$runs/turntable100" --size 100 --train 100 --test 20 2>&1 | tee "$out/turntable_100.txt"
$bin train --scene "$runs/turntable100" --split extrapolation --out "$runs/turntable100_run" --budget "${BUDGET:-300}" \
    --log-every 50 2>&1 | tee -a "$out/turntable_100.txt"
$bin eval "$runs/turntable100_run" --views test --lpips-nets alex \
    --out "$out/turntable_100_metrics.json" 2>&1 | tail -1 \
    | tee -a "$out/turntable_100.txt"
cp "$runs/turntable100_run/config.json" "$out/turntable_100_config.json"

# 3. fern at 4x, all 20 views.
$bin train --scene "$data/llff/fern" --factor 4 --split all --out "$runs/fern4x_all" \
    --steps "${STEPS_FERN:-100}" --log-every 50 2>&1 | tee "$out/fern_4x_all.txt"
