#!/usr/bin/env bash
# Reproduces results/train_occupancy_lavapipe/: training with the occupancy grid in the fused
# step against the standalone chain with the same grid and against the fused step without a
# grid. fern 8x, extrapolation split, 1000 steps of 128 rays x 32 samples, 2^17 table; the grid
# is 64^3, swept every 64 steps, from step 256 on. Each run is then scored on the 8 test views
# (PSNR, SSIM, LPIPS AlexNet). Usage: tools/train_occupancy.sh [STEPS]
set -euo pipefail
cd "$(dirname "$0")/.."
steps="${1:-1000}"
out="results/train_occupancy_lavapipe"
cargo build --release -p extranerf
mkdir -p runs "$out"
run_one() {
    local name="$1"
    shift
    local run="runs/occ_${name}"
    rm -rf "$run"
    ./target/release/extranerf train --scene ../shared/data/llff/fern --split extrapolation --out "$run" \
        --steps "$steps" --rays 128 --samples 32 --log2-table 17 --log-every 50 "$@" 2>&1 \
        | tee "$out/${name}.train.log"
    ./target/release/extranerf eval "$run" --views test --lpips-nets alex \
        --lpips ../shared/models/lpips --out "$out/${name}.metrics.json"
}
grid=(--occupancy-res 64 --occupancy-every 64)
run_one fused_grid --step fused "${grid[@]}"
run_one standalone_grid --step standalone "${grid[@]}"
run_one fused_nogrid --step fused
