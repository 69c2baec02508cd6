#!/usr/bin/env bash
# Reproduces results/basenerf_fern_<NAME>/: BaseNeRF on fern 8x, extrapolation split (train on
# the 6 central views, test on the 8 farthest), the paper's 5000-step schedule with 128 rays x 32
# samples per step and a 2^17 table, then eval (PSNR, SSIM, LPIPS AlexNet + VGG on the 8 test
# views; PSNR on the 6 training views). Usage: tools/basenerf_fern.sh [NAME] (run folder: runs/fern_NAME).
set -euo pipefail
cd "$(dirname "$0")/.."
name="${1:-lavapipe}"
run="runs/fern_${name}"
out="results/basenerf_fern_${name}"
cargo build --release -p extranerf
mkdir -p runs
./target/release/extranerf train --scene ../shared/data/llff/fern --split extrapolation --out "$run" --depth sparse \
    --steps 5000 --rays 128 --samples 32 --log2-table 17 --log-every 50 2>&1 | tee "$run.train.log"
./target/release/extranerf eval "$run" --views test --save-images --lpips ../shared/models/lpips
./target/release/extranerf eval "$run" --views train --lpips-nets alex --lpips ../shared/models/lpips \
    --out "$run/metrics_train.json"
mkdir -p "$out"
cp "$run/config.json" "$run/metrics.json" "$run/metrics_train.json" "$run/progress.jsonl" "$out/"
cp "$run.train.log" "$out/train.log"
cp "$run/eval/test_004.png" "$run/eval/test_015.png" "$out/"
