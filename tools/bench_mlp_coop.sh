#!/usr/bin/env bash
# The MLPs through cooperative matrices against the scalar kernels, on the device this machine
# selects: device and driver (`extranerf info`, which lists the cooperative-matrix shapes),
# `bench kernels --only mlp` (both paths, and the coop gradient's difference from f32),
# `bench train --mlp coop,scalar` on fern 8x with the paper's MLPs (fused and standalone
# steps) in ROUNDS alternating rounds, and `bench render` (the fused march with either path,
# exact, with cuts and occupancy grids) of view 0 of a 300-step fern run.
# Writes results/mlp_coop_<NAME>/.
#
# On lavapipe select the Mesa 26 driver first: eval "$(tools/lavapipe_coop.sh)".
# Usage: tools/bench_mlp_coop.sh [NAME] [ROUNDS]   (EXTRANERF_BIN: a built binary to use;
# EXTRANERF_DATA: the data folder, default ../shared/data)
set -euo pipefail
cd "$(dirname "$0")/.."
name="${1:-lavapipe}"
rounds="${2:-2}"
out="results/mlp_coop_${name}"
mkdir -p "$out"
bin="${EXTRANERF_BIN:-}"
if [ -z "$bin" ]; then
    cargo build --release -p extranerf
    bin=./target/release/extranerf
fi
{
    echo "date: $(date -u +%FT%TZ)"
    echo "command: tools/bench_mlp_coop.sh $name $rounds (binary $bin)"
    echo "VK_DRIVER_FILES=${VK_DRIVER_FILES:-}"
} >"$out/info.txt"
"$bin" info | tee -a "$out/info.txt"
"$bin" bench kernels --only mlp --json "$out/kernels.json" | tee "$out/kernels.txt"
: >"$out/train.txt"
for r in $(seq 1 "$rounds"); do
    for mlp in coop scalar; do
        echo "== round $r, --mlp $mlp" | tee -a "$out/train.txt"
        "$bin" bench train --log2-table 17 --steps 10 --mlp "$mlp" \
            --json "$out/train_${mlp}_round${r}.json" | tee -a "$out/train.txt"
    done
done
grep -h "samples/s;" "$out/train.txt" | sed 's/^/  /' | tee "$out/summary.txt"
data="${EXTRANERF_DATA:-../shared/data}"
"$bin" train --scene "$data/llff/fern" --split extrapolation --depth sparse --steps 300 --mlp scalar --out "$out/fern_run" \
    >"$out/fern_run.txt" 2>&1
"$bin" bench render "$out/fern_run" --views 0 --json "$out/render.json" | tee "$out/render.txt"
rm -rf "$out/fern_run"
