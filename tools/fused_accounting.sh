#!/usr/bin/env bash
# Issue 61's accounting of the fused training step on this machine's lavapipe: ROUNDS rounds of
# `bench kernels --only micro` (each operation the step is made of, ns per operation) and
# `bench train` in issue 61's fixed configuration (the fused step's GPU time, median of 5
# profiled steps), then tools/fused_accounting.py: per trained sample each operation's count
# times its cost, the predicted kernel time beside the measured one, per round. Writes
# OUT/round*/{micro,train}.{json,txt} and OUT/table.md (with OUT/callgrind*.txt from
# tools/callgrind_step.sh when present). Run nothing else meanwhile: times are the point.
#
# Usage: [BASE_BIN=...] tools/fused_accounting.sh [OUT] [ROUNDS]
#   OUT: default results/fused_accounting_lavapipe; ROUNDS: default 3.
#   BASE_BIN: an older build (e.g. c85d100's, tools/callgrind_step.sh shows how to build it)
#   whose `bench train` in the same configuration runs in every round too, for its fused
#   kernel's and whole step's times beside this build's (OUT/round*/train_base.*).
#   The driver is whatever Vulkan selects: the system's lavapipe, or with
#   eval "$(tools/lavapipe_coop.sh)" the Mesa 26 one (use another OUT).
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-results/fused_accounting_lavapipe}"
rounds="${2:-3}"
cargo build --release -p extranerf
bin=./target/release/extranerf
mkdir -p "$out"
rm -rf "$out"/round*
for r in $(seq "$rounds"); do
    d="$out/round$r"
    mkdir -p "$d"
    "$bin" bench kernels --sizes 4096 --only micro --repeats 7 --json "$d/micro.json" > "$d/micro.txt"
    "$bin" bench train --rays 256 --samples 32 --log2-table 17 --levels 16 --step fused \
        --mlp scalar --sampler uniform --steps 10 --profile-steps 5 --json "$d/train.json" \
        > "$d/train.txt"
    if [ -n "${BASE_BIN:-}" ]; then
        base=(bench train --rays 256 --samples 32 --log2-table 17 --levels 16 --step fused
            --mlp scalar --steps 10 --json "$d/train_base.json")
        # Builds before the proposal sampler (issue 53) have only uniform strata.
        if "$BASE_BIN" bench train --help | grep -q -- "--sampler"; then
            base+=(--sampler uniform)
        fi
        "$BASE_BIN" "${base[@]}" > "$d/train_base.txt"
    fi
    echo "round $r of $rounds done"
done
BASE_NAME="${BASE_NAME:-${BASE_BIN:-}}" python3 tools/fused_accounting.py "$out" > "$out/table.md"
cat "$out/table.md"
