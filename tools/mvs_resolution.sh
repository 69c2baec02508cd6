#!/usr/bin/env bash
# How fine the plane sweep must match to supervise training (issue 52): `extranerf mvs` on the
# training views of synth2 (extrapolation split, 6 views, against its exact depth/) and of fern
# few-shot 17 (17 views, against COLMAP's sparse points) at 1/1, 1/2 and 1/4 of 504x378 with
# 32, 64 and 128 planes. Writes OUT/SCENE_dD_pP.json (each run's mvs.json) and OUT/summary.md
# (seconds of the sweep, kept fraction, median and within-5% relative errors).
#
# Usage: [SCENES="synth2 fern17"] [DOWNSCALES="1 2 4"] [PLANES="32 64 128"] tools/mvs_resolution.sh [OUT]
# (the summary covers every run in OUT, so subsets add up; the committed table ran fern17 at
# 1/1 with 32 and 64 planes only, 181 and 315 s of sweeping: 128 planes would take longer still)
set -euo pipefail
# One brace group, read whole before it runs: editing this file during a run cannot change it.
{
cd "$(dirname "$0")/.."
out="${1:-results/mvs_resolution_lavapipe}"
data="${EXTRANERF_DATA:-../shared/data}"
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
eval "$(tools/lavapipe_coop.sh)"
mkdir -p "$out"
for scene in ${SCENES:-synth2 fern17}; do
    case "$scene" in
        synth2) args=(--scene "$data/synth2" --split extrapolation --truth-depth "$data/synth2/depth") ;;
        fern17) args=(--scene "$data/llff/fern" --split fewshot --fewshot-views 17) ;;
    esac
    for d in ${DOWNSCALES:-1 2 4}; do
        for p in ${PLANES:-32 64 128}; do
            tmp="${TMPDIR:-/tmp}/mvs_resolution_${scene}_d${d}_p${p}"
            rm -rf "$tmp"
            echo "== $scene downscale $d planes $p" >&2
            "$bin" mvs "${args[@]}" --downscale "$d" --planes "$p" --out "$tmp" 2>&1 | tail -n 2 >&2
            cp "$tmp/mvs.json" "$out/${scene}_d${d}_p${p}.json"
        done
    done
done
python3 - "$out" > "$out/summary.md" <<'PY'
import glob, json, os, sys
out = sys.argv[1]
print("`extranerf mvs` on the training views (tools/mvs_resolution.sh); seconds: the sweep and the "
      "consistency pass; kept: fraction of the reference pixels (synth2: exact depth) or points "
      "(fern: COLMAP's sparse points) with a kept depth; errors relative to the reference.\n")
print("| scene | matching size | planes | seconds | kept | median error | within 5% | within 10% |")
print("|---|---|---|---|---|---|---|---|")
def key(p):
    j = json.load(open(p))
    return (os.path.basename(p).split("_")[0], -j["width"], j["planes"])
for p in sorted(glob.glob(f"{out}/*_d*_p*.json"), key=key):
    j = json.load(open(p))
    scene = os.path.basename(p).split("_")[0]
    ag = j.get("truth_agreement") or j.get("sparse_agreement")
    print(f"| {scene} | {j['width']}x{j['height']} | {j['planes']} | {j['seconds']:.1f} "
          f"| {100 * ag['coverage']:.1f}% | {100 * ag['median_rel_error']:.2f}% "
          f"| {100 * ag['within_5pct']:.1f}% | {100 * ag['within_10pct']:.1f}% |")
PY
cat "$out/summary.md"
exit
}
