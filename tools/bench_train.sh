#!/usr/bin/env bash
# Reproduces results/bench_train_<NAME>.{txt,json}: the training step on fern 8x (256 rays x 32
# samples) with the paper's MLPs and a 2^17 table, and with the demo's small model.
# Usage: tools/bench_train.sh [NAME]
set -euo pipefail
cd "$(dirname "$0")/.."
name="${1:-lavapipe}"
cargo build --release -p extranerf
./target/release/extranerf bench train --log2-table 17 --steps 10 \
    --json "results/bench_train_${name}.json" | tee "results/bench_train_${name}.txt"
./target/release/extranerf bench train --log2-table 15 --width 32 --levels 8 --steps 10 \
    --json "results/bench_train_${name}_small.json" | tee -a "results/bench_train_${name}.txt"
