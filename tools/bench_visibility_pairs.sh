#!/usr/bin/env bash
# Two builds of extranerf in alternating rounds of `bench visibility RUN --downscale 16` (the
# run's first held-out view at 1/16 resolution, exact segment march and transmittance volumes
# for 1-6 training cameras), OLD then NEW in every round, into OUT/visibility.txt, with the
# march's milliseconds per view at 6 cameras per round and their medians in OUT/visibility.md.
# Usage: tools/bench_visibility_pairs.sh OLD_BIN NEW_BIN RUN [ROUNDS] [OUT]
#   ROUNDS: default 3; OUT: default results/step_pairs_lavapipe.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ $# -lt 3 ]; then
    echo "usage: tools/bench_visibility_pairs.sh OLD_BIN NEW_BIN RUN [ROUNDS] [OUT]" >&2
    exit 2
fi
old="$1"; new="$2"; run="$3"; rounds="${4:-3}"; out="${5:-results/step_pairs_lavapipe}"
for b in "$old" "$new"; do
    [ -x "$b" ] || { echo "$b: not an executable extranerf binary" >&2; exit 2; }
done
[ -d "$run" ] || { echo "$run: no such run folder" >&2; exit 2; }
mkdir -p "$out"
: > "$out/visibility.txt"
for r in $(seq "$rounds"); do
    for which in old new; do
        bin="$old"
        [ "$which" = new ] && bin="$new"
        echo "== round $r build $which" | tee -a "$out/visibility.txt"
        "$bin" bench visibility "$run" --downscale 16 2>&1 | tee -a "$out/visibility.txt"
    done
done
python3 - "$out/visibility.txt" "$old" "$new" > "$out/visibility.md" <<'PY'
import re, statistics, sys
path, old, new = sys.argv[1:4]
ms = {"old": [], "new": []}
which = None
for line in open(path):
    m = re.match(r"== round \d+ build (\S+)", line)
    if m:
        which = m.group(1)
        continue
    f = line.split()
    # The exact march toward all 6 training cameras: its ms per view (fourth column).
    if which and len(f) > 3 and f[0] == "march" and f[1] == "6":
        ms[which].append(float(f[3]))
o, n = ms["old"], ms["new"]
print(f"old: `{old}`, new: `{new}` (tools/bench_visibility_pairs.sh); exact march, 6 training cameras, ms per view\n")
print("| old (each round) | new (each round) | old median | new median | new / old |")
print("|---|---|---|---|---|")
if o and n:
    print(f"| {', '.join(f'{x:.0f}' for x in o)} | {', '.join(f'{x:.0f}' for x in n)} | "
          f"{statistics.median(o):.0f} | {statistics.median(n):.0f} | "
          f"{statistics.median(n) / statistics.median(o):.3f} |")
PY
cat "$out/visibility.md"
