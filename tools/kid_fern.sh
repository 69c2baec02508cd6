#!/usr/bin/env bash
# KID of a fern extrapolate run (issue 18) under both protocols, into its results folder:
#  1. the issue's: `extranerf eval RUN` (full frame over the 8 held-out views; patch KID on 500
#     128x128 crops covering the not-visible mask by at least half, 100 subsets of 100);
#  2. fern's masks are thin borders of the frame (about 5% of each view), which no 128x128 crop
#     covers by half, so patch KID is also measured with crops that cover it by a quarter
#     (`--kid-min-fraction 0.25`), which ranks the variants there.
# Each eval writes RUN/eval.md, eval.json and report.html; the tables are copied to OUT as
# eval.md/json (protocol 1) and eval_kid_quarter.md/json (protocol 2). The report (about 11 MB,
# every image inlined) stays in RUN.
#
# Usage: [RUN=runs/extrapolate_fern_stage3] [OUT=results/extrapolate_fern_stage3_lavapipe]
#        [EXTRANERF_BIN=...] tools/kid_fern.sh
# Needs the Inception weights (tools/fetch_inception.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
run="${RUN:-runs/extrapolate_fern_stage3}"
out="${OUT:-results/extrapolate_fern_stage3_lavapipe}"
mkdir -p "$out"
/usr/bin/time -f "eval (quarter-covered crops) wall %e s" \
    "$bin" eval "$run" --kid-min-fraction 0.25 2>&1 | tee "$out/eval_kid_quarter.log"
cp "$run/eval.md" "$out/eval_kid_quarter.md"
cp "$run/eval.json" "$out/eval_kid_quarter.json"
/usr/bin/time -f "eval wall %e s" "$bin" eval "$run" 2>&1 | tee "$out/eval.log"
cp "$run/eval.md" "$run/eval.json" "$out/"
