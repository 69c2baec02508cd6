#!/usr/bin/env bash
# Reproduces results/bench_kernels_<device>.{txt,json}: the primitive microbenchmarks at the
# default sizes (2^16, 2^20, 2^24 elements), 7 timed runs each. Usage: tools/bench_kernels.sh [NAME]
set -euo pipefail
cd "$(dirname "$0")/.."
name="${1:-lavapipe}"
cargo build --release -p extranerf
./target/release/extranerf info | tee "results/bench_kernels_${name}.txt"
./target/release/extranerf bench kernels --json "results/bench_kernels_${name}.json" | tee -a "results/bench_kernels_${name}.txt"
