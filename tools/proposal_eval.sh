#!/usr/bin/env bash
# Issue 53: the held-out views of trained runs rendered with uniform strata at several sample
# counts (`eval --samples N`): what a proposal-trained field learned, while the march does not
# use the proposal field yet (issue 54), against a uniform-trained run at the same counts.
# Writes OUT/RUNNAME_sN.metrics.json per run and count (kept: delete one to evaluate it again),
# and OUT/eval.md (PSNR, SSIM, LPIPS-alex and the checkpoint's step).
#
# Usage: [SAMPLES="32 128"] [OUT=results/proposal_lavapipe] [EXTRANERF_BIN=...]
#        tools/proposal_eval.sh RUN...
set -euo pipefail
# One brace group, read whole before it runs: editing this file during a run cannot change it.
{
cd "$(dirname "$0")/.."
[ $# -ge 1 ] || { sed -n 2,10p "$0"; exit 2; }
bin="${EXTRANERF_BIN:-${CARGO_TARGET_DIR:-target}/release/extranerf}"
[ -n "${EXTRANERF_BIN:-}" ] || cargo build --release -p extranerf >&2
counts="${SAMPLES:-32 128}"
out="${OUT:-results/proposal_lavapipe}"
mkdir -p "$out"
for run in "$@"; do
    for s in $counts; do
        # A run and count already evaluated (its metrics file exists) is not evaluated again.
        f="$out/$(basename "$run")_s$s.metrics.json"
        [ -f "$f" ] || "$bin" eval "$run" --views test --samples "$s" --lpips-nets alex --out "$f" >&2
    done
done
python3 - "$out" "$counts" "$@" <<'EOF'
import json, pathlib, struct, sys
out, counts, runs = pathlib.Path(sys.argv[1]), sys.argv[2].split(), sys.argv[3:]
def step(run):
    with open(pathlib.Path(run) / "checkpoint.safetensors", "rb") as f:
        n = struct.unpack("<Q", f.read(8))[0]
        return json.loads(f.read(n))["__metadata__"]["step"]
def sampler(run):
    m = json.loads((pathlib.Path(run) / "config.json").read_text())["model"]
    p = m.get("sampler", "uniform")
    return "uniform" if p == "uniform" else f"proposal, {p['proposal']['samples']} strata"
lines = [
    "# Held-out views by render sample count (tools/proposal_eval.sh)",
    "",
    "`eval RUN --views test --samples N --lpips-nets alex`: uniform strata at N samples per ray "
    "(the march does not use the proposal field yet).",
    "",
    "| run | sampler | train samples | step | render samples | PSNR | SSIM | LPIPS-alex |",
    "|---|---|---|---|---|---|---|---|",
]
for run in runs:
    cfg = json.loads((pathlib.Path(run) / "config.json").read_text())
    for s in counts:
        t = json.loads((out / f"{pathlib.Path(run).name}_s{s}.metrics.json").read_text())["test"]
        lines.append(
            f"| {pathlib.Path(run).name} | {sampler(run)} | {cfg['train']['samples']} | {step(run)} | {s} | "
            f"{t['psnr']:.2f} | {t['ssim']:.3f} | {t['lpips_alex']:.3f} |"
        )
(out / "eval.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
EOF
}
