#!/usr/bin/env bash
# Runs the parser fuzz targets (tests/fuzz.rs: module fuzz of the test binary `main`) with CASES
# freshly drawn inputs each (default 5000; the test suite runs a fixed set of 256) and writes the
# per-target counts to results/fuzz_CASES.txt.
# Usage: tools/fuzz.sh [CASES]
set -euo pipefail
cd "$(dirname "$0")/.."
cases="${1:-5000}"
mkdir -p results
out="results/fuzz_${cases}.txt"
EXTRANERF_FUZZ_RANDOM=1 EXTRANERF_FUZZ_CASES="$cases" cargo test --release --workspace --test main fuzz:: -- --nocapture --test-threads 1 2>&1 \
    | tee /dev/stderr | grep -oE 'fuzz [^:]+: [0-9]+ inputs.*|test result.*' > "$out"
echo "wrote $out" >&2
