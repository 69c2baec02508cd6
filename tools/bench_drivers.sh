#!/usr/bin/env bash
# The training step under each lavapipe build, in one session, alternating: the system's driver
# (bookworm-backports' Mesa 25.0.7, LLVM 15) and the one tools/build_lavapipe.sh built (selected
# with VK_DRIVER_FILES), each at lavapipe's default SIMD width and with LP_NATIVE_VECTOR_WIDTH=512
# (16 lanes on AVX-512). Runs `bench train --step fused` at 1024 rays x 32 samples with a 2^19
# table and at 256 x 32 with 2^17, ROUNDS times (default 2), and writes
# results/drivers_lavapipe/{bench.txt,summary.md}.
# Usage: tools/bench_drivers.sh [ROUNDS]
set -euo pipefail
cd "$(dirname "$0")/.."
rounds="${1:-2}"
bin="${CARGO_TARGET_DIR:-target}/release/extranerf"
cargo build --release -p extranerf >&2
built="$(tools/build_lavapipe.sh --print)" || {
    echo "no lavapipe built by tools/build_lavapipe.sh: run it first" >&2
    exit 1
}
out=results/drivers_lavapipe
mkdir -p "$out"
: > "$out/bench.txt"
drivers=(system system512 built built512)
run() {
    local d="$1"; shift
    case "$d" in
        system) env -u VK_DRIVER_FILES -u LP_NATIVE_VECTOR_WIDTH "$bin" "$@" ;;
        system512) env -u VK_DRIVER_FILES LP_NATIVE_VECTOR_WIDTH=512 "$bin" "$@" ;;
        built) env -u LP_NATIVE_VECTOR_WIDTH VK_DRIVER_FILES="$built" "$bin" "$@" ;;
        built512) env VK_DRIVER_FILES="$built" LP_NATIVE_VECTOR_WIDTH=512 "$bin" "$@" ;;
    esac
}
for r in $(seq "$rounds"); do
    for d in "${drivers[@]}"; do
        for cfg in "1024 19" "256 17"; do
            set -- $cfg
            echo "== round $r driver $d rays $1 table 2^$2" | tee -a "$out/bench.txt"
            run "$d" bench train --step fused --rays "$1" --samples 32 --log2-table "$2" \
                --steps 10 2>&1 | grep -E "device:|fused step:" | tee -a "$out/bench.txt"
        done
    done
done
# Summary: samples/s per driver and configuration, every round.
python3 - "$out/bench.txt" > "$out/summary.md" <<'PY'
import re, sys, collections
rows = collections.OrderedDict()
dev = {}
key = None
for line in open(sys.argv[1]):
    m = re.match(r"== round (\d+) driver (\S+) rays (\d+) table 2\^(\d+)", line)
    if m:
        key = (m.group(2), f"{m.group(3)} x 32, 2^{m.group(4)}")
        continue
    m = re.match(r"device: (.*)", line)
    if m and key:
        dev[key[0]] = m.group(1).strip()
    m = re.search(r"fused step: ([\d.]+) ms wall per step.*?([\d.e+]+) samples/s", line)
    if m and key:
        rows.setdefault(key, []).append(float(m.group(2)))
cfgs = list(dict.fromkeys(k[1] for k in rows))
print("| driver | device | " + " | ".join(f"{c} samples/s" for c in cfgs) + " |")
print("|---|---|" + "---|" * len(cfgs))
for d in dict.fromkeys(k[0] for k in rows):
    cells = []
    for c in cfgs:
        v = rows.get((d, c), [])
        cells.append(", ".join(f"{x:.3g}" for x in v))
    print(f"| {d} | {dev.get(d, '?')} | " + " | ".join(cells) + " |")
PY
cat "$out/summary.md"
