#!/usr/bin/env bash
# Issue 48's second deliverable: the training recipe on fern few-shot 17 at equal compute, that
# is equal samples processed (steps x rays x samples per ray), so the machine's speed does not
# enter. Each variant changes one setting of the defaults and trains for BUDGET million samples
# (default 49.152: 6,000 steps of 256 x 32), evaluated 6 times along the way (tools/curve.sh:
# the held-out views' PSNR, SSIM, LPIPS-alex); the training rays' PSNR is that of the last 10
# logged windows of 50 steps (RUN/progress.jsonl, copied beside the curve); EVAL=1 also runs
# `eval --views all --lpips-nets alex` (the training views' PSNR; about 3.5 minutes a run).
# Results: results/curves/fern17/recipe_VARIANT_mBUDGET.* and recipe_mBUDGET.md (a table);
# plots with tools/plot_curves.py fern17 ... --x samples.
#
# Usage: [BUDGET=49.152] [ONLY="base s64 ..."] [EVAL=1] [TABLE_ONLY=1] [BASE_FROM=NAME]
#        [EXTRANERF_BIN=...] tools/recipe_fern.sh
# Variants (the first word of each line below); `base` is the recipe before issue 48's new defaults
# (256 x 32, a 2^17 table, which every variant names so that it does not depend on this build's
# auto-config), and each variant changes one setting of it. The r1024_* variants ask
# the learning-rate, loss and table questions again at 1,024 rays per step (the batch that
# processes samples fastest here, tools/bench_recipe.sh).
# TABLE_ONLY=1 trains nothing: it writes the table and plots of the ONLY variants already run.
# BASE_FROM=NAME takes `base` from results/curves/fern17/NAME.* and runs/curve_fern17_NAME
# (a curve that tools/curve.sh already ran with the same settings, for example
# ndc_cameras_bounds_steps6000 of tools/ndc_fit_fern.sh) instead of training it again; its
# config must match `base` at this budget (checked) and the table says where it came from.
set -euo pipefail
# One brace group, read whole before it runs: editing this file during a run cannot change it.
{
cd "$(dirname "$0")/.."
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
export EXTRANERF_BIN="$bin"
budget="${BUDGET:-49.152}"
# name | rays | samples | other flags
variants="base 256 32 --log2-table 17
s64 256 64 --log2-table 17
s128 256 128 --log2-table 17
r1024 1024 32 --log2-table 17
r2048 2048 32 --log2-table 17
r4096 4096 32 --log2-table 17
lrend3e-4 256 32 --lr-end 3e-4 --log2-table 17
lrend1e-3 256 32 --lr-end 1e-3 --log2-table 17
lrconst1e-2 256 32 --lr-end 1e-2 --log2-table 17
lr2e-2 256 32 --lr-start 2e-2 --log2-table 17
lr3e-2 256 32 --lr-start 3e-2 --log2-table 17
huber 256 32 --rgb-loss huber --log2-table 17
t19 256 32 --log2-table 19
r1024_lrend3e-4 1024 32 --lr-end 3e-4 --log2-table 17
r1024_lrend1e-3 1024 32 --lr-end 1e-3 --log2-table 17
r1024_lrconst1e-2 1024 32 --lr-end 1e-2 --log2-table 17
r1024_lr2e-2 1024 32 --lr-start 2e-2 --log2-table 17
r1024_lr3e-2 1024 32 --lr-start 3e-2 --log2-table 17
r1024_huber 1024 32 --rgb-loss huber --log2-table 17
r1024_t19 1024 32 --log2-table 19
r1024_t19_sparse 1024 32 --log2-table 19 --adam sparse"
only="${ONLY:-$(echo "$variants" | cut -d' ' -f1 | tr '\n' ' ')}"
tag="m$budget"
out=results/curves/fern17
for v in $only; do
    [ "${TABLE_ONLY:-0}" = 1 ] && break
    if [ "$v" = base ] && [ -n "${BASE_FROM:-}" ]; then
        # The scene and model must be those of a variant trained here with the default table
        # (the model depends on the scene only), the training settings the defaults.
        python3 - "$out/$BASE_FROM.config.json" "$budget" "$out" "$tag" <<'PY'
import glob, json, sys
c = json.load(open(sys.argv[1]))
t = c["train"]
want = {"rays": 256, "samples": 32, "steps": round(float(sys.argv[2]) * 1e6 / 8192),
        "lr_start": 0.01, "lr_end": 0.003, "rgb_loss": "l2"}
bad = {k: (t[k], v) for k, v in want.items() if t[k] != v}
if bad:
    sys.exit(f"BASE_FROM {sys.argv[1]}: not the base training settings (found, wanted): {bad}")
refs = [json.load(open(f)) for f in sorted(glob.glob(f"{sys.argv[3]}/recipe_*_{sys.argv[4]}.config.json"))
        if "recipe_base_" not in f]
refs = [r for r in refs if r["model"]["log2_table"] == 17]
if not refs:
    sys.exit("BASE_FROM: run a variant with the default table first (its model is the reference)")
if (c["model"], c["scene"]) != (refs[0]["model"], refs[0]["scene"]):
    sys.exit(f"BASE_FROM {sys.argv[1]}: its scene or model differs from this build's defaults: "
             f"{c['model']} against {refs[0]['model']}")
PY
        for ext in jsonl config.json log; do
            cp "$out/$BASE_FROM.$ext" "$out/recipe_base_$tag.$ext"
        done
        cp "runs/curve_fern17_$BASE_FROM/progress.jsonl" "$out/recipe_base_$tag.progress.jsonl"
        echo "$BASE_FROM" > "$out/recipe_base_$tag.from"
        continue
    fi
    line=$(echo "$variants" | awk -v v="$v" '$1 == v')
    [ -n "$line" ] || { echo "unknown variant $v" >&2; exit 2; }
    read -r _ rays samples flags <<<"$line"
    steps=$(python3 -c "print(round($budget * 1e6 / ($rays * $samples)))")
    every=$(( (steps + 5) / 6 ))
    name="recipe_${v}_$tag"
    # A variant that cannot run (4096 x 32 needs MLP records larger than lavapipe's 128 MiB
    # binding) is reported and the others go on.
    # shellcheck disable=SC2086 # the flags are words
    if ! tools/curve.sh fern17 "$name" "$every" --steps "$steps" --rays "$rays" --samples "$samples" $flags; then
        echo "variant $v failed: see runs/curve_fern17_$name.log" >&2
        continue
    fi
    # The training rays' PSNR: the last 10 logged windows of 50 steps (RUN/progress.jsonl).
    cp "runs/curve_fern17_$name/progress.jsonl" "$out/$name.progress.jsonl"
    if [ "${EVAL:-0}" = 1 ]; then
        "$bin" eval "runs/curve_fern17_$name" --views all --lpips-nets alex \
            --out "$out/$name.metrics.json" 2>&1 | tail -1
    fi
done
python3 - "$out" "$tag" $only <<'PY'
import json, sys
out, tag, names = sys.argv[1], sys.argv[2], sys.argv[3:]
import math
rows = ["| variant | steps | rays x samples | held-out PSNR | SSIM | LPIPS-alex | training rays PSNR (last 10 windows of 50 steps) | training views PSNR (EVAL=1) | train s |",
        "|---|---|---|---|---|---|---|---|---|"]
for n in names:
    base = f"{out}/recipe_{n}_{tag}"
    try:
        c = json.load(open(base + ".config.json"))["train"]
    except FileNotFoundError:
        continue
    last = [json.loads(l) for l in open(base + ".jsonl") if l.strip()][-1]
    prog = [json.loads(l) for l in open(base + ".progress.jsonl") if l.strip()][-10:]
    rays = -10 * math.log10(sum(p["mse"] for p in prog) / len(prog))
    try:
        views = f"{json.load(open(base + '.metrics.json'))['train']['psnr']:.2f}"
    except FileNotFoundError:
        views = "-"
    try:
        n_shown = f"{n} (the run {open(base + '.from').read().strip()})"
    except FileNotFoundError:
        n_shown = n
    rows.append(f"| {n_shown} | {last['step']} | {c['rays']} x {c['samples']} | {last['test_psnr']:.2f} | {last['test_ssim']:.3f} | {last['test_lpips_alex']:.3f} | {rays:.2f} | {views} | {last['train_seconds']:.0f} |")
open(f"{out}/recipe_{tag}.md", "w").write("\n".join(rows) + "\n")
print("\n".join(rows))
PY
# One plot per question against samples processed, for the questions whose curves all exist:
# results/curves/fern17_recipe_QUESTION_mBUDGET.svg.
for q in "samples:base s64 s128" "rays:base r1024 r2048 r4096" "lr_end:base lrend3e-4 lrend1e-3 lrconst1e-2" \
         "lr_start:base lr2e-2 lr3e-2" "loss:base huber" "table:base t19" \
         "r1024_lr_end:r1024 r1024_lrend3e-4 r1024_lrend1e-3 r1024_lrconst1e-2" \
         "r1024_lr_start:r1024 r1024_lr2e-2 r1024_lr3e-2" "r1024_loss:r1024 r1024_huber" \
         "r1024_table:r1024 r1024_t19" "t19_adam:r1024_t19 r1024_t19_sparse"; do
    names=()
    for v in ${q#*:}; do
        [ -f "$out/recipe_${v}_$tag.jsonl" ] && names+=("recipe_${v}_$tag")
    done
    [ "${#names[@]}" -gt 1 ] || continue
    python3 tools/plot_curves.py fern17 "${names[@]}" --x samples \
        --out "fern17_recipe_${q%%:*}_$tag" >/dev/null
done
exit
}
