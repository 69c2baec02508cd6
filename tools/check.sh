#!/usr/bin/env bash
# The quick check for work in progress: formatting, clippy, and the tests that the changed files
# select, in the release profile the full suite and the main job share (docs/testing.md). The
# full suite stays README.md's test command; CI runs only that.
#
# Usage: tools/check.sh [--since REV] [--no-lint] [--list] [TARGET...]
#   TARGET      a module of the `main` test binary (gpu, prims, field, render, march, optim, train,
#               stability, split, data, fuzz, metrics, mvs, visibility, diffusion,
#               diffusion_models, enhancer, extrapolate), or cli (bin/tests/cli.rs, the command
#               line's own test binary).
#               Given targets replace the selection from changed files.
#   --since REV also select by the files changed since REV (default: only uncommitted changes,
#               tracked or new)
#   --no-lint   skip cargo fmt and clippy
#   --list      print the selection and exit
#
# Selection rule: a changed tests/NAME.rs selects NAME; a changed file of a crate or kernel family
# selects the modules in the table below (the modules that test that code directly). Every crate
# whose files changed runs its own unit tests. Nothing changed (or only docs, results and tools):
# the unit tests of every crate and the quick set `gpu prims optim`.
#
# Example: after editing engine/nerf/src/optim.rs,
#   tools/check.sh            # fmt, clippy, extranerf-nerf's unit tests, module optim
set -euo pipefail
cd "$(dirname "$0")/.."

since=""
lint=1
list=0
targets=()
while [ $# -gt 0 ]; do
    case "$1" in
        --since) since="${2:?--since needs a revision}"; shift 2 ;;
        --no-lint) lint=0; shift ;;
        --list) list=1; shift ;;
        -h|--help) sed -n '2,23p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        -*) echo "check.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
        *) targets+=("$1"); shift ;;
    esac
done

# The modules of the test binary `main`, as tests/main.rs declares them.
main_modules=" $(sed -n 's/^mod \([a-z0-9_]*\);$/\1/p' tests/main.rs | tr '\n' ' ')"
own_binaries=" cli "

# Changed path -> integration targets that test it directly (first match wins).
targets_of() {
    case "$1" in
        tests/support.rs|tests/main.rs|tests/Cargo.toml) echo "gpu prims optim" ;;
        tests/*.rs) basename "$1" .rs ;;
        tests/fixtures/diffusers_tiny/*) echo "diffusion_models diffusion" ;;
        tests/fixtures/inception*) echo "metrics" ;;
        bin/*) echo "cli" ;;
        engine/gpu/*) echo "gpu prims" ;;
        engine/prims/*|kernels/wgsl/prims/*) echo "prims" ;;
        kernels/wgsl/common/*|kernels/build.rs|kernels/src/*|kernels/Cargo.toml)
            echo "prims field render march train proposal" ;;
        engine/nerf/src/field/proposal.rs) echo "proposal" ;;
        kernels/wgsl/field/*|engine/nerf/src/field/*) echo "field proposal" ;;
        kernels/wgsl/render/visibility.wgsl|engine/nerf/src/render/visibility.rs) echo "visibility" ;;
        kernels/wgsl/render/train_step*|engine/nerf/src/render/train_step.rs|engine/nerf/src/trainer.rs)
            echo "train proposal" ;;
        kernels/wgsl/render/proposal.wgsl|engine/nerf/src/render/proposal.rs) echo "proposal" ;;
        kernels/wgsl/render/march*|engine/nerf/src/render/march.rs|engine/nerf/src/renderer.rs)
            echo "march render" ;;
        kernels/wgsl/render/occupancy.wgsl|engine/nerf/src/render/occupancy.rs) echo "render march train" ;;
        kernels/wgsl/render/*|engine/nerf/src/render/*) echo "render train" ;;
        kernels/wgsl/optim/*|engine/nerf/src/optim.rs) echo "optim" ;;
        kernels/wgsl/depth/mvs.wgsl|engine/nerf/src/mvs.rs) echo "mvs" ;;
        kernels/wgsl/depth/*|engine/nerf/src/depth_completion.rs) echo "render" ;;
        engine/nerf/src/data/*|engine/nerf/src/safetensors.rs|engine/nerf/src/cameras.rs) echo "data fuzz" ;;
        engine/nerf/src/metrics/*) echo "metrics" ;;
        engine/nerf/src/reference.rs) echo "field render proposal" ;;
        engine/nerf/src/*) echo "train stability" ;;
        engine/diffusion/src/device.rs) echo "diffusion" ;;
        engine/diffusion/src/enhancer.rs) echo "enhancer diffusion_models" ;;
        engine/diffusion/*) echo "diffusion_models" ;;
        engine/extrapolate/src/visibility.rs) echo "visibility" ;;
        engine/extrapolate/src/inception.rs|engine/extrapolate/src/eval.rs) echo "metrics" ;;
        engine/extrapolate/src/stage3.rs) echo "extrapolate enhancer" ;;
        engine/extrapolate/src/inpaint/*) echo "extrapolate diffusion_models" ;;
        engine/extrapolate/*) echo "extrapolate" ;;
        Cargo.toml|Cargo.lock|.cargo/*) echo "gpu prims optim" ;;
        *) ;;
    esac
}

# Changed path -> the package whose unit tests it selects (extranerf-gpu and extranerf-kernels
# have none: their code is tested by the modules above).
package_of() {
    case "$1" in
        engine/prims/*) echo extranerf-prims ;;
        engine/nerf/*) echo extranerf-nerf ;;
        engine/diffusion/*) echo extranerf-diffusion ;;
        engine/extrapolate/*) echo extranerf-extrapolate ;;
        bin/*) echo extranerf ;;
        *) ;;
    esac
}

packages=()
if [ ${#targets[@]} -eq 0 ]; then
    while IFS= read -r f; do
        [ -n "$f" ] || continue
        # shellcheck disable=SC2207
        targets+=($(targets_of "$f"))
        p="$(package_of "$f")"
        if [ -n "$p" ]; then packages+=("$p"); fi
    done < <({ git diff --name-only HEAD; git ls-files --others --exclude-standard;
               if [ -n "$since" ]; then git diff --name-only "$since" HEAD; fi; } | sort -u)
    if [ ${#targets[@]} -eq 0 ] && [ ${#packages[@]} -eq 0 ]; then
        targets=(gpu prims optim)
        packages=(extranerf-prims extranerf-nerf extranerf-diffusion extranerf-extrapolate extranerf)
    fi
fi
# shellcheck disable=SC2207
targets=($(printf '%s\n' "${targets[@]}" | sort -u))
# shellcheck disable=SC2207
packages=($(printf '%s\n' "${packages[@]}" | sort -u))

filters=()
binaries=()
for t in "${targets[@]}"; do
    if [[ "$main_modules" == *" $t "* ]]; then
        filters+=("$t::")
    elif [[ "$own_binaries" == *" $t "* ]]; then
        binaries+=("$t")
    else
        echo "check.sh: no test module or binary named '$t' (see --help)" >&2
        exit 2
    fi
done

echo "check: unit tests of ${packages[*]:-no crate}; modules ${filters[*]:-none}; binaries ${binaries[*]:-none}" >&2
[ "$list" = 1 ] && exit 0

step() { echo "== $*" >&2; }
start=$(date +%s)
if [ "$lint" = 1 ]; then
    step "cargo fmt --all -- --check"
    cargo fmt --all -- --check
    step "cargo clippy --all-targets -- -D warnings"
    cargo clippy --all-targets -- -D warnings
fi

export EXTRANERF_VALIDATION="${EXTRANERF_VALIDATION:-required}"
if [ ${#packages[@]} -gt 0 ]; then
    # The binary's package is always selected: cargo unifies features over the packages a
    # command selects, and without it the engine crates would build without the features the
    # release binary gives them (clap, wgpu), a second time.
    args=(-p extranerf --bins)
    for p in "${packages[@]}"; do
        if [ "$p" != extranerf ]; then args+=(-p "$p"); fi
    done
    # --lib only with a library package selected (the binary's has none).
    if [ ${#args[@]} -gt 2 ]; then args+=(--lib); fi
    step "unit tests of ${packages[*]} (and the binary's)"
    cargo test --release "${args[@]}"
fi
if [ ${#filters[@]} -gt 0 ]; then
    # --workspace, not -p extranerf-tests: the features of the shared dependencies are then those
    # of the full build (with the test crate alone, portable-atomic loses its default features
    # and burn, wgpu and cubecl would compile again).
    step "cargo test --release --workspace --test main -- ${filters[*]}"
    cargo test --release --workspace --test main -- "${filters[@]}"
fi
for b in "${binaries[@]}"; do
    step "cargo test --release --workspace --test $b"
    cargo test --release --workspace --test "$b"
done
echo "check: passed in $(( $(date +%s) - start )) s" >&2
