#!/usr/bin/env bash
# Issue 53: the held-out views of trained runs rendered at several sample counts per ray
# (`eval --samples N`, the fused march): uniform strata for a uniform-trained run, the samples
# its proposal field draws for a proposal-trained one. Writes OUT/RUNNAME_sN.metrics.json per
# run and count (kept: delete one to evaluate it again) and OUT/eval.md (PSNR, SSIM,
# LPIPS-alex and the checkpoint's step).
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
def sampler(cfg):
    p = cfg["model"].get("sampler", "uniform")
    return "uniform" if p == "uniform" else f"proposal, {p['proposal']['samples']} strata"
lines = [
    "# Held-out views by render sample count (tools/proposal_eval.sh)",
    "",
    "`eval RUN --views test --samples N --lpips-nets alex`, the fused march at N samples per ray: "
    "uniform strata, or the samples a proposal-trained run's proposal field draws.",
    "",
    "| run | sampler | train samples | step | render | PSNR | SSIM | LPIPS-alex |",
    "|---|---|---|---|---|---|---|---|",
]
for run in runs:
    cfg = json.loads((pathlib.Path(run) / "config.json").read_text())
    name, how = pathlib.Path(run).name, sampler(cfg)
    kind = "strata" if how == "uniform" else "proposal samples"
    for label, suffix in [(f"{s} {kind}", f"_s{s}") for s in counts]:
        t = json.loads((out / f"{name}{suffix}.metrics.json").read_text())["test"]
        lines.append(
            f"| {name} | {how} | {cfg['train']['samples']} | {step(run)} | {label} | "
            f"{t['psnr']:.2f} | {t['ssim']:.3f} | {t['lpips_alex']:.3f} |"
        )
(out / "eval.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
EOF
}
