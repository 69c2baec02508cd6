#!/usr/bin/env bash
# Time per training step on trained fields, in alternating rounds: each round copies each run's
# checkpoint and config to a scratch folder and resumes it for STEPS more steps (`train
# --resume`, no evaluations), taking `train`'s own "trained N steps in S s" line. A field
# that has converged renders opaque surfaces, so the uniform strata's march stops early behind
# them; the first steps of a fresh run (`bench train`, tools/proposal_pairs.sh) do not show it.
#
# Usage: [ROUNDS=3] [STEPS=60] [OUT=results/...] [EXTRANERF_BIN=...]
#        tools/trained_step_pairs.sh NAME=RUN [NAME=RUN ...]
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -ge 1 ] || { sed -n 2,9p "$0"; exit 2; }
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
rounds="${ROUNDS:-3}"; steps="${STEPS:-60}"
out="${OUT:-results/trained_step_pairs_lavapipe}"
mkdir -p "$out"
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
: > "$out/rounds.txt"
for r in $(seq 1 "$rounds"); do
    for pair in "$@"; do
        name="${pair%%=*}"; run="${pair#*=}"
        rm -rf "$scratch/$name"; mkdir -p "$scratch/$name"
        cp "$run/checkpoint.safetensors" "$run/config.json" "$scratch/$name/"
        at=$(python3 -c "import json,sys; print(json.load(open(sys.argv[1]))['train']['steps'])" "$run/config.json")
        line=$("$bin" train --resume --out "$scratch/$name" --steps $((at + steps)) 2>&1 | grep '^trained ')
        echo "round $r $name: $line" | tee -a "$out/rounds.txt" >&2
    done
done
python3 - "$out/rounds.txt" "$steps" > "$out/summary.md" <<'PY'
import re, sys
best = {}
for l in open(sys.argv[1]):
    m = re.match(r"round (\d+) (\S+): trained (\d+) steps in ([0-9.]+) s", l)
    if m:
        ms = 1000 * float(m.group(4)) / int(m.group(3))
        best.setdefault(m.group(2), []).append(ms)
print("| run | ms per step, each round | best |\n|---|---|---|")
for k, v in best.items():
    print(f"| {k} | {', '.join(f'{x:.0f}' for x in v)} | {min(v):.0f} |")
PY
cat "$out/summary.md"
