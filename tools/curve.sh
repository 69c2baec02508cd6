#!/usr/bin/env bash
# One convergence curve: trains with `train --eval-every`, which renders the held-out views every
# few steps and appends their mean PSNR, SSIM, LPIPS-alex and opacity, with the training seconds
# so far (evaluations left out), to RUN/curve.jsonl; the curve, the config and the log are then
# copied to results/curves/SCENE/NAME.*.
#
# Usage: tools/curve.sh SCENE NAME EVAL_EVERY [train flags...]
#   SCENE: fern17 (fern 8x, few-shot 17: the standard LLFF hold-out of views 0, 8, 16),
#          fern17colmap (the same views of fern 8x exported as a COLMAP capture by
#                 `extranerf export`, under runs/fern_colmap, read by the COLMAP loader),
#          fernx  (fern 8x, extrapolation split: 6 central views, 8 farthest held out),
#          demo   (the demo's procedural scene: 6-camera rig, 8 views outside it).
#   The flags go to `extranerf train` after the scene's own (for example --budget 900, or
#   --steps 3000 --rays 256). tools/curves.sh runs the committed set.
#   Depth targets: the ones c85d100's baselines (../shared/baselines) and every curve before
#   issue 52 trained with, unless the flags give --depth or --depth-dir: fern17 and fernx
#   --depth sparse (COLMAP's points), synth2 and demo --depth none (train's own default, auto,
#   would take synth2's exact depth/ and MVS depth elsewhere).
set -euo pipefail
# One brace group, read whole before it runs: editing this file during a run cannot change it.
{
cd "$(dirname "$0")/.."
[ $# -ge 3 ] || { sed -n 2,18p "$0"; exit 2; }
scene="$1"; name="$2"; every="$3"; shift 3
data="${EXTRANERF_DATA:-../shared/data}"
# EXTRANERF_BIN: a binary to use instead of building the release one.
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
case "$scene" in
    fern17) args=(--scene "$data/llff/fern" --split fewshot --fewshot-views 17); depth=sparse ;;
    fern17colmap)
        if [ ! -f runs/fern_colmap/sparse/0/cameras.txt ]; then
            rm -rf runs/fern_colmap
            "$bin" export --scene "$data/llff/fern" --factor 8 --out runs/fern_colmap >&2
        fi
        args=(--scene runs/fern_colmap --factor 1 --split fewshot --fewshot-views 17)
        depth=sparse ;;
    fernx) args=(--scene "$data/llff/fern" --split extrapolation); depth=sparse ;;
    synth2) args=(--scene "$data/synth2" --split extrapolation); depth=none ;;
    demo)
        # The demo writes its scene (ray traced in code, 96x72) under runs/curve_demo_scene/scene.
        if [ ! -f runs/curve_demo_scene/scene/poses_bounds.npy ]; then
            "$bin" demo --out runs/curve_demo_scene --width 96 --stop-after scene >&2
        fi
        args=(--scene runs/curve_demo_scene/scene --split extrapolation --factor 1); depth=none ;;
    *) echo "unknown scene $scene: use fern17, fern17colmap, fernx, synth2 or demo" >&2; exit 2 ;;
esac
case " $* " in
    *" --depth "*|*" --depth="*|*" --depth-dir "*|*" --depth-dir="*) ;;
    *) args+=(--depth "$depth") ;;
esac
run="runs/curve_${scene}_${name}"
rm -rf "$run"
mkdir -p runs "results/curves/$scene"
"$bin" train "${args[@]}" --out "$run" --eval-every "$every" --log-every 50 "$@" 2>&1 | tee "$run.log"
cp "$run/curve.jsonl" "results/curves/$scene/$name.jsonl"
cp "$run/config.json" "results/curves/$scene/$name.config.json"
cp "$run.log" "results/curves/$scene/$name.log"
exit
}
