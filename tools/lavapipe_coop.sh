#!/usr/bin/env bash
# Installs a Mesa 26 lavapipe, which offers VK_KHR_cooperative_matrix (8x8x8 tiles, f16 inputs
# with f16 or f32 accumulators), and the Khronos validation layer 1.4.309 that knows that
# extension, on Debian 12 (bookworm), into a cache folder outside the repository. Nothing on
# the system is replaced.
#
# Why binaries: Mesa 26's source files are not served by the Debian mirror these machines reach
# (tools/build_lavapipe.sh, docs/drivers.md), but Debian 13's binary packages are:
# trixie-backports' mesa-vulkan-drivers 26.1.6 (built against LLVM 19, which bookworm also has)
# and trixie's vulkan-validationlayers 1.4.309 (bookworm's 1.3.239 predates the extension and
# would reject its SPIR-V). They are fetched with apt-get from a private package list (the
# system's own mirror and keyring, signatures checked; no entry is added to the system's
# sources), checked against the SHA-256 sums below, and unpacked. Debian 13's builds need a few
# entry points that Debian 12's libraries lack: five C23 libc functions (__isoc23_strtol, ...),
# two GCC 13/14 libstdc++ ones, and four window-system functions that compute never calls.
# tools/lavapipe_coop/shim.c defines them under the symbol versions asked for, the two
# libraries load it (patchelf --add-needed, RUNPATH $ORIGIN), and their requirements of those
# versions are marked weak (tools/lavapipe_coop/elf_weak_version.py) so that the dynamic linker
# binds them to the shim. Build dependencies installed with apt-get from bookworm(-backports):
# libllvm19, libdisplay-info2, patchelf, gcc.
#
# Usage:
#   tools/lavapipe_coop.sh          install (or reuse the cached install); prints the two
#                                   export lines that select it
#   tools/lavapipe_coop.sh --print  only print them for a finished install (exit 1 without one)
#   eval "$(tools/lavapipe_coop.sh)"   selects it in the current shell
#
# Selecting it (the loader's own variables; bookworm's loader 1.3.239 supports both):
#   VK_DRIVER_FILES=<root>/share/vulkan/icd.d/lvp_icd.x86_64.json
#   VK_LAYER_PATH=<root>/share/vulkan/explicit_layer.d
# EXTRANERF_LAVAPIPE_CACHE sets the cache root (default $HOME/.cache/extranerf-lavapipe); the
# install goes to <root>/coop-26.1.6. Delete that folder to reinstall.
set -euo pipefail

MESA_VERSION="26.1.6-1~bpo13+1"
MESA_SUITE="trixie-backports"
MESA_SHA256="e2d4a843b8c55ed17c1e8856805f67b553b013b6ce5f15faeec4db7d4d38ff90"
VVL_VERSION="1.4.309.0-1"
VVL_SUITE="trixie"
VVL_SHA256="ff7e18ef011ff448ac799daf16134a676ccf9c5987e1a9f4b779611ed5fc3b0d"

HERE="$(cd "$(dirname "$0")" && pwd)"
CACHE_ROOT="${EXTRANERF_LAVAPIPE_CACHE:-$HOME/.cache/extranerf-lavapipe}"
ROOT="$CACHE_ROOT/coop-26.1.6"
ICD="$ROOT/share/vulkan/icd.d/lvp_icd.x86_64.json"
LAYERS="$ROOT/share/vulkan/explicit_layer.d"

log() { printf '[lavapipe_coop] %s\n' "$*" >&2; }
die() { printf '[lavapipe_coop] ERROR: %s\n' "$*" >&2; exit 1; }
exports() { printf 'export VK_DRIVER_FILES=%s\nexport VK_LAYER_PATH=%s\n' "$ICD" "$LAYERS"; }

if [ -f "$ROOT/.extranerf-complete" ] && [ -f "$ICD" ]; then
    exports
    exit 0
fi
[ "${1:-}" = "--print" ] && die "no finished install in $ROOT; run tools/lavapipe_coop.sh"
[ "$(uname -m)" = x86_64 ] || die "the pinned packages are for x86_64 (this is $(uname -m))"

SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"
export DEBIAN_FRONTEND=noninteractive
mkdir -p "$CACHE_ROOT"
exec 9>"$CACHE_ROOT/.coop.lock"
flock 9

# 1. Runtime libraries of the driver (bookworm, bookworm-backports) and the patching tools.
missing=()
for p in libllvm19 libdisplay-info2 patchelf gcc python3; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ]; then
    log "installing ${missing[*]}"
    $SUDO apt-get install -y -q "${missing[@]}" >&2 ||
        { $SUDO apt-get update -q >&2 && $SUDO apt-get install -y -q "${missing[@]}" >&2; } ||
        die "cannot install ${missing[*]} (libdisplay-info2 comes from bookworm-backports, as .ci/run enables it)"
fi

# 2. The two packages, from a private package list of the system's own mirror.
mirror="$(awk '/^URIs:/ { print $2; exit }' /etc/apt/sources.list.d/debian.sources 2>/dev/null || true)"
[ -n "$mirror" ] || mirror="$(awk '$1 == "deb" { for (i = 2; i <= NF; i++) if ($i ~ /^[a-z]+:\/\//) { print $i; exit } }' /etc/apt/sources.list 2>/dev/null | head -n 1)"
[ -n "$mirror" ] || die "cannot find the Debian mirror in /etc/apt/sources.list.d/debian.sources or /etc/apt/sources.list"
APT="$CACHE_ROOT/apt-coop"
mkdir -p "$APT/lists/partial" "$APT/cache/archives/partial" "$APT/debs"
printf 'deb [signed-by=/usr/share/keyrings/debian-archive-keyring.gpg] %s %s main\n' \
    "$mirror" "$MESA_SUITE" "$mirror" "$VVL_SUITE" >"$APT/sources.list"
aptp=(-o "Dir::Etc::SourceList=$APT/sources.list" -o "Dir::Etc::SourceParts=/nonexistent"
      -o "Dir::State::Lists=$APT/lists" -o "Dir::Cache=$APT/cache" -o "APT::Architecture=amd64"
      -o "APT::Architectures::=amd64" -o "Debug::NoLocking=1")
fetch() { # package version sha256
    local deb
    deb="$(ls "$APT/debs/$1"_*.deb 2>/dev/null | head -n 1 || true)"
    if [ -z "$deb" ] || [ "$(sha256sum "$deb" | cut -d' ' -f1)" != "$3" ]; then
        rm -f "$APT/debs/$1"_*.deb
        [ -f "$APT/lists.done" ] || {
            log "reading the package lists of $MESA_SUITE and $VVL_SUITE (private, in $APT)"
            apt-get "${aptp[@]}" update -q >&2 || die "apt-get update of the private list failed"
            touch "$APT/lists.done"
        }
        log "downloading $1 $2"
        (cd "$APT/debs" && apt-get "${aptp[@]}" download "$1=$2" >&2) ||
            die "cannot download $1 $2 from $mirror ($MESA_SUITE / $VVL_SUITE); the mirror may have moved on: pin a version it has"
        deb="$(ls "$APT/debs/$1"_*.deb | head -n 1)"
    fi
    local sum
    sum="$(sha256sum "$deb" | cut -d' ' -f1)"
    [ "$sum" = "$3" ] || die "$deb: SHA-256 $sum, expected $3"
    printf '%s\n' "$deb"
}
mesa_deb="$(fetch mesa-vulkan-drivers "$MESA_VERSION" "$MESA_SHA256")"
vvl_deb="$(fetch vulkan-validationlayers "$VVL_VERSION" "$VVL_SHA256")"

# 3. Unpack, add the shim, weaken the version requirements, write the manifests.
rm -rf "$ROOT"
mkdir -p "$ROOT/x" "$ROOT/lib" "$(dirname "$ICD")" "$LAYERS"
dpkg-deb -x "$mesa_deb" "$ROOT/x"
dpkg-deb -x "$vvl_deb" "$ROOT/x"
cp "$ROOT/x/usr/lib/x86_64-linux-gnu/libvulkan_lvp.so" "$ROOT/lib/"
cp "$ROOT/x/usr/lib/x86_64-linux-gnu/libVkLayer_khronos_validation.so" "$ROOT/lib/"
gcc -O2 -shared -fPIC -Wl,--version-script="$HERE/lavapipe_coop/shim.map" \
    -o "$ROOT/lib/libextranerf_shim.so" "$HERE/lavapipe_coop/shim.c" -lstdc++
weak="$HERE/lavapipe_coop/elf_weak_version.py"
python3 "$weak" "$ROOT/lib/libvulkan_lvp.so" GLIBC_2.38 >&2
for v in GLIBC_2.38 GLIBCXX_3.4.32 CXXABI_1.3.15; do
    python3 "$weak" "$ROOT/lib/libVkLayer_khronos_validation.so" "$v" >&2
done
for so in libvulkan_lvp.so libVkLayer_khronos_validation.so; do
    patchelf --add-needed libextranerf_shim.so "$ROOT/lib/$so"
    patchelf --set-rpath '$ORIGIN' "$ROOT/lib/$so"
done
unresolved="$(cd "$ROOT/lib" && for so in libvulkan_lvp.so libVkLayer_khronos_validation.so; do
    LD_BIND_NOW=1 ldd -r "./$so" 2>&1 | grep -E 'undefined symbol|not found' | grep -v 'weak version' || true
done)"
[ -z "$unresolved" ] || die "unresolved after patching:
$unresolved"
python3 - "$ROOT" "$ICD" "$LAYERS" <<'PY'
import json, sys
root, icd, layers = sys.argv[1:4]
src = json.load(open(f"{root}/x/usr/share/vulkan/icd.d/lvp_icd.json"))
src["ICD"]["library_path"] = f"{root}/lib/libvulkan_lvp.so"
json.dump(src, open(icd, "w"), indent=1)
lay = json.load(open(f"{root}/x/usr/share/vulkan/explicit_layer.d/VkLayer_khronos_validation.json"))
lay["layer"]["library_path"] = f"{root}/lib/libVkLayer_khronos_validation.so"
json.dump(lay, open(f"{layers}/VkLayer_khronos_validation.json", "w"), indent=1)
PY
rm -rf "$ROOT/x"
touch "$ROOT/.extranerf-complete"
log "installed Mesa $MESA_VERSION lavapipe and validation layer $VVL_VERSION in $ROOT"
exports
