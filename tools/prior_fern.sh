#!/usr/bin/env bash
# Reproduces results/prior_fern_<NAME>/: the scene prior (a pixel-space inpainting diffusion
# U-Net trained from scratch, no pretrained weights) on fern's 6 extrapolation training views at
# 1/16 resolution (images_8 halved: 252x189), with 2 held-out 16-pixel regions per view that it
# never trains on; then its inpainting of those regions against the mean-colour, harmonic and
# edge-aware fills (PSNR inside the hole, LPIPS AlexNet on a 32x32 crop around it).
# Usage: tools/prior_fern.sh [NAME] [STEPS] [more `diffusion prior` flags] (run folder:
# runs/prior_fern_NAME), e.g. tools/prior_fern.sh lavapipe_sample 2000 --prediction sample.
set -euo pipefail
cd "$(dirname "$0")/.."
name="${1:-lavapipe}"
steps="${2:-2000}"
shift $(( $# > 2 ? 2 : $# ))
run="runs/prior_fern_${name}"
out="results/prior_fern_${name}"
cargo build --release -p extranerf
mkdir -p runs
rm -rf "$run"
./target/release/extranerf diffusion prior --scene ../shared/data/llff/fern --split extrapolation --out "$run" \
    --steps "$steps" "$@" 2>&1 | tee "$run.log"
mkdir -p "$out"
cp "$run/prior_eval.json" "$run/loss.csv" "$run/loss.svg" "$out/"
cp "$run.log" "$out/prior.log"
rm -rf "$out/eval" && cp -r "$run/eval" "$out/eval"
