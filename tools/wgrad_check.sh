#!/usr/bin/env bash
# Issue 51's measurements of the tiled MLP weight gradient against an older build, on one
# machine, one session; writes OUT (default results/wgrad_lavapipe):
#   curves:  fern few-shot 17, 6,000 steps of 256 x 32 with a 2^17 table (the recipe's `base`),
#            held-out views every 1,000 steps, OLD and NEW side by side (quality by step count
#            does not depend on the machine's load); curves.md compares them point by point.
#            The curves and logs go to results/curves/fern17/wgrad_{old,new}_steps6000.*
#            (the scripts' own output to $TMPDIR/wgrad_curve_{old,new}.out).
#   kernels: `bench kernels --only wgrad` (the tiled GEMM and the weight gradient of the
#            field's two MLPs in the same run) with NEW, ROUNDS times -> kernels.txt.
#   pairs:   tools/bench_step_pairs.sh OLD NEW ROUNDS (the whole step's samples/s and the
#            profiled step's stage times at 1024 x 32 / 2^19 and 256 x 32 / 2^17) -> pairs/.
#   Run `pairs` and `kernels` on an otherwise idle machine; `curves` may share it.
#
# Usage: [PHASES="curves kernels pairs"] [ROUNDS=8] tools/wgrad_check.sh OLD_BIN NEW_BIN [OUT]
set -euo pipefail
cd "$(dirname "$0")/.."
if [ $# -lt 2 ]; then
    sed -n 2,16p "$0" >&2
    exit 2
fi
old="$1"
new="$2"
out="${3:-results/wgrad_lavapipe}"
rounds="${ROUNDS:-8}"
phases="${PHASES:-curves kernels pairs}"
for b in "$old" "$new"; do
    [ -x "$b" ] || { echo "$b: not an executable extranerf binary" >&2; exit 2; }
done
mkdir -p "$out"
for phase in $phases; do
    case "$phase" in
    curves)
        flags=(--steps 6000 --rays 256 --samples 32 --log2-table 17)
        EXTRANERF_BIN="$old" tools/curve.sh fern17 wgrad_old_steps6000 1000 "${flags[@]}" \
            > "${TMPDIR:-/tmp}/wgrad_curve_old.out" 2>&1 &
        pid_old=$!
        EXTRANERF_BIN="$new" tools/curve.sh fern17 wgrad_new_steps6000 1000 "${flags[@]}" \
            > "${TMPDIR:-/tmp}/wgrad_curve_new.out" 2>&1
        wait "$pid_old"
        python3 - results/curves/fern17/wgrad_old_steps6000.jsonl \
            results/curves/fern17/wgrad_new_steps6000.jsonl > "$out/curves.md" <<'PY'
import json, sys
old, new = ([json.loads(l) for l in open(p) if l.strip()] for p in sys.argv[1:3])
print("fern few-shot 17, 6,000 steps of 256 x 32, 2^17 table; held-out views 0, 8, 16 "
      "(tools/wgrad_check.sh, phase curves)\n")
print("| step | old PSNR | new PSNR | new - old dB | old SSIM | new SSIM | old LPIPS | new LPIPS |")
print("|---|---|---|---|---|---|---|---|")
worst = 0.0
for o, n in zip(old, new):
    assert o["step"] == n["step"], (o["step"], n["step"])
    d = n["test_psnr"] - o["test_psnr"]
    worst = max(worst, abs(d))
    print(f"| {o['step']} | {o['test_psnr']:.3f} | {n['test_psnr']:.3f} | {d:+.3f} "
          f"| {o['test_ssim']:.4f} | {n['test_ssim']:.4f} | {o['test_lpips_alex']:.4f} "
          f"| {n['test_lpips_alex']:.4f} |")
print(f"\nlargest |new - old|: {worst:.3f} dB over {len(old)} points")
PY
        cat "$out/curves.md"
        ;;
    kernels)
        eval "$(tools/lavapipe_coop.sh)"
        : > "$out/kernels.txt"
        for r in $(seq "$rounds"); do
            echo "== round $r" | tee -a "$out/kernels.txt"
            "$new" bench kernels --only wgrad --sizes 524288,2097152 2>&1 \
                | grep -E "^device|^gemm|^mlp weight" | tee -a "$out/kernels.txt"
        done
        ;;
    pairs)
        tools/bench_step_pairs.sh "$old" "$new" "$rounds" "$out/pairs"
        ;;
    *)
        echo "unknown phase $phase: use curves, kernels or pairs" >&2
        exit 2
        ;;
    esac
done
