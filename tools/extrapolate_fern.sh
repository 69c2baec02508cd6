#!/usr/bin/env bash
# ExtraNeRF stage 2 on fern (8x, extrapolation split: 6 central views trained, the 8 farthest
# held out), one variant per inpainter, against the BaseNeRF; then `eval`'s comparison table.
#
# The BaseNeRF is the curve run fernx/steps6889 (`tools/curve.sh fernx steps6889 2000 --steps
# 6889`: the steps that `--budget 900` reached in the committed run fernx/budget900_clock, fixed
# so that the field does not depend on how fast the machine was), trained first when missing.
#
# The diffusion variant uses a scene prior trained here from scratch (no pretrained weights):
# `extranerf diffusion prior --scene ../shared/data/llff/fern --out runs/prior_fern_sPRIOR_STEPS
# --steps PRIOR_STEPS` (PRIOR_STEPS=1000 by default: about 15 minutes on two cores), run first
# when its model is missing and the default inpainters are used.
# The fly-throughs (RUN/flythrough/*.gif) are copied too.
#
# Stage 3 runs too (the enhancer trained here from scratch) unless --no-stage3 is given.
#
# BASE=RUN takes another trained fern run (extrapolation split) as the BaseNeRF instead; it
# must exist.
#
# Usage: [PRIOR_STEPS=N] [OUT=results/...] [BASE=RUN] [RUN=runs/...] [EXTRANERF_BIN=...]
#        tools/extrapolate_fern.sh [extrapolate flags...]
#   (default: --inpainter harmonic,exemplar,diffusion; OUT: results/extrapolate_fern_lavapipe)
set -euo pipefail
cd "$(dirname "$0")/.."
data="${EXTRANERF_DATA:-../shared/data}"
# EXTRANERF_BIN: a binary to use instead of building the release one.
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
base="${BASE:-runs/curve_fernx_steps6889}"
if [ ! -f "$base/checkpoint.safetensors" ]; then
    [ -z "${BASE:-}" ] || { echo "BASE=$base holds no checkpoint.safetensors" >&2; exit 2; }
    tools/curve.sh fernx steps6889 2000 --steps 6889
fi
steps="${PRIOR_STEPS:-1000}"
prior=runs/prior_fern_s$steps
inp=(--inpainter harmonic,exemplar,diffusion --diffusion-model "$prior/model")
for a in "$@"; do [ "$a" = --inpainter ] && inp=(); done
if [ ${#inp[@]} -gt 0 ] && [ ! -f "$prior/model/model_index.json" ]; then
    "$bin" diffusion prior --scene "$data/llff/fern" --split extrapolation --out "$prior" \
        --steps "$steps" \
        2>&1 | tee "$prior.log" >&2
fi
run="${RUN:-runs/extrapolate_fern}"
rm -rf "$run"
/usr/bin/time -f "extrapolate wall %e s" "$bin" extrapolate --base "$base" --out "$run" "${inp[@]}" "$@"
"$bin" eval "$run"
out="${OUT:-results/extrapolate_fern_lavapipe}"
rm -rf "$out"
mkdir -p "$out/images"
cp "$run/eval.md" "$run/eval.json" "$run/extrapolate.json" "$run/extrapolate.log" \
    "$run/visibility/visibility.json" "$out/"
if [ ${#inp[@]} -gt 0 ] && [ -f "$prior.log" ]; then cp "$prior.log" "$out/prior.log"; fi
# Held-out view 0 of the split (scene index 0 is the farthest-left view of fern's rig).
view=$(ls "$run"/visibility/test_*_base.png | head -1 | sed 's/.*test_\([0-9]*\)_base.png/\1/')
cp "$run/visibility/test_${view}_base.png" "$out/images/test_${view}_base.png"
cp "$run/visibility/test_${view}_mask.png" "$out/images/test_${view}_mask.png"
for d in "$run"/stage2-* "$run"/stage3-*; do
    case "$d" in *stage3-data|*stage3-enhancer|*'*') continue ;; esac
    v=$(basename "$d")
    cp "$d/test_${view}.png" "$out/images/test_${view}_$v.png"
    last=$(ls -d "$d"/round_* | tail -1)
    cp "$last/virtual_004.png" "$out/images/virtual_004_$v.png"
done
cp "$run/visibility/virtual_004_base.png" "$run/visibility/virtual_004_mask.png" "$out/images/"
if [ -d "$run/stage3-enhancer" ]; then
    cp "$run/stage3-enhancer/enhancer.json" "$out/"
    cp "$run/stage3-data/triplets.json" "$out/"
    mkdir -p "$out/images/stage3-data"
    cp "$run"/stage3-data/pseudo_mask_000.png "$run"/stage3-data/t*_view000_*.png "$out/images/stage3-data/"
fi
if [ -d "$run/flythrough" ]; then
    mkdir -p "$out/flythrough"
    cp "$run"/flythrough/*.gif "$out/flythrough/"
fi
photo=$(ls "$data/llff/fern/images_8" | sort | sed -n "$((10#$view + 1))p")
cp "$data/llff/fern/images_8/$photo" "$out/images/test_${view}_photo.png"
echo "wrote $out" >&2
