#!/usr/bin/env bash
# Issue 48's third deliverable: the time per sample of each training setting that changes the
# step's work (samples per ray, rays per step, table size), so that each curve of
# tools/recipe_fern.sh can also be read against training seconds. The fused step
# (`bench train --step fused`) of fern's auto-config model (10 levels up to 687 over the fitted
# box, 2^17 unless the setting says otherwise), every setting once per round, ROUNDS rounds
# alternating on one machine in one session: the machine's speed drifts by up to 2x from one
# minute to the next, so the settings are compared round by round and by their medians. The
# learning rates and the loss do not change the step's work (the Huber loss is a few more
# operations per ray).
# 4096 x 32 does not run on lavapipe: its MLP records exceed the device's 128 MiB binding.
# Writes OUT/bench.txt (every run) and OUT/summary.md (samples/s per round, the median, and the
# median's nanoseconds per sample and ratio to base).
#
# Usage: [EXTRANERF_BIN=...] tools/bench_recipe.sh [ROUNDS] [OUT]
#   ROUNDS: default 4; OUT: default results/bench_recipe_lavapipe
set -euo pipefail
# One brace group, read whole before it runs: editing this file during a run cannot change it.
{
cd "$(dirname "$0")/.."
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
rounds="${1:-4}"
out="${2:-results/bench_recipe_lavapipe}"
# name | rays | samples | log2 table
settings="base 256 32 17
s64 256 64 17
s128 256 128 17
r1024 1024 32 17
r2048 2048 32 17
t19 256 32 19
r1024_t19 1024 32 19"
mkdir -p "$out"
: > "$out/bench.txt"
for r in $(seq "$rounds"); do
    while read -r name rays samples table; do
        # About the same samples per timed run: 48 steps of 8192 samples, fewer of more (at
        # least 12: a few steps of a large batch measured 1.1-1.4x apart from round to round).
        steps=$(( 48 * 8192 / (rays * samples) ))
        [ "$steps" -ge 12 ] || steps=12
        echo "== round $r setting $name rays $rays samples $samples table 2^$table" | tee -a "$out/bench.txt"
        "$bin" bench train --step fused --rays "$rays" --samples "$samples" --log2-table "$table" \
            --levels 10 --max-res 687 --steps "$steps" 2>&1 \
            | grep -E "^device:|^fused step.*ms wall per step" | tee -a "$out/bench.txt"
    done <<<"$settings"
done
python3 - "$out/bench.txt" > "$out/summary.md" <<'PY'
import re, statistics, sys
runs = {}
key = None
for line in open(sys.argv[1]):
    m = re.match(r"== round (\d+) setting (\S+) rays (\d+) samples (\d+) table 2\^(\d+)", line)
    if m:
        key = (m.group(2), f"{m.group(3)} x {m.group(4)}, 2^{m.group(5)}")
        continue
    m = re.search(r"^fused step[^:]*: [\d.]+ ms wall per step.*?([\d.e+]+) samples/s", line)
    if m and key:
        runs.setdefault(key, []).append(float(m.group(1)))
print("fused step, fern's auto-config model (10 levels, N up to 687), alternating rounds in one "
      "session (tools/bench_recipe.sh)\n")
print("| setting | rays x samples, table | samples/s (each round) | median | ns per sample | vs base |")
print("|---|---|---|---|---|---|")
base = statistics.median(next(v for k, v in runs.items() if k[0] == "base"))
for (name, what), v in runs.items():
    med = statistics.median(v)
    print(f"| {name} | {what} | {', '.join(f'{x:.4g}' for x in v)} | {med:.4g} | {1e9 / med:.0f} "
          f"| {med / base:.3f} |")
PY
cat "$out/summary.md"
exit
}
