#!/usr/bin/env bash
# Reproduces results/bench_diffusion_<NAME>.{txt,json}: `extranerf bench diffusion` (U-Net
# forward and forward+backward at a tiny and a medium config, the LoRA step, on burn's CPU
# backend and on the engine's Vulkan device, plus SD-1.5 inpainting's FLOPs for scale).
# The device rows' warm-up includes burn's shader compilation; run nothing else meanwhile.
# Usage: tools/bench_diffusion.sh [NAME]
set -euo pipefail
cd "$(dirname "$0")/.."
name="${1:-lavapipe}"
cargo build --release -p extranerf
mkdir -p results
{
    ./target/release/extranerf info
    CUBECL_AUTOTUNE_LEVEL=minimal ./target/release/extranerf bench diffusion --iters 3 \
        --json "results/bench_diffusion_${name}.json"
} 2>&1 | tee "results/bench_diffusion_${name}.txt"
