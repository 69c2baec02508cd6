#!/usr/bin/env bash
# Build and test times as a new user meets them (docs/build-times.md): a fresh clone of REV
# (default HEAD) with a cold target folder runs README.md's main job, then the test command
# (its build and its run timed apart), then the same again warm, then a one-line change in
# engine/nerf followed by the release rebuild and tools/check.sh. With --ci it then runs .ci/run
# from another clean clone with a cold target folder of its own, then again with it warm.
# Writes OUT/times.tsv (step, seconds, exit status) and one log per step. Run it alone: the
# machine's 2 cores are the measurement.
# Usage: tools/build_times.sh OUT [REV] [--ci] [--keep]
#   --keep  leave the clones and their target folders in /tmp (their path is printed)
# Needs what .ci/run installs (lavapipe, the validation layer, EXTRANERF_INCEPTION, and for the
# tests the cooperative-matrix lavapipe: eval "$(tools/lavapipe_coop.sh)" first).
set -euo pipefail
cd "$(dirname "$0")/.."
case "${1:-}" in
    ""|-*) echo "usage: tools/build_times.sh OUT [REV] [--ci] [--keep]" >&2; exit 2 ;;
esac
out="$(realpath -m "$1")"
rev="HEAD"
ci=0
keep=0
shift
for a in "$@"; do
    case "$a" in
        --ci) ci=1 ;;
        --keep) keep=1 ;;
        *) rev="$a" ;;
    esac
done
repo="$(pwd)"
commit="$(git rev-parse "$rev")"
mkdir -p "$out"
work="$(mktemp -d /tmp/extranerf-build-times.XXXXXX)"
if [ "$keep" = 1 ]; then
    echo "build_times: working in $work (kept)" >&2
else
    trap 'rm -rf "$work"' EXIT
fi
git clone -q "$repo" "$work/clone"
git -C "$work/clone" checkout -q "$commit"
# The clone needs ../shared beside it, as the checkout has it.
ln -s "$(realpath ../shared)" "$work/shared"
tsv="$out/times.tsv"
{
    echo "# commit $commit, $(nproc) cores, $(date -u +%Y-%m-%dT%H:%MZ), $(cargo --version)"
    printf 'step\tseconds\tstatus\n'
} > "$tsv"

# step NAME DIR COMMAND...: runs COMMAND in DIR, appends its wall time and status.
step() {
    local name="$1" dir="$2"
    shift 2
    local t0 rc
    t0=$(date +%s%N)
    set +e
    (cd "$dir" && "$@") > "$out/$name.log" 2>&1
    rc=$?
    set -e
    printf '%s\t%d\t%s\n' "$name" $(( ($(date +%s%N) - t0) / 1000000000 )) "$rc" >> "$tsv"
    echo "$name: rc=$rc ($(tail -n 1 "$tsv" | cut -f2) s)" >&2
}

c="$work/clone"
export CARGO_TERM_COLOR=never
export EXTRANERF_VALIDATION=required
unset CARGO_TARGET_DIR
step cold_main_job "$c" cargo run --release -p extranerf -- demo
step cold_test_build "$c" cargo test --release --workspace --no-run
step test_run "$c" cargo test --release --workspace
du -sm "$c/target" | awk '{print "target_mib\t" $1 "\t0"}' >> "$tsv"
step warm_main_job "$c" cargo run --release -p extranerf -- demo
step warm_test_build "$c" cargo test --release --workspace --no-run
# The quick check's own first builds (clippy's check units are not the release build's), so
# that the one-line change below meets a warm target as a developer's would.
step check_first_tests "$c" tools/check.sh --no-lint optim
step clippy_cold "$c" cargo clippy --all-targets -- -D warnings
echo "// build_times.sh: a one-line change" >> "$c/engine/nerf/src/optim.rs"
step one_line_release_build "$c" cargo build --release -p extranerf
step one_line_check "$c" tools/check.sh
if [ "$ci" = 1 ]; then
    git clone -q "$repo" "$work/ci"
    git -C "$work/ci" checkout -q "$commit"
    step ci_cold "$work/ci" env CI=true EXTRANERF_CI_TARGET="$work/ci-target" bash .ci/run
    step ci_warm "$work/ci" env CI=true EXTRANERF_CI_TARGET="$work/ci-target" bash .ci/run
fi
cat "$tsv"
