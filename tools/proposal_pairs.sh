#!/usr/bin/env bash
# Issue 53: the time per training step of the uniform sampler and of proposal-sampler settings,
# in alternating rounds with one binary on one machine (machine speed drifts by up to 2x from
# minute to minute here, so every round runs every setting once, in turn). Each run is
# `bench train --step fused --mlp scalar` on fern 8x at fern few-shot 17's auto-configured
# model (10 levels, 2^19 table, finest resolution 687) and RAYS rays per step.
# Writes OUT/bench.txt (every run's output) and OUT/summary.md (ms per step per round, the
# median and the best of each setting, and each against the uniform sampler's).
#
# Usage: [ROUNDS=3] [STEPS=30] [RAYS=1024] [OUT=results/proposal_pairs_lavapipe]
#        [EXTRANERF_BIN=...] tools/proposal_pairs.sh [SETTING...]
#   SETTING: uniform_K (K samples per ray) or proposal_P_K (P proposal strata, K samples);
#   default: uniform_32 proposal_64_32 proposal_64_16 proposal_32_16 proposal_32_8.
set -euo pipefail
# One brace group, read whole before it runs: editing this file during a run cannot change it.
{
cd "$(dirname "$0")/.."
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
rounds="${ROUNDS:-3}"
steps="${STEPS:-30}"
rays="${RAYS:-1024}"
out="${OUT:-results/proposal_pairs_lavapipe}"
settings=("$@")
[ ${#settings[@]} -gt 0 ] || settings=(uniform_32 proposal_64_32 proposal_64_16 proposal_32_16 proposal_32_8)
mkdir -p "$out"
: > "$out/bench.txt"
for r in $(seq 1 "$rounds"); do
    for s in "${settings[@]}"; do
        IFS=_ read -r kind a b <<< "$s"
        case "$kind" in
            uniform) flags=(--samples "$a") ;;
            proposal) flags=(--sampler proposal --proposal-samples "$a" --samples "$b") ;;
            *) echo "unknown setting $s" >&2; exit 2 ;;
        esac
        echo "== round $r setting $s" >> "$out/bench.txt"
        "$bin" bench train --rays "$rays" --levels 10 --log2-table 19 --max-res 687 \
            --step fused --mlp scalar --steps "$steps" "${flags[@]}" >> "$out/bench.txt" 2>&1
        echo "round $r $s done" >&2
    done
done
python3 - "$out" "$rays" "$steps" "${settings[@]}" <<'EOF'
import re, statistics, sys, pathlib
out, rays, steps, settings = pathlib.Path(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4:]
ms = {s: [] for s in settings}
cur = None
for line in (out / "bench.txt").read_text().splitlines():
    m = re.match(r"== round (\d+) setting (\S+)", line)
    if m:
        cur = m.group(2)
        continue
    m = re.search(r"([\d.]+) ms wall per step", line)
    if m and cur:
        ms[cur].append(float(m.group(1)))
base = ms.get(settings[0]) or [float("nan")]
lines = [
    f"# Time per training step by sampler (tools/proposal_pairs.sh, {rays} rays, {steps} steps a run)",
    "",
    "fern 8x, fern17's auto-configured model (10 levels, 2^19, N to 687), fused step, scalar MLPs, "
    "lavapipe on 2 cores. Each round runs every setting once, in turn; the best run is the least "
    "disturbed by the machine's other load. The time of a proposal step includes its field, "
    "resampling, interlevel loss and backward pass.",
    "",
    "| setting | ms per step, by round | median | best | best against " + settings[0] + " |",
    "|---|---|---|---|---|",
]
for s in settings:
    v = ms[s]
    if not v:
        continue
    lines.append(
        f"| {s} | {', '.join(f'{x:.0f}' for x in v)} | {statistics.median(v):.0f} | {min(v):.0f} | "
        f"{min(v) / min(base):.2f}x |"
    )
(out / "summary.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
EOF
}
