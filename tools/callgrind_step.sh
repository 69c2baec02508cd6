#!/usr/bin/env bash
# Instruction counts of the training step, the measure that this machine's load does not
# change (its wall time varies 2x from one minute to the next): `bench train` in issue 61's
# configuration (256 rays x 32 samples, 2^17 table, 16 levels, fused step, scalar MLPs, uniform
# strata) under valgrind's callgrind, twice (STEPS_A and STEPS_B timed steps; each run adds 2
# warm-up steps and 1 profiled step), then tools/callgrind_step.py: the fused kernel's and the
# whole step's instructions per trained sample. Prints them and writes them to OUT.
#
# Usage: tools/callgrind_step.sh [BIN] [OUT] [STEPS_A] [STEPS_B]
#   BIN: default ./target/release/extranerf (built first); OUT: default
#   results/fused_accounting_lavapipe/callgrind_<commit>.txt; steps: default 1 and 3.
#   An older commit's binary, e.g. c85d100's (its 600 s GPU wait must be raised first, since it
#   has no EXTRANERF_GPU_TIMEOUT_S):
#     git worktree add /tmp/c85 c85d100 && cd /tmp/c85 && sed -i \
#       's/WAIT_TIMEOUT_S: u64 = 600;/WAIT_TIMEOUT_S: u64 = 36000;/' engine/gpu/src/context.rs \
#       && CARGO_TARGET_DIR=/tmp/c85-target cargo build --release -p extranerf
#     tools/callgrind_step.sh /tmp/c85-target/release/extranerf \
#       results/fused_accounting_lavapipe/callgrind_c85d100.txt
#
# Notes: valgrind offers the program no AVX-512, so lavapipe compiles AVX2 code under it (on
# an AVX-512 machine the native code differs); the first run of a build compiles every kernel
# under valgrind (many minutes: EXTRANERF_GPU_TIMEOUT_S is raised here), later runs find them
# in Mesa's shader cache. Validation is off (the layer's own instructions are not the step's).
set -euo pipefail
cd "$(dirname "$0")/.."
bin="${1:-}"
if [ -z "$bin" ]; then
    cargo build --release -p extranerf
    bin=./target/release/extranerf
fi
out="${2:-results/fused_accounting_lavapipe/callgrind_$(git rev-parse --short HEAD).txt}"
steps_a="${3:-1}"
steps_b="${4:-3}"
flags=(bench train --rays 256 --samples 32 --log2-table 17 --levels 16 --step fused --mlp scalar)
# Builds before the proposal sampler (issue 53) have no --sampler and only uniform strata.
if "$bin" bench train --help | grep -q -- "--sampler"; then
    flags+=(--sampler uniform)
fi
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
export EXTRANERF_VALIDATION=off EXTRANERF_GPU_TIMEOUT_S=36000
for s in "$steps_a" "$steps_b"; do
    mkdir -p "$tmp/$s"
    start=$(date +%s)
    valgrind --tool=callgrind --separate-threads=yes \
        --callgrind-out-file="$tmp/$s/callgrind.out.%p" \
        "$bin" "${flags[@]}" --steps "$s" > "$tmp/$s/stdout.txt" 2> "$tmp/$s/valgrind.txt"
    echo "callgrind run of $s timed steps: $(( $(date +%s) - start )) s" >&2
done
mkdir -p "$(dirname "$out")"
{
    echo "binary: $bin"
    echo "command: $bin ${flags[*]} --steps $steps_a / $steps_b, under valgrind --tool=callgrind"
    grep -m1 "^device:" "$tmp/$steps_b/stdout.txt" || true
    python3 tools/callgrind_step.py "$tmp/$steps_a" "$tmp/$steps_b" 256 32
} > "$out"
cat "$out"
