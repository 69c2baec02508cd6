#!/usr/bin/env bash
# Issue 52: what each `train --depth` buys at a fixed step count.
#   synth2 (extrapolation split: 6 central views train, 8 outside held out): --depth none, mvs,
#     and the exact maps of ../shared/data/synth2/depth; each run is then scored by `eval` over
#     the held-out views' whole images and over the visible / not-visible pixels of
#     ../shared/data/synth2/gt_visibility.
#   fern17 (few-shot, held-out views 0, 8, 16): --depth sparse (the COLMAP points: what
#     c85d100's baselines used) and auto (MVS depth plus the COLMAP points).
# Every run trains STEPS steps of 256 rays x 32 samples with a 2^17 table (the rest of the
# model auto-configured) through tools/curve.sh, so the curves land in results/curves/SCENE/
# depth_VARIANT.*; the eval metrics and summary.md go to results/depth_lavapipe/.
#
# Usage: tools/depth_compare.sh [VARIANT...]   (default: all five, in the order below)
#   VARIANT: synth2_none synth2_mvs synth2_exact fern17_sparse fern17_auto, each optionally
#   with _lLAMBDA (for example synth2_mvs_l1): the same with --depth-lambda LAMBDA (default
#   0.1), _fN (synth2_mvs_f300): --mvs-fill N, and _sN (synth2_none_s2): --seed N.
#   STEPS (default 3000), EXTRANERF_BIN (default target/release/extranerf, built first).
set -euo pipefail
# One brace group, read whole before it runs: editing this file during a run cannot change it.
{
cd "$(dirname "$0")/.."
data="${EXTRANERF_DATA:-../shared/data}"
steps="${STEPS:-3000}"
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
export EXTRANERF_BIN="$bin"
out=results/depth_lavapipe
mkdir -p "$out"
variants=("$@")
[ ${#variants[@]} -gt 0 ] || variants=(synth2_none synth2_mvs synth2_exact fern17_sparse fern17_auto)
common=(--steps "$steps" --rays 256 --samples 32 --log2-table 17)
for v in "${variants[@]}"; do
    scene="${v%%_*}"; name="${v#*_}"; kind="${name%%_*}"; extra=()
    IFS=_ read -r -a opts <<< "${name#"$kind"}"
    for o in "${opts[@]}"; do
        case "$o" in
            "") ;;
            l*) extra+=(--depth-lambda "${o#l}") ;;
            f*) extra+=(--mvs-fill "${o#f}") ;;
            s*) extra+=(--seed "${o#s}") ;;
            *) echo "unknown option $o in $v" >&2; exit 2 ;;
        esac
    done
    case "$kind" in
        exact) depth="$data/synth2/depth" ;;
        none|mvs|sparse|auto) depth="$kind" ;;
        *) echo "unknown variant $v" >&2; exit 2 ;;
    esac
    case "$scene" in
        synth2) every=1500 ;;
        fern17) every=1000 ;;
        *) echo "unknown variant $v" >&2; exit 2 ;;
    esac
    echo "== $v: --depth $depth" >&2
    tools/curve.sh "$scene" "depth_$name" "$every" "${common[@]}" --depth "$depth" "${extra[@]}" >/dev/null
    run="runs/curve_${scene}_depth_${name}"
    if [ "$scene" = synth2 ]; then
        "$bin" eval "$run" --views test --lpips-nets alex \
            --visibility-masks "$data/synth2/gt_visibility" --out "$out/$v.metrics.json" >&2
    fi
done
python3 - "$out" "$steps" <<'EOF'
import json, re, sys, pathlib
out, steps = pathlib.Path(sys.argv[1]), sys.argv[2]
rows = []
order = ["synth2_none", "synth2_mvs", "synth2_exact", "fern17_sparse", "fern17_auto"]
# Any other variant run (the _lLAMBDA ones), after the five.
extra = sorted(f"{s}_{p.stem[len('depth_'):]}" for s in ["synth2", "fern17"]
               for p in pathlib.Path(f"results/curves/{s}").glob("depth_*.jsonl"))
for v in order + [e for e in extra if e not in order]:
    scene, kind = v.split("_", 1)
    curve = pathlib.Path(f"results/curves/{scene}/depth_{kind}.jsonl")
    if not curve.exists():
        continue
    last = [json.loads(l) for l in curve.read_text().splitlines() if l.strip()][-1]
    log = pathlib.Path(f"results/curves/{scene}/depth_{kind}.log").read_text()
    depth = (re.findall(r"^depth: (.*)$", log, re.M) or [None])[-1]
    m = out / f"{v}.metrics.json"
    vis = json.loads(m.read_text())["test"] if m.exists() else {}
    f = lambda x, p=2: "" if x is None else f"{x:.{p}f}"
    rows.append(f"| {v} | {depth or '?'} | {last['step']} | "
                f"{f(last.get('test_psnr'))} | {f(last.get('test_ssim'), 3)} | "
                f"{f(last.get('test_lpips_alex'), 3)} | {f(vis.get('psnr_visible'))} | "
                f"{f(vis.get('psnr_not_visible'))} |")
text = (f"# Depth supervision at a fixed step count (tools/depth_compare.sh, STEPS={steps})\n\n"
        "Held-out views at the last step (the curve's evaluation); synth2's visible and "
        "not-visible PSNR from `eval --visibility-masks ../shared/data/synth2/gt_visibility`.\n\n"
        "| variant (_lX: --depth-lambda X, _fN: --mvs-fill N, _sN: --seed N) | depth targets (train log) | step | PSNR | SSIM | LPIPS-alex | PSNR visible | PSNR not visible |\n"
        "|---|---|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n")
(out / "summary.md").write_text(text)
print(text)
EOF
exit
}
