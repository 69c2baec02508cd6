#!/usr/bin/env bash
# Issue 48's fourth deliverable: the BaseNeRF with this build's defaults (or with the train flags
# given) at a fixed compute, that is a fixed number of samples processed (steps x rays x samples
# per ray), so the machine's speed does not enter. By default c85d100's 15-minute compute:
# 16,969 steps of 256 x 32 = 139.01 M samples (`--budget 900` on fern few-shot 17 on 2026-12-04,
# ../shared/baselines/README.md). For each scene (tools/curve.sh scenes) a curve with the held-out
# views evaluated 6 times, then `eval --views all --lpips-nets alex` (on synth2 also over the
# exact visible and not-visible pixels of ../shared/data/synth2/gt_visibility); the training
# rays' PSNR is that of the last 10 logged windows of 50 steps.
# Results: results/curves/SCENE/NAME_mMILLIONS.* and results/curves/equal_compute_NAME_mMILLIONS.md
#
# EVAL=0 leaves out the `eval` (about 3.5 minutes a scene): the held-out figures are then the
# curve's last, and the training views' PSNR is not measured. The table lists every scene that
# has results under NAME, so that scenes run in separate calls (in parallel) share it.
#
# Usage: [MSAMPLES=139.01] [SCENES="fern17 fernx synth2"] [NAME=defaults] [EVAL=1] [EXTRANERF_BIN=...]
#        tools/equal_compute.sh [train flags, for example --rays 256 --lr-end 1e-3]
set -euo pipefail
# One brace group, read whole before it runs: editing this file during a run cannot change it.
{
cd "$(dirname "$0")/.."
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
export EXTRANERF_BIN="$bin"
msamples="${MSAMPLES:-139.01}"
scenes="${SCENES:-fern17 fernx synth2}"
name="${NAME:-defaults}_m$msamples"
data="${EXTRANERF_DATA:-../shared/data}"
# Rays and samples per ray: the flags' where given, else the defaults `train --help` states.
read -r rays samples < <(python3 - "$("$bin" train --help)" "$@" <<'PY'
import re, sys
helptext, flags = sys.argv[1], sys.argv[2:]
def pick(flag, label):
    for i, f in enumerate(flags):
        if f == flag and i + 1 < len(flags):
            return flags[i + 1]
        if f.startswith(flag + "="):
            return f.split("=", 1)[1]
    m = re.search(label + r" \[default: (\d+)\]", helptext)
    if not m:
        sys.exit(f"train --help does not state the default of {flag}")
    return m.group(1)
print(pick("--rays", "Rays per step"), pick("--samples", "Samples per ray"))
PY
)
steps=$(python3 -c "print(round($msamples * 1e6 / ($rays * $samples)))")
every=$(( (steps + 5) / 6 ))
echo "$name: $steps steps of $rays x $samples ($msamples M samples)" >&2
for scene in $scenes; do
    masks=()
    [ "$scene" = synth2 ] && masks=(--visibility-masks "$data/synth2/gt_visibility")
    out="results/curves/$scene"
    tools/curve.sh "$scene" "$name" "$every" --steps "$steps" "$@"
    cp "runs/curve_${scene}_$name/progress.jsonl" "$out/$name.progress.jsonl"
    rm -f "$out/$name.metrics.json"
    if [ "${EVAL:-1}" = 1 ]; then
        "$bin" eval "runs/curve_${scene}_$name" --views all --lpips-nets alex "${masks[@]}" \
            --out "$out/$name.metrics.json" 2>&1 | tail -1
    fi
done
python3 - "$name" fern17 fernx synth2 > "results/curves/equal_compute_$name.md" <<'PY'
import json, math, os, sys
name, scenes = sys.argv[1], sys.argv[2:]
print("| scene | steps | rays x samples | held-out PSNR | SSIM | LPIPS-alex | held-out visible / not visible | training views PSNR | training rays PSNR (last 10 windows of 50 steps) | train s |")
print("|---|---|---|---|---|---|---|---|---|---|")
f = lambda v: "-" if v is None else f"{v:.2f}"
for s in scenes:
    base = f"results/curves/{s}/{name}"
    if not os.path.exists(base + ".progress.jsonl"):
        continue
    c = json.load(open(base + ".config.json"))["train"]
    last = [json.loads(l) for l in open(base + ".jsonl") if l.strip()][-1]
    prog = [json.loads(l) for l in open(base + ".progress.jsonl") if l.strip()][-10:]
    rays = -10 * math.log10(sum(p["mse"] for p in prog) / len(prog))
    if os.path.exists(base + ".metrics.json"):
        m = json.load(open(base + ".metrics.json"))
        t = m["test"]
        views = f(m["train"]["psnr"])
    else:
        t = {"psnr": last["test_psnr"], "ssim": last["test_ssim"], "lpips_alex": last["test_lpips_alex"]}
        views = "- (EVAL=0)"
    vis = f"{f(t.get('psnr_visible'))} / {f(t.get('psnr_not_visible'))}"
    print(f"| {s} | {last['step']} | {c['rays']} x {c['samples']} | {f(t['psnr'])} | {t['ssim']:.3f} | {t['lpips_alex']:.3f} | {vis} | {views} | {rays:.2f} | {last['train_seconds']:.0f} |")
PY
cat "results/curves/equal_compute_$name.md"
exit
}
