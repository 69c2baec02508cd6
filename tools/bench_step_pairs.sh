#!/usr/bin/env bash
# Two builds of extranerf in alternating rounds on one machine, in one session: the fused
# training step (`bench train --step fused`) at 1024 rays x 32 samples with a 2^19 table and at
# 256 x 32 with 2^17, OLD then NEW in every round. Writes OUT/bench.txt (every run's whole-step
# samples/s and the GPU milliseconds of its profiled step's stages) and OUT/summary.md (each
# figure per round, the medians, and the ratio of the best runs: on a shared machine noise only
# slows a run down, by up to 2x here from one minute to the next).
#
# Usage: [OLD_FLAGS=...] [NEW_FLAGS=...] tools/bench_step_pairs.sh OLD_BIN NEW_BIN [ROUNDS] [OUT] [RUN]
#   OLD_FLAGS, NEW_FLAGS: more `bench train` flags for each side, so that one binary can be
#   compared with itself under two settings (e.g. NEW_FLAGS="--adam sparse").
#   ROUNDS: default 8; OUT: default results/step_pairs_lavapipe; RUN: a trained run folder
#   (fern 8x), whose test views 4 and 15 (504x378) each build also renders every round
#   (`render RUN --views 4,15`, the fused march at the run's samples per ray).
# An older commit's binary, for example:
#   git worktree add /tmp/old REV && (cd /tmp/old && cargo build --release -p extranerf) &&
#   cp "${CARGO_TARGET_DIR:-/tmp/old/target}/release/extranerf" /tmp/extranerf-old
# (build the new one after copying the old, when both share a CARGO_TARGET_DIR).
set -euo pipefail
cd "$(dirname "$0")/.."
if [ $# -lt 2 ]; then
    echo "usage: tools/bench_step_pairs.sh OLD_BIN NEW_BIN [ROUNDS] [OUT] [RUN]" >&2
    exit 2
fi
old="$1"
new="$2"
rounds="${3:-8}"
out="${4:-results/step_pairs_lavapipe}"
run="${5:-}"
for b in "$old" "$new"; do
    if [ ! -x "$b" ]; then
        echo "$b: not an executable extranerf binary" >&2
        exit 2
    fi
done
mkdir -p "$out"
: > "$out/bench.txt"
for r in $(seq "$rounds"); do
    for which in old new; do
        bin="$old"
        flags="${OLD_FLAGS:-}"
        [ "$which" = new ] && bin="$new" && flags="${NEW_FLAGS:-}"
        for cfg in "1024 19" "256 17"; do
            set -- $cfg
            echo "== round $r build $which rays $1 table 2^$2" | tee -a "$out/bench.txt"
            # shellcheck disable=SC2086 # the flags are words
            "$bin" bench train --step fused --rays "$1" --samples 32 --log2-table "$2" \
                --steps 12 $flags 2>&1 \
                | grep -E "^device:|^fused step|^MLP weight|^adam|^zero grad|^sparse Adam" \
                | tee -a "$out/bench.txt"
        done
        if [ -n "$run" ]; then
            echo "== round $r build $which render" | tee -a "$out/bench.txt"
            "$bin" render "$run" --views 4,15 --out "${TMPDIR:-/tmp}/step_pairs_render_$which" 2>&1 \
                | grep -E "^rendered" | tee -a "$out/bench.txt"
        fi
    done
done
python3 - "$out/bench.txt" "$old" "$new" "${OLD_FLAGS:-}" "${NEW_FLAGS:-}" > "$out/summary.md" <<'PY'
import re, statistics, sys
path, old, new, old_flags, new_flags = sys.argv[1:6]
runs = {}
renders = {}
key = None
for line in open(path):
    m = re.match(r"== round (\d+) build (\S+) render", line)
    if m:
        key = None
        rk = m.group(2)
        continue
    m = re.match(r"rendered .* in ([\d.]+) s", line)
    if m:
        renders.setdefault(rk, []).append(float(m.group(1)))
        continue
    m = re.match(r"== round (\d+) build (\S+) rays (\d+) table 2\^(\d+)", line)
    if m:
        key = (m.group(2), f"{m.group(3)} x 32, 2^{m.group(4)}")
        runs.setdefault(key, []).append({})
        continue
    if key is None:
        continue
    cur = runs[key][-1]
    m = re.search(r"^fused step[^:]*: [\d.]+ ms wall per step.*?([\d.e+]+) samples/s", line)
    if m:
        cur["samples/s"] = float(m.group(1))
    for stage, pat in [("fused kernel ms", r"^fused step \("), ("weight gradients ms", r"^MLP weight"),
                       ("adam ms", r"^adam"), ("zero gradients ms", r"^zero grad")]:
        if re.match(pat, line):
            cur[stage] = float(line.split()[-3])
print(f"old: `{old} {old_flags}`, new: `{new} {new_flags}`; alternating rounds, one session "
      "(tools/bench_step_pairs.sh)\n")
cfgs = list(dict.fromkeys(k[1] for k in runs))
for c in cfgs:
    print(f"### {c}\n")
    print("| figure | old (each round) | new (each round) | old median | new median | new / old "
          "(medians) | new / old (best of each) |")
    print("|---|---|---|---|---|---|---|")
    for fig in ["samples/s", "fused kernel ms", "weight gradients ms", "adam ms", "zero gradients ms"]:
        o = [r[fig] for r in runs.get(("old", c), []) if fig in r]
        n = [r[fig] for r in runs.get(("new", c), []) if fig in r]
        if not o or not n:
            continue
        mo, mn = statistics.median(o), statistics.median(n)
        # Noise here only slows a run down: the best run of each build is the other estimate.
        best = (max(n) / max(o)) if fig == "samples/s" else (min(n) / min(o))
        print(f"| {fig} | {', '.join(f'{x:.4g}' for x in o)} | {', '.join(f'{x:.4g}' for x in n)} "
              f"| {mo:.4g} | {mn:.4g} | {mn / mo:.3f} | {best:.3f} |")
    print()
if renders:
    o, n = renders.get("old", []), renders.get("new", [])
    print("### render, s per 504x378 view (views 4 and 15, every round)\n")
    print("| old | new | old median | new median | new / old (medians) |")
    print("|---|---|---|---|---|")
    if o and n:
        mo, mn = statistics.median(o), statistics.median(n)
        print(f"| {', '.join(f'{x:.2f}' for x in o)} | {', '.join(f'{x:.2f}' for x in n)} | {mo:.2f} "
              f"| {mn:.2f} | {mn / mo:.3f} |")
PY
cat "$out/summary.md"
