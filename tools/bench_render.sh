#!/usr/bin/env bash
# Reproduces results/bench_render_<NAME>.{txt,json}: rendering fern 8x test views 4 and 15
# (504x378, 32 samples per ray) from a BaseNeRF trained 1500 steps (128 rays x 32 samples, 2^17
# table), through the standalone training kernels and the fused march with each accuracy cut
# and occupancy grid. Usage: tools/bench_render.sh [NAME] (run folder: runs/fern1500; an
# existing one is reused).
set -euo pipefail
cd "$(dirname "$0")/.."
name="${1:-lavapipe}"
run="runs/fern1500"
cargo build --release -p extranerf
if [ ! -f "$run/checkpoint.safetensors" ]; then
    mkdir -p runs
    ./target/release/extranerf train --scene ../shared/data/llff/fern --split extrapolation --out "$run" --depth sparse \
        --steps 1500 --rays 128 --samples 32 --log2-table 17 --log-every 50
fi
./target/release/extranerf bench render "$run" --views 4,15 \
    --json "results/bench_render_${name}.json" | tee "results/bench_render_${name}.txt"
