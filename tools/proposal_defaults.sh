#!/usr/bin/env bash
# Issue 54's measurements of the default sampler (the proposal sampler, 32 strata for 16
# samples per ray, 1024 rays a step) at c85d100's compute, on 2 cores with lavapipe:
#   1. fern, extrapolation split: 2600 steps (about 15 minutes at 345 ms a step, the time
#      per step measured in alternating rounds in results/proposal_pairs_idle_lavapipe/),
#      held-out PSNR / SSIM / LPIPS-alex every 650 (results/curves/fernx/);
#   2. synth2, extrapolation split, no depth (as c85d100's baseline): 1040 steps (about 6
#      minutes), then `eval` of the training views and of the held-out views with their exact
#      visibility (results/proposal_defaults_lavapipe/synth2_*.metrics.json);
#   3. `extrapolate`'s stage times on fern (harmonic inpainting, no stage 3) before and after:
#      on a uniform-strata BaseNeRF (fernx uniform_s1300: 1024 x 32, 1300 steps) and on the
#      proposal BaseNeRF of 1 (results/proposal_defaults_lavapipe/extrapolate_{uniform,proposal}/).
# Steps 1 and 2 give quality by step count, which the machine's load does not change; step 3's
# times need an otherwise idle machine. Each part is skipped when its output exists (SKIP=0
# redoes all).
#
# Usage: [EXTRANERF_BIN=...] tools/proposal_defaults.sh
set -euo pipefail
cd "$(dirname "$0")/.."
data="${EXTRANERF_DATA:-../shared/data}"
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
export EXTRANERF_BIN="$bin"
out=results/proposal_defaults_lavapipe
mkdir -p "$out"
redo() { [ "${SKIP:-1}" = 0 ] || [ ! -e "$1" ]; }
p=(--sampler proposal --proposal-samples 32 --samples 16)
if redo runs/curve_fernx_proposal_p32_k16_s2600/checkpoint.safetensors; then
    tools/curve.sh fernx proposal_p32_k16_s2600 650 --steps 2600 "${p[@]}"
fi
s2=runs/curve_synth2_proposal_p32_k16_s1040
if redo "$s2/checkpoint.safetensors"; then
    tools/curve.sh synth2 proposal_p32_k16_s1040 520 --steps 1040 "${p[@]}"
fi
if redo "$out/synth2_test.metrics.json"; then
    "$bin" eval "$s2" --views train --lpips-nets alex --no-kid --out "$out/synth2_train.metrics.json"
    "$bin" eval "$s2" --views test --lpips-nets alex --no-kid \
        --visibility-masks "$data/synth2/gt_visibility" --out "$out/synth2_test.metrics.json"
fi
if redo runs/curve_fernx_uniform_s1300/checkpoint.safetensors; then
    tools/curve.sh fernx uniform_s1300 1300 --steps 1300 --sampler uniform
fi
for v in uniform:runs/curve_fernx_uniform_s1300 proposal:runs/curve_fernx_proposal_p32_k16_s2600; do
    name="${v%%:*}"
    if redo "$out/extrapolate_$name/extrapolate.json"; then
        BASE="${v#*:}" RUN="runs/extrapolate_fern_$name" OUT="$out/extrapolate_$name" \
            tools/extrapolate_fern.sh --inpainter harmonic --no-stage3
    fi
done
echo "wrote $out" >&2
