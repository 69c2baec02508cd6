#!/usr/bin/env bash
# ExtraNeRF stage 2 on the demo scene (generated in code; its generator knows exactly which
# points the rig cameras see): the demo's BaseNeRF at 96x72 after 300 steps (`extranerf demo
# --stop-after basenerf`), then `extrapolate` with each inpainter and `eval`'s table.
# visibility.json scores the held-out views' masks against the exact visibility (IoU, accuracy).
# Writes results/extrapolate_demo_lavapipe/: eval.md, eval.json, extrapolate.json,
# visibility.json, extrapolate.log, flythrough/*.gif.
set -euo pipefail
cd "$(dirname "$0")/.."
bin="${CARGO_TARGET_DIR:-target}/release/extranerf"
cargo build --release -p extranerf >&2
rm -rf runs/extrapolate_demo
"$bin" demo --out runs/extrapolate_demo --width 96 --steps 300 --stop-after basenerf >&2
"$bin" extrapolate --base runs/extrapolate_demo/basenerf --out runs/extrapolate_demo/ex \
    --virtual-downscale 1 --inpainter harmonic,exemplar,hybrid "$@"
"$bin" eval runs/extrapolate_demo/ex
out=results/extrapolate_demo_lavapipe
rm -rf "$out"; mkdir -p "$out"
run=runs/extrapolate_demo/ex
cp "$run/eval.md" "$run/eval.json" "$run/extrapolate.json" "$run/extrapolate.log" \
    "$run/visibility/visibility.json" "$out/"
mkdir -p "$out/flythrough"
cp "$run"/flythrough/*.gif "$out/flythrough/"
echo "wrote $out" >&2
