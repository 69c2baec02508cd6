#!/usr/bin/env bash
# Issue 48's first deliverable: what the NDC grid box and the sampled range do to fern few-shot
# 17 at a fixed step count. Four curves of STEPS steps (tools/curve.sh, held-out views every
# EVERY steps), the c85d100 model and each fix alone and together:
#   unit_full      --grid-box unit --sample-range full  (the model before: NDC's unit cube, t 0..1)
#   cameras_full   --sample-range full                   (the box that holds every camera's samples)
#   unit_bounds    --grid-box unit                       (samples between the scene's depth bounds)
#   cameras_bounds (the defaults: both)
# then `eval --views all --lpips-nets alex` of each run: held-out and training-view PSNR, and
# the PSNR of the pixels whose rendered point lies inside and outside NDC's unit cube
# (metrics.json's unit_cube), into results/curves/fern17/ndc_NAME_stepsSTEPS.metrics.json.
# A table of the results goes to results/curves/fern17/ndc_fit_stepsSTEPS.md; plot with
#   tools/plot_curves.py fern17 ndc_unit_full_steps6000 ... --x steps --out fern17_ndc_fit
#
# EVAL_ONLY=1 evaluates the runs already trained again (runs/curve_fern17_ndc_*) without
# training them again.
#
# Usage: [STEPS=6000] [EVERY=1000] [ONLY="unit_full cameras_bounds"] [EVAL_ONLY=1]
#        [EXTRANERF_BIN=...]
#        tools/ndc_fit_fern.sh [more train flags, other than --grid-box and --sample-range]
set -euo pipefail
cd "$(dirname "$0")/.."
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
export EXTRANERF_BIN="$bin"
steps="${STEPS:-6000}"
every="${EVERY:-1000}"
declare -A flags=(
    [unit_full]="--grid-box unit --sample-range full"
    [cameras_full]="--sample-range full"
    [unit_bounds]="--grid-box unit"
    [cameras_bounds]=""
)
order="${ONLY:-unit_full cameras_full unit_bounds cameras_bounds}"
out=results/curves/fern17
for v in $order; do
    [ -n "${flags[$v]+x}" ] || { echo "unknown variant $v" >&2; exit 2; }
    name="ndc_${v}_steps$steps"
    if [ "${EVAL_ONLY:-0}" = 1 ] && [ -f "runs/curve_fern17_$name/checkpoint.safetensors" ]; then
        echo "$name: trained already (EVAL_ONLY=1), evaluating" >&2
    else
        # shellcheck disable=SC2086 # the flags are words
        tools/curve.sh fern17 "$name" "$every" --steps "$steps" ${flags[$v]} "$@"
    fi
    "$bin" eval "runs/curve_fern17_$name" --views all --lpips-nets alex \
        --out "$out/$name.metrics.json" 2>&1 | tail -1
done
python3 - "$out" "$steps" $order <<'PY'
import json, sys
out, steps, names = sys.argv[1], sys.argv[2], sys.argv[3:]
rows = ["| variant | held-out PSNR | SSIM | LPIPS-alex | training views PSNR | training views inside / outside the unit cube (outside share) | held-out inside / outside (share) |",
        "|---|---|---|---|---|---|---|"]
f = lambda v: "-" if v is None else f"{v:.2f}"
for n in names:
    m = json.load(open(f"{out}/ndc_{n}_steps{steps}.metrics.json"))
    u = m.get("unit_cube", {})
    reg = lambda r: (f"{f(u[r]['psnr_inside'])} / {f(u[r]['psnr_outside'])} ({100*u[r]['outside_fraction']:.1f}%)" if r in u else "-")
    t = m["test"]
    rows.append(f"| {n} | {f(t['psnr'])} | {t['ssim']:.3f} | {t['lpips_alex']:.3f} | {f(m['train']['psnr'])} | {reg('train')} | {reg('test')} |")
open(f"{out}/ndc_fit_steps{steps}.md", "w").write("\n".join(rows) + "\n")
print("\n".join(rows))
PY
