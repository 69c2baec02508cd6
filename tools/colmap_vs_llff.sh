#!/usr/bin/env bash
# Issue 57's target: fern read as a COLMAP capture trains to the held-out PSNR of fern read as
# LLFF. `extranerf export` writes fern 8x as a COLMAP text model (PINHOLE camera, poses in
# COLMAP's world, its real points3D) under runs/fern_colmap; both scenes then train the same
# steps with the same flags (tools/curve.sh fern17 and fern17colmap: views 0, 8, 16 held out,
# the other 17 train, sparse depth), and the last evaluation of each is compared.
#
# Usage: tools/colmap_vs_llff.sh [STEPS] [train flags...]   (STEPS default 3000)
# Writes results/curves/{fern17,fern17colmap}/colmap_vs_llff_sSTEPS.* and
# results/colmap_vs_llff_sSTEPS.txt.
set -euo pipefail
{
cd "$(dirname "$0")/.."
steps="${1:-3000}"; [ $# -gt 0 ] && shift
name="colmap_vs_llff_s$steps"
cargo build --release -p extranerf >&2
# One binary for both runs, whatever is rebuilt meanwhile.
bin="runs/$name.extranerf"
mkdir -p runs
cp target/release/extranerf "$bin"
rm -rf runs/fern_colmap
"$bin" export --scene "${EXTRANERF_DATA:-../shared/data}/llff/fern" --factor 8 \
    --out runs/fern_colmap >&2
every=$((steps / 3))
EXTRANERF_BIN="$bin" tools/curve.sh fern17 "$name" "$every" --steps "$steps" "$@" >/dev/null
EXTRANERF_BIN="$bin" tools/curve.sh fern17colmap "$name" "$every" --steps "$steps" "$@" >/dev/null
out="results/colmap_vs_llff_s$steps.txt"
python3 - "$name" "$steps" "$*" > "$out" <<'PY'
import json, sys
name, steps, flags = sys.argv[1:4]
rows = {}
for scene in ("fern17", "fern17colmap"):
    with open(f"results/curves/{scene}/{name}.jsonl") as f:
        rows[scene] = [json.loads(l) for l in f if l.strip()]
print(f"fern 8x, views 0 8 16 held out, {steps} steps, flags: {flags or '(none)'}")
print(f"{'step':>6} {'LLFF PSNR':>10} {'COLMAP PSNR':>12} {'difference':>11}")
for a, b in zip(rows["fern17"], rows["fern17colmap"]):
    assert a["step"] == b["step"] and a["views"] == b["views"]
    print(f"{a['step']:>6} {a['test_psnr']:>10.3f} {b['test_psnr']:>12.3f} "
          f"{b['test_psnr'] - a['test_psnr']:>+11.3f}")
a, b = rows["fern17"][-1], rows["fern17colmap"][-1]
d = b["test_psnr"] - a["test_psnr"]
print(f"target |difference| <= 0.2 dB at step {a['step']}: "
      f"{'met' if abs(d) <= 0.2 else 'NOT met'} ({d:+.3f} dB)")
PY
cat "$out"
rm -f "$bin"
exit
}
