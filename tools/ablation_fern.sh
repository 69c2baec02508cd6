#!/usr/bin/env bash
# The paper's diffusion ablation rows on fern (issue 18): the fern stage-3 run of
# tools/extrapolate_fern.sh (RUN, its harmonic variant already done) is resumed with two more
# stage-2 inpainters, each followed by stage 3:
#   diffusion-base  the scene prior without adapters (the "un-fine-tuned" row),
#   diffusion       the same prior with LoRA adapters fine-tuned on the 6 training views and
#                   their pseudo-disocclusion masks (the "fine-tuned" row).
# No pretrained Stable Diffusion weights exist on these machines: the prior is
# `extranerf diffusion prior` trained here from scratch on fern's training views.
#
# Steps (each skipped when its output exists):
#  1. the prior: runs/prior_fern_sPRIOR_STEPS (PRIOR_STEPS=1000, as tools/extrapolate_fern.sh);
#  2. the training views' pseudo-disocclusion masks: `visibility BASE --training-masks`
#     (runs/trainmasks_fernx);
#  3. the adapters: `diffusion finetune` (LORA_STEPS=500, ExtraNeRF's) into runs/lora_fern_sN;
#  4. `extrapolate --resume` on RUN with --inpainter harmonic,diffusion-base,diffusion and the
#     settings RUN was made with (EXTRA: by default those of results/extrapolate_fern_stage3_lavapipe);
#  5. tools/kid_fern.sh: eval.md/json (the issue's KID protocol) and eval_kid_quarter.md/json
#     into OUT (QUARTER=0: only the issue's protocol, about an hour less with seven rows), plus the run's
#     manifest, log and the new variants' images.
#
# Usage: [RUN=runs/extrapolate_fern_stage3] [OUT=results/extrapolate_fern_stage3_lavapipe]
#        [PRIOR_STEPS=1000] [LORA_STEPS=500] [QUARTER=1] [EXTRANERF_BIN=...] tools/ablation_fern.sh
set -euo pipefail
cd "$(dirname "$0")/.."
data="${EXTRANERF_DATA:-../shared/data}"
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
export EXTRANERF_BIN="$bin"
base=runs/curve_fernx_steps6889
run="${RUN:-runs/extrapolate_fern_stage3}"
out="${OUT:-results/extrapolate_fern_stage3_lavapipe}"
if [ ! -f "$run/extrapolate.json" ]; then
    echo "$run holds no extrapolate run: make it first with" >&2
    echo "  RUN=$run OUT=$out tools/extrapolate_fern.sh --inpainter harmonic --diffusion-backend cpu" >&2
    exit 2
fi
steps="${PRIOR_STEPS:-1000}"
prior=runs/prior_fern_s$steps
if [ ! -f "$prior/model/model_index.json" ]; then
    /usr/bin/time -f "diffusion prior wall %e s" \
        "$bin" diffusion prior --scene "$data/llff/fern" --split extrapolation --out "$prior" \
        --steps "$steps" \
        2>&1 | tee "$prior.log" >&2
fi
masks=runs/trainmasks_fernx
if [ ! -f "$masks/visibility.json" ]; then
    /usr/bin/time -f "training masks wall %e s" \
        "$bin" visibility "$base" --training-masks --out "$masks" 2>&1 | tee "$masks.log" >&2
fi
lsteps="${LORA_STEPS:-500}"
lora=runs/lora_fern_s$lsteps
if [ ! -f "$lora/pytorch_lora_weights.safetensors" ]; then
    /usr/bin/time -f "diffusion finetune wall %e s" \
        "$bin" diffusion finetune --model "$prior/model" --scene "$data/llff/fern" --split extrapolation \
        --masks "$masks" --out "$lora" --steps "$lsteps" --diffusion-backend cpu \
        2>&1 | tee "$lora.log" >&2
fi
# The settings the stage-3 run in results/ was made with (docs/results.md, the first fern ablation).
read -r -a extra <<<"${EXTRA:---diffusion-backend cpu --enhancer-steps 200 --stage3-gate off}"
/usr/bin/time -f "extrapolate (resumed) wall %e s" \
    "$bin" extrapolate --base "$base" --out "$run" --resume \
    --inpainter harmonic,diffusion-base,diffusion --diffusion-model "$prior/model" \
    --diffusion-lora "$lora" "${extra[@]}"
mkdir -p "$out/images"
cp "$run/extrapolate.json" "$run/extrapolate.log" "$out/"
cp "$prior.log" "$out/prior.log"
cp "$lora.log" "$out/finetune.log"
cp "$lora/loss.svg" "$out/finetune_loss.svg"
cp "$masks/visibility.json" "$out/training_masks.json"
view=$(ls "$run"/visibility/test_*_base.png | head -1 | sed 's/.*test_\([0-9]*\)_base.png/\1/')
for v in stage2-diffusion-base stage2-diffusion stage3-diffusion-base stage3-diffusion; do
    cp "$run/$v/test_${view}.png" "$out/images/test_${view}_$v.png"
    last=$(ls -d "$run/$v"/round_* | tail -1)
    cp "$last/virtual_004.png" "$out/images/virtual_004_$v.png"
done
mkdir -p "$out/flythrough"
cp "$run"/flythrough/*.gif "$out/flythrough/"
if [ "${QUARTER:-1}" = 1 ]; then
    RUN="$run" OUT="$out" tools/kid_fern.sh
else
    /usr/bin/time -f "eval wall %e s" "$bin" eval "$run" 2>&1 | tee "$out/eval.log"
    cp "$run/eval.md" "$run/eval.json" "$out/"
fi
echo "wrote $out" >&2
