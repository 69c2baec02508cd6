#!/usr/bin/env bash
# How much of the fused training step the two MLPs cost: `bench train --step fused` at 256 rays
# x 32 samples with a 2^17 table, for hidden widths 64 (the default), 32 and 16, in alternating
# rounds (the MLPs' multiply-adds and weight loads scale with the width squared, the hash grid,
# compositing and records much less). Writes OUT/bench.txt and OUT/summary.md (per width the
# GPU milliseconds of the fused kernel, the weight gradients and Adam per round, and the best).
# Usage: tools/bench_mlp_width.sh [ROUNDS] [OUT]   (default 3, results/step_pairs_lavapipe)
set -euo pipefail
cd "$(dirname "$0")/.."
rounds="${1:-3}"
out="${2:-results/step_pairs_lavapipe}"
bin="${CARGO_TARGET_DIR:-target}/release/extranerf"
cargo build --release -p extranerf >&2
mkdir -p "$out"
: > "$out/mlp_width.txt"
for r in $(seq "$rounds"); do
    for w in 64 32 16; do
        echo "== round $r width $w" | tee -a "$out/mlp_width.txt"
        "$bin" bench train --step fused --rays 256 --samples 32 --log2-table 17 --width "$w" \
            --steps 12 2>&1 | grep -E "^model:|fused step:|^fused step \(|^MLP weight|^adam" \
            | tee -a "$out/mlp_width.txt"
    done
done
python3 - "$out/mlp_width.txt" > "$out/mlp_width.md" <<'PY'
import re, sys
runs = {}
w = None
for line in open(sys.argv[1]):
    m = re.match(r"== round \d+ width (\d+)", line)
    if m:
        w = int(m.group(1))
        runs.setdefault(w, []).append({})
        continue
    if w is None:
        continue
    for stage, pat in [("fused kernel ms", r"^fused step \("), ("weight gradients ms", r"^MLP weight"),
                       ("adam ms", r"^adam")]:
        if re.match(pat, line):
            runs[w][-1][stage] = float(line.split()[-3])
print("256 rays x 32 samples, 2^17 table (tools/bench_mlp_width.sh); GPU ms of one profiled step\n")
print("| hidden width | fused kernel ms (each round) | best | weight gradients ms (best) | adam ms (best) |")
print("|---|---|---|---|---|")
for w in sorted(runs, reverse=True):
    f = [r["fused kernel ms"] for r in runs[w] if "fused kernel ms" in r]
    g = [r["weight gradients ms"] for r in runs[w] if "weight gradients ms" in r]
    a = [r["adam ms"] for r in runs[w] if "adam ms" in r]
    print(f"| {w} | {', '.join(f'{x:.4g}' for x in f)} | {min(f):.4g} | {min(g):.4g} | {min(a):.4g} |")
PY
cat "$out/mlp_width.md"
