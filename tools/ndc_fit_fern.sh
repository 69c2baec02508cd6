#!/usr/bin/env bash
# Issue 48's first deliverable: what the NDC grid box and the sampled range do at a fixed step
# count, on SCENE (a tools/curve.sh scene: fern17 by default, fernx, synth2). Curves of STEPS steps (tools/curve.sh, held-out views every
# EVERY steps), the c85d100 model and each fix alone and together:
#   unit_full      --grid-box unit --sample-range full  (the model before: NDC's unit cube, t 0..1)
#   cameras_full   --sample-range full                   (the box that holds every camera's samples)
#   unit_bounds    --grid-box unit                       (samples between the scene's depth bounds)
#   cameras_bounds (the defaults: both)
#   training_bounds --grid-box training                  (the box of the training cameras only)
# then `eval --views all --lpips-nets alex` of each run: held-out and training-view PSNR, and
# the PSNR of the pixels whose rendered point lies inside and outside NDC's unit cube
# (metrics.json's unit_cube), into results/curves/SCENE/ndc_NAME_stepsSTEPS.metrics.json; on
# synth2 also over the exactly visible and not-visible pixels (--visibility-masks
# ../shared/data/synth2/gt_visibility).
# A table of every variant evaluated so far goes to results/curves/SCENE/ndc_fit_stepsSTEPS.md;
# plot with
#   tools/plot_curves.py fern17 ndc_unit_full_steps6000 ... --x steps --out fern17_ndc_fit
#
# EVAL_ONLY=1 evaluates the runs already trained again (runs/curve_SCENE_ndc_*) without
# training them again.
#
# Usage: [SCENE=fern17] [STEPS=6000] [EVERY=1000] [ONLY="unit_full cameras_bounds"] [EVAL_ONLY=1]
#        [EXTRANERF_BIN=...]
#        tools/ndc_fit_fern.sh [more train flags, other than --grid-box and --sample-range]
set -euo pipefail
# One brace group, read whole before it runs: editing this file during a run cannot change it.
{
cd "$(dirname "$0")/.."
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
export EXTRANERF_BIN="$bin"
scene="${SCENE:-fern17}"
data="${EXTRANERF_DATA:-../shared/data}"
masks=()
[ "$scene" = synth2 ] && masks=(--visibility-masks "$data/synth2/gt_visibility")
steps="${STEPS:-6000}"
every="${EVERY:-1000}"
declare -A flags=(
    [unit_full]="--grid-box unit --sample-range full"
    [cameras_full]="--sample-range full"
    [unit_bounds]="--grid-box unit"
    [cameras_bounds]=""
    [training_bounds]="--grid-box training"
)
order="${ONLY:-unit_full cameras_full unit_bounds cameras_bounds}"
out="results/curves/$scene"
for v in $order; do
    [ -n "${flags[$v]+x}" ] || { echo "unknown variant $v" >&2; exit 2; }
    name="ndc_${v}_steps$steps"
    if [ "${EVAL_ONLY:-0}" = 1 ] && [ -f "runs/curve_${scene}_$name/checkpoint.safetensors" ]; then
        echo "$name: trained already (EVAL_ONLY=1), evaluating" >&2
    else
        # shellcheck disable=SC2086 # the flags are words
        tools/curve.sh "$scene" "$name" "$every" --steps "$steps" ${flags[$v]} "$@"
    fi
    "$bin" eval "runs/curve_${scene}_$name" --views all --lpips-nets alex "${masks[@]}" \
        --out "$out/$name.metrics.json" 2>&1 | tail -1
done
python3 - "$out" "$steps" unit_full cameras_full unit_bounds cameras_bounds training_bounds <<'PY'
import json, sys
out, steps, names = sys.argv[1], sys.argv[2], sys.argv[3:]
rows = ["| variant | held-out PSNR | SSIM | LPIPS-alex | training views PSNR | training views inside / outside the unit cube (outside share) | held-out inside / outside (share) | held-out visible / not visible |",
        "|---|---|---|---|---|---|---|---|"]
f = lambda v: "-" if v is None else f"{v:.2f}"
import os
for n in names:
    if not os.path.exists(f"{out}/ndc_{n}_steps{steps}.metrics.json"):
        continue
    m = json.load(open(f"{out}/ndc_{n}_steps{steps}.metrics.json"))
    u = m.get("unit_cube", {})
    reg = lambda r: (f"{f(u[r]['psnr_inside'])} / {f(u[r]['psnr_outside'])} ({100*u[r]['outside_fraction']:.1f}%)" if r in u else "-")
    t = m["test"]
    vis = f"{f(t.get('psnr_visible'))} / {f(t.get('psnr_not_visible'))}"
    rows.append(f"| {n} | {f(t['psnr'])} | {t['ssim']:.3f} | {t['lpips_alex']:.3f} | {f(m['train']['psnr'])} | {reg('train')} | {reg('test')} | {vis} |")
open(f"{out}/ndc_fit_steps{steps}.md", "w").write("\n".join(rows) + "\n")
print("\n".join(rows))
PY
exit
}
