#!/usr/bin/env bash
# A prepared run for a GPU machine (one 15-minute window): checks the driver, then measures the
# cooperative-matrix MLP path against the scalar one and trains fern for 5000 steps, collecting
# everything in results/gpu_<NAME>/ (copy that folder back).
#   1. nvidia-smi, the Vulkan devices (`extranerf info --list`, `extranerf info`: the
#      cooperative-matrix shapes, 16x16x16 f16*f16+f32 expected on NVIDIA)
#   2. `bench kernels` (all primitives and the MLP variants)
#   3. `bench train --mlp coop,scalar` (fused and standalone steps, 2^17 table)
#   4. `train` on fern 4x, 5000 steps, --mlp auto, then `eval` on the held-out views
#   5. `bench render` of that run's views 0 and 1 (the fused march with scalar and
#      coop MLPs, exact, with cuts and occupancy grids)
# Usage: tools/gpu_coop.sh [NAME]   (EXTRANERF_BIN: a built binary; else a release build,
# several minutes from cold on 16 cores). Each step has its own time limit, so one that hangs
# does not eat the window; a failed step is recorded and the next one runs.
set -uo pipefail
cd "$(dirname "$0")/.."
name="${1:-h200}"
out="results/gpu_${name}"
mkdir -p "$out"
bin="${EXTRANERF_BIN:-}"
if [ -z "$bin" ]; then
    timeout 420 cargo build --release -p extranerf >"$out/build.log" 2>&1 || { echo "build failed: $out/build.log"; exit 1; }
    bin=./target/release/extranerf
fi
step() { # name seconds command...
    local n="$1" s="$2"; shift 2
    echo "== $n ($*)"
    if timeout "$s" "$@" >"$out/$n.txt" 2>&1; then echo "ok"; else echo "FAILED or timed out (exit $?): see $out/$n.txt"; fi
    tail -n 5 "$out/$n.txt"
}
{ date -u +%FT%TZ; nvidia-smi || true; } >"$out/driver.txt" 2>&1
step info_list 30 "$bin" info --list
step info 30 "$bin" info --json "$out/info.json"
step bench_kernels 120 "$bin" bench kernels --json "$out/bench_kernels.json"
step bench_train 180 "$bin" bench train --log2-table 17 --steps 20 --mlp coop,scalar --json "$out/bench_train.json"
data="${EXTRANERF_DATA:-../shared/data}"
step train_fern 300 "$bin" train --scene "$data/llff/fern" --split extrapolation --factor 4 --steps 5000 --mlp auto --out "$out/fern_run"
step eval_fern 120 "$bin" eval "$out/fern_run" --out "$out/fern_eval.json"
step bench_render 90 "$bin" bench render "$out/fern_run" --views 0,1 --json "$out/bench_render.json"
rm -f "$out/fern_run/"*.safetensors
echo "results in $out"
