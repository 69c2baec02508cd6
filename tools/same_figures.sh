#!/usr/bin/env bash
# A refactor's check against the binary before it: the demo's table from each binary (and
# from the new one twice, since training on lavapipe is not bit-reproducible), and run folders the old binary wrote, resumed by the new one: an extrapolate run
# interrupted in stage 2 (it must continue after its last finished round) and a finished one
# (every stage skipped as done).
#
# Usage: tools/same_figures.sh OLD_BIN NEW_BIN OUT
#   OLD_BIN, NEW_BIN: extranerf binaries (e.g. built from the commit before and from this one)
#   OUT: a folder for the runs (created; replaced when it holds an earlier check)
# Writes OUT/summary.txt; exits 1 when a resume does not hold or the tables' rows differ.
set -euo pipefail
[ $# -eq 3 ] || { sed -n 2,10p "$0"; exit 2; }
old="$1"; new="$2"; out="$3"
[ -x "$old" ] && [ -x "$new" ] || { echo "$old or $new is not an executable" >&2; exit 2; }
if [ -e "$out" ]; then
    [ -f "$out/summary.txt" ] || [ -d "$out/old" ] || { echo "$out exists and is not an earlier check; choose another OUT" >&2; exit 2; }
    rm -rf "$out"
fi
mkdir -p "$out"
sum="$out/summary.txt"
status=0

# 1. The demo: its table from each binary, and from the new one again. Training on lavapipe is
# not bit-reproducible (float atomics add in thread order: the same binary's loss differs in
# the 6th digit after 25 steps), so the summary sets old against new beside new against new
# again, cell by cell (the old one's run folder is reused below).
"$old" demo --out "$out/old" > "$out/old.log" 2>&1
"$new" demo --out "$out/new" > "$out/new.log" 2>&1
"$new" demo --out "$out/new2" > "$out/new2.log" 2>&1
python3 - "$out" >> "$sum" <<'PY' || status=1
import sys
out = sys.argv[1]
def table(name):
    rows = {}
    for line in open(f"{out}/{name}/extranerf/eval.md"):
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("| ") and cells[0] not in ("variant",) and not cells[0].startswith("-"):
            rows[cells[0]] = cells[1:]
    return rows
old, new, new2 = table("old"), table("new"), table("new2")
def spread(a, b):
    worst = 0.0
    for k in a:
        for x, y in zip(a[k], b.get(k, [])):
            try:
                worst = max(worst, abs(float(x.rstrip("%")) - float(y.rstrip("%"))))
            except ValueError:
                if x != y:
                    return float("inf")
    return worst
on, nn = spread(old, new), spread(new, new2)
print(f"demo: largest cell difference old/new {on:.3f}, new/new again {nn:.3f}")
for k in new:
    print(f"  {k}: old {' '.join(old.get(k, []))}")
    print(f"  {k}: new {' '.join(new[k])}")
    print(f"  {k}: new again {' '.join(new2.get(k, []))}")
# Reported, not judged: two pairs of runs say how far apart runs fall, not a bound.
sys.exit(0 if set(old) == set(new) else 1)
PY
# 2. An extrapolate run of the old binary, interrupted after stage 2's first round, resumed by
# the new one.
args=(--base "$out/old/basenerf" --inpainter harmonic --virtual 4 --rounds 3
    --steps-per-round 40 --stage3-enhancer unsharp --stage3-rounds 1
    --stage3-steps-per-round 40 --flythrough 4)
"$old" extrapolate "${args[@]}" --out "$out/interrupted" > "$out/interrupted_old.log" 2>&1 &
pid=$!
for _ in $(seq 1 600); do
    [ -f "$out/interrupted/stage2-harmonic/round.json" ] && break
    kill -0 "$pid" 2> /dev/null || break
    sleep 1
done
kill "$pid" 2> /dev/null || true
wait "$pid" 2> /dev/null || true
if [ -f "$out/interrupted/stage2-harmonic/round.json" ]; then
    echo "interrupted: old binary stopped after $(cat "$out/interrupted/stage2-harmonic/round.json")" >> "$sum"
else
    echo "interrupted: the old binary finished no stage-2 round" >> "$sum"; status=1
fi
"$new" extrapolate "${args[@]}" --out "$out/interrupted" --resume > "$out/interrupted_new.log" 2>&1 || {
    echo "interrupted: the new binary failed to resume ($out/interrupted_new.log)" >> "$sum"; status=1; }
grep -E "skipped|resuming|done in" "$out/interrupted_new.log" | sed 's/^/  new: /' >> "$sum" || true
grep -q "stage2-harmonic: resuming after round" "$out/interrupted_new.log" || {
    echo "interrupted: the new binary did not continue stage 2 from its round" >> "$sum"; status=1; }

# 3. A finished run of the old binary: the new one finds every stage done.
"$old" extrapolate "${args[@]}" --out "$out/finished" > "$out/finished_old.log" 2>&1
"$new" extrapolate "${args[@]}" --out "$out/finished" --resume > "$out/finished_new.log" 2>&1 || {
    echo "finished: the new binary refused the old run ($out/finished_new.log)" >> "$sum"; status=1; }
ran=$(grep -c "done in" "$out/finished_new.log" || true)
skipped=$(grep -c "done, skipped" "$out/finished_new.log" || true)
echo "finished: the new binary skipped $skipped stages and ran $ran" >> "$sum"
[ "$ran" -eq 0 ] && [ "$skipped" -gt 0 ] || status=1
"$new" eval "$out/finished" > "$out/finished_eval.log" 2>&1 || {
    echo "finished: eval of the old run failed ($out/finished_eval.log)" >> "$sum"; status=1; }

echo "status $status" >> "$sum"
cat "$sum"
exit "$status"
