#!/usr/bin/env bash
# Issue 58's targets: a 120-frame 252x189 fern fly-through (`render --path spiral`) in under
# 10 minutes on 2 cores, and writing its video adding at most 10% to the time of rendering its
# frames (the render reports both). The BaseNeRF is trained first if its run is not there
# (fern 8x, the default holdout split, sparse depth, STEPS steps).
#
# Usage: tools/flythrough_fern.sh [STEPS] [render flags...]   (STEPS default 2000)
# Writes runs/flythrough_fern_sSTEPS (the run), runs/flythrough_fern_path (frames, path.mp4)
# and results/flythrough_fern/ (the render's log, camera_path.json, the video's size).
set -euo pipefail
{
cd "$(dirname "$0")/.."
steps="${1:-2000}"; [ $# -gt 0 ] && shift
cargo build --release -p extranerf >&2
bin=target/release/extranerf
run="runs/flythrough_fern_s$steps"
if [ ! -f "$run/checkpoint.safetensors" ]; then
    rm -rf "$run"
    "$bin" train --scene "${EXTRANERF_DATA:-../shared/data}/llff/fern" --steps "$steps" \
        --depth sparse --out "$run" >&2
fi
out=runs/flythrough_fern_path
res=results/flythrough_fern
mkdir -p "$res"
/usr/bin/time -f "render --path: %e s wall, %M KiB peak memory" \
    "$bin" render "$run" --path spiral --frames 120 --width 252 --out "$out" "$@" \
    2>&1 | grep -v "render path view" | tee "$res/render.log"
cp "$out/camera_path.json" "$res/"
ls -l "$out/path.mp4" | awk '{print "path.mp4: " $5 " bytes"}' | tee -a "$res/render.log"
exit
}
