#!/usr/bin/env bash
# One stage-3 setting tried on the fern stage-3 run (issue 18): the run RUN is copied to NEW
# (once), its stage3-STAGE2 stage redone there with the stage-3 flags given as arguments
# (`extrapolate --resume --redo stage3-STAGE2`, its fly-through runs again too), and NEW is
# evaluated without KID (`eval --no-kid`, every variant of the copy). The table, the run's
# manifest and log and the redone variant's images go to OUT.
#
# Usage: [RUN=runs/extrapolate_fern_stage3] [STAGE2=harmonic] [EXTRANERF_BIN=...]
#        tools/stage3_variant_fern.sh NEW OUT [STAGE-3 FLAGS...]
# e.g.   tools/stage3_variant_fern.sh runs/fern_stage3_anchor3 \
#            results/extrapolate_fern_stage3_anchor3_lavapipe --stage3-anchor 3
# RUN's other settings are repeated from results/extrapolate_fern_stage3_lavapipe (its
# enhancer stopped at 200 steps, stage 3 not gated as in the runs made before the gate): EXTRA
# (default `--diffusion-backend cpu --enhancer-steps 200 --stage3-gate off`).
set -euo pipefail
cd "$(dirname "$0")/.."
if [ $# -lt 2 ]; then
    sed -n '2,14p' "$0" >&2
    exit 2
fi
new="$1"
out="$2"
shift 2
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
run="${RUN:-runs/extrapolate_fern_stage3}"
kind="${STAGE2:-harmonic}"
base=runs/curve_fernx_steps6889
if [ ! -f "$run/extrapolate.json" ]; then
    echo "$run holds no extrapolate run (tools/extrapolate_fern.sh makes it)" >&2
    exit 2
fi
if [ ! -d "$new" ]; then
    cp -a "$run" "$new.part"
    mv "$new.part" "$new"
fi
read -r -a extra <<<"${EXTRA:---diffusion-backend cpu --enhancer-steps 200 --stage3-gate off}"
mkdir -p "$out/images"
/usr/bin/time -f "extrapolate --redo stage3-$kind wall %e s" \
    "$bin" extrapolate --base "$base" --out "$new" --resume --inpainter "$kind" \
    --redo "stage3-$kind" "${extra[@]}" "$@" 2>&1 | tee "$out/extrapolate_redo.log"
/usr/bin/time -f "eval wall %e s" "$bin" eval "$new" --no-kid 2>&1 | tee "$out/eval.log"
cp "$new/eval.md" "$new/eval.json" "$new/extrapolate.json" "$out/"
if ! ls -d "$new/stage3-$kind"/round_* >/dev/null 2>&1; then
    # --stage3-gate check kept the stage-2 field: its renders are stage 2's, byte for byte.
    rm -rf "$out/images"
    echo "stage3-$kind was skipped by its gate (eval.md says why): no images of its own" >&2
else
    for f in "$new/stage3-$kind"/test_*.png; do
        cp "$f" "$out/images/$(basename "$f" .png)_stage3-$kind.png"
    done
    last=$(ls -d "$new/stage3-$kind"/round_* | tail -1)
    cp "$last/virtual_004.png" "$out/images/virtual_004_stage3-$kind.png"
    cp "$last/virtual_004_render.png" "$out/images/virtual_004_render_stage3-$kind.png"
fi
echo "wrote $out" >&2
