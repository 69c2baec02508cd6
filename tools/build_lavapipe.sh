#!/usr/bin/env bash
# Builds Mesa's lavapipe (the Vulkan CPU driver, "llvmpipe" device) from Debian's `mesa` source
# package -- by default the newest one in Debian unstable -- on a Debian 12 (bookworm) machine,
# for lavapipe ONLY (no GL, no EGL/GLX/GBM, no window-system platforms, no other drivers), and
# installs it into a per-version cache directory outside the repository.
#
# Nothing on the system is replaced: only a `deb-src` entry is added to apt (never a binary
# `deb` line), so every installed package still comes from bookworm / bookworm-backports.
# Build dependencies come from bookworm (+ meson from bookworm-backports, and libdrm-dev from there
# when libdrm2 is already installed from there) and are installed with apt-get when running as
# root; otherwise each missing one is named with the command to get it. When mesa needs a newer
# glslangValidator than bookworm's, it is built from the same suite's `glslang` source.
#
# Usage:
#   tools/build_lavapipe.sh            build (or reuse the cached build) and print the export line
#   tools/build_lavapipe.sh --print    only print the ICD json path of a finished build: the
#                                      pinned version's, else the newest one in the cache (exit 1
#                                      with a message when there is none)
#
# Selecting the built driver (one variable, the Vulkan loader's standard one; bookworm's loader
# 1.3.239 supports it):
#   export VK_DRIVER_FILES=$HOME/.cache/extranerf-lavapipe/<mesa version>/share/vulkan/icd.d/lvp_icd.x86_64.json
# The script prints that exact line at the end; `export VK_DRIVER_FILES=$(tools/build_lavapipe.sh --print)`
# does the same. Unset it to go back to the system's drivers.
#
# Variables:
#   EXTRANERF_LAVAPIPE_CACHE  cache root (default $HOME/.cache/extranerf-lavapipe). The install
#                             goes to <root>/<mesa version>; sources to <root>/src, build trees to
#                             <root>/build, so a rerun after a failure resumes where it stopped.
#   EXTRANERF_MESA_VERSION    pin the Debian source version (e.g. 26.0.3-1) or the upstream one
#                             (e.g. 26.0.3). Default: the newest `mesa` in EXTRANERF_MESA_SUITE
#                             as apt's lists know it (when the mirror lacks its files, the next
#                             older version of that suite is tried, with a loud note).
#   EXTRANERF_MESA_SUITE      Debian suite for the deb-src entry (default unstable).
#   EXTRANERF_JOBS            parallel compile jobs (default 2); everything compiles at nice 19.
#   EXTRANERF_BUILD_GLSLANG   1: always build glslangValidator from the suite's `glslang` source
#                             (done anyway when mesa needs a newer one than bookworm's 12.0, as
#                             Mesa 26's lavapipe does for its BVH shaders: >= 12.2); it goes to
#                             <root>/tools/glslang-<version> and is used through meson's native file.
#
# Re-run safe: when the ICD json of the selected version (the pin, or the suite's newest version
# in apt's current lists) already exists, it is printed and the script exits 0 immediately,
# without apt or network. Delete <root>/<mesa version> to force a rebuild.
set -euo pipefail

CACHE_ROOT="${EXTRANERF_LAVAPIPE_CACHE:-$HOME/.cache/extranerf-lavapipe}"
SUITE="${EXTRANERF_MESA_SUITE:-unstable}"
PIN="${EXTRANERF_MESA_VERSION:-}"
JOBS="${EXTRANERF_JOBS:-2}"
LLVM_VER=19
LLVM_CONFIG="/usr/bin/llvm-config-${LLVM_VER}"
SYS_PYTHON=/usr/bin/python3
SRC_LIST="/etc/apt/sources.list.d/extranerf-${SUITE}-src.sources"

log() { printf '[build_lavapipe] %s\n' "$*" >&2; }
die() { printf '[build_lavapipe] ERROR: %s\n' "$*" >&2; exit 1; }

# Upstream version of a Debian version: drop the epoch and the Debian revision.
upstream_of() { local v="${1#*:}"; [[ "$v" == *-* ]] && v="${v%-*}"; printf '%s\n' "$v"; }

# ICD json of a finished install in $1 (prints nothing when there is none or it is broken).
finished_icd() {
    local dir="$1" json lib
    for json in "$dir"/share/vulkan/icd.d/lvp_icd.*.json; do
        [ -f "$json" ] || continue
        lib="$(sed -n 's/.*"library_path"[[:space:]]*:[[:space:]]*"\([^"]*\)".*/\1/p' "$json")"
        [ -n "$lib" ] && [ -f "$lib" ] && [ -f "$dir/.extranerf-complete" ] && { printf '%s\n' "$json"; return 0; }
    done
    return 0
}

# Versions of the source package $1 in $SUITE per apt's current lists, newest first (offline).
suite_versions_of() {
    apt-cache madison "$1" 2>/dev/null | awk -F'|' -v s=" $SUITE/" '$3 ~ /Sources/ && index($3, s) { gsub(/ /, "", $2); print $2 }' | sort -rV | uniq
}

# The finished ICD json of a pinned version, or else of the newest finished version in the cache.
newest_icd() {
    if [ -n "$PIN" ]; then
        finished_icd "$CACHE_ROOT/$(upstream_of "$PIN")"
        return 0
    fi
    local d best=""
    for d in "$CACHE_ROOT"/*/; do
        d="${d%/}"
        [ -n "$(finished_icd "$d")" ] || continue
        if [ -z "$best" ] || [ "$(printf '%s\n%s\n' "$(basename "$best")" "$(basename "$d")" | sort -V | tail -n1)" = "$(basename "$d")" ]; then
            best="$d"
        fi
    done
    [ -n "$best" ] && finished_icd "$best"
    return 0
}

case "${1:-}" in
    --print)
        icd="$(newest_icd)"
        [ -n "$icd" ] || die "no finished lavapipe build in $CACHE_ROOT${PIN:+ for mesa $PIN}; run tools/build_lavapipe.sh first"
        printf '%s\n' "$icd"
        exit 0 ;;
    -h|--help)
        sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'
        exit 0 ;;
    "") ;;
    *) die "unknown argument '$1' (use --print or --help)" ;;
esac

if [ -n "$PIN" ]; then
    icd="$(newest_icd)"
else
    icd="$(finished_icd "$CACHE_ROOT/$(upstream_of "$(suite_versions_of mesa | head -n1)")")"
fi
if [ -n "$icd" ]; then
    log "cached build found: $icd"
    echo "export VK_DRIVER_FILES=$icd"
    exit 0
fi

START=$(date +%s)
IS_ROOT=0; [ "$(id -u)" = 0 ] && IS_ROOT=1
mkdir -p "$CACHE_ROOT/src" "$CACHE_ROOT/build"
exec 9>"$CACHE_ROOT/.lock"
flock -n 9 || { log "another build_lavapipe.sh holds $CACHE_ROOT/.lock; waiting"; flock 9; }

export DEBIAN_FRONTEND=noninteractive

# ---------------------------------------------------------------------------------------------
# 1. deb-src entry for $SUITE (source packages only), with the mirror the system already uses.
# ---------------------------------------------------------------------------------------------
codename="$(. /etc/os-release && printf '%s' "${VERSION_CODENAME:-}")"
mirror_stanza() {
    # Prints "URIS|SIGNED_BY" of the deb822 stanza that serves the release codename itself.
    local f="/etc/apt/sources.list.d/debian.sources"
    [ -f "$f" ] || return 0
    awk -v cn="$codename" '
        function flush() { if (types ~ /(^| )deb( |$)/ && (" " suites " ") ~ (" " cn " ") && uris != "") { print uris "|" signed; found = 1; exit } types = suites = uris = signed = "" }
        /^[[:space:]]*$/ { flush(); next }
        /^[[:space:]]*#/ { next }
        /^Types:/     { sub(/^Types:[[:space:]]*/, "");     types = $0 }
        /^Suites:/    { sub(/^Suites:[[:space:]]*/, "");    suites = $0 }
        /^URIs:/      { sub(/^URIs:[[:space:]]*/, "");      uris = $0 }
        /^Signed-By:/ { sub(/^Signed-By:[[:space:]]*/, ""); signed = $0 }
        END { if (!found) flush() }' "$f"
}
have_src_entry() { [ -f "$SRC_LIST" ] || grep -Rqs "^deb-src .* $SUITE " /etc/apt/sources.list /etc/apt/sources.list.d/*.list 2>/dev/null; }

if [ "$IS_ROOT" = 1 ]; then
    IFS='|' read -r uris signed <<<"$(mirror_stanza)" || true
    if [ -z "${uris:-}" ]; then
        uris="$(awk -v cn="$codename" '$1 == "deb" && $0 ~ (" " cn " ") { for (i = 2; i <= NF; i++) if ($i ~ /^[a-z]+:\/\//) { print $i; exit } }' /etc/apt/sources.list 2>/dev/null || true)"
    fi
    [ -n "${uris:-}" ] || die "cannot find the Debian mirror for '$codename' in /etc/apt/sources.list.d/debian.sources or /etc/apt/sources.list; add a deb-src entry for '$SUITE' by hand as $SRC_LIST"
    want="Types: deb-src
URIs: $uris
Suites: $SUITE
Components: main
Signed-By: ${signed:-/usr/share/keyrings/debian-archive-keyring.gpg}"
    if [ ! -f "$SRC_LIST" ] || [ "$(cat "$SRC_LIST")" != "$want" ]; then
        log "writing $SRC_LIST (deb-src only, suite $SUITE, URIs $uris)"
        printf '%s\n' "$want" >"$SRC_LIST"
    fi
    log "apt-get update"
    apt-get update -qq || die "apt-get update failed"
else
    have_src_entry || die "no deb-src entry for '$SUITE' and not root: as root, create $SRC_LIST with 'Types: deb-src', the URIs of /etc/apt/sources.list.d/debian.sources, 'Suites: $SUITE', 'Components: main', then run apt-get update (or just run this script once as root)"
    log "not root: using the existing apt lists (no apt-get update)"
fi

# ---------------------------------------------------------------------------------------------
# 2. Pick the mesa source version and fetch + extract it into $CACHE_ROOT/src.
# ---------------------------------------------------------------------------------------------
mapfile -t suite_versions < <(suite_versions_of mesa)
[ "${#suite_versions[@]}" -gt 0 ] || die "apt knows no 'mesa' source package in suite '$SUITE' (is the deb-src entry in place and apt-get update done?)"
log "mesa source versions in $SUITE: ${suite_versions[*]}"

if [ -n "$PIN" ]; then
    candidates=()
    for v in "${suite_versions[@]}"; do
        if [ "$v" = "$PIN" ] || { [[ "$PIN" != *-* ]] && [ "$(upstream_of "$v")" = "$PIN" ]; }; then candidates+=("$v"); fi
    done
    [ "${#candidates[@]}" -gt 0 ] || die "EXTRANERF_MESA_VERSION=$PIN is not in $SUITE (available: ${suite_versions[*]})"
    candidates=("${candidates[0]}")
else
    candidates=("${suite_versions[@]}")
fi

DEBVER=""
cd "$CACHE_ROOT/src"
for v in "${candidates[@]}"; do
    dsc="mesa_${v#*:}.dsc"
    if [ -f "$dsc" ] && [ -f ".fetched-$v" ]; then DEBVER="$v"; break; fi
    log "fetching mesa $v source (apt-get source --download-only mesa=$v)"
    if apt-get source --download-only "mesa=$v" >"fetch-$v.log" 2>&1; then
        touch ".fetched-$v"; DEBVER="$v"; break
    fi
    log "could not fetch mesa $v from the mirror:"; grep -E '^E:' "fetch-$v.log" | head -n 4 >&2 || true
    if [ -n "$PIN" ]; then die "fetching pinned mesa $v failed (see $CACHE_ROOT/src/fetch-$v.log)"; fi
    [ "$v" = "${candidates[-1]}" ] || log "trying the next older version of $SUITE"
done
[ -n "$DEBVER" ] || die "none of the mesa versions in $SUITE (${candidates[*]}) could be downloaded from the configured mirror; pin one that it has with EXTRANERF_MESA_VERSION (and EXTRANERF_MESA_SUITE)"

MESA_VERSION="$(upstream_of "$DEBVER")"
PREFIX="$CACHE_ROOT/$MESA_VERSION"
SRC="$CACHE_ROOT/src/mesa-${DEBVER#*:}"
BUILD="$CACHE_ROOT/build/mesa-${DEBVER#*:}"
log "mesa version: $DEBVER (upstream $MESA_VERSION) -> $PREFIX"

icd="$(finished_icd "$PREFIX")"
if [ -n "$icd" ]; then
    log "cached build found: $icd"; echo "export VK_DRIVER_FILES=$icd"; exit 0
fi

if [ ! -f "$SRC/.extranerf-extracted" ]; then
    command -v dpkg-source >/dev/null || die "missing dpkg-source: apt-get install dpkg-dev"
    rm -rf "$SRC"
    log "extracting with dpkg-source -x into $SRC"
    dpkg-source -x "mesa_${DEBVER#*:}.dsc" "$SRC" >"extract-$DEBVER.log" 2>&1 || { tail -n 20 "extract-$DEBVER.log" >&2; die "dpkg-source -x failed"; }
    touch "$SRC/.extranerf-extracted"
fi
SRC_VERSION="$(cat "$SRC/VERSION" 2>/dev/null || echo "$MESA_VERSION")"

# ---------------------------------------------------------------------------------------------
# 3. Build dependencies (bookworm; meson from bookworm-backports). Check, install if root.
# ---------------------------------------------------------------------------------------------
need_meson="$(sed -n "s/.*meson_version[[:space:]]*:[[:space:]]*'>=[[:space:]]*\([0-9.]*\)'.*/\1/p" "$SRC/meson.build" | head -n1)"
need_meson="${need_meson:-1.4.0}"
# Debian package | what must work for it to count as present
deps=(
    "ninja-build|command -v ninja"
    "llvm-${LLVM_VER}-dev|test -x $LLVM_CONFIG && test -n \"\$($LLVM_CONFIG --shared-mode 2>/dev/null)\""
    "python3-mako|$SYS_PYTHON -c 'import mako'"
    "python3-yaml|$SYS_PYTHON -c 'import yaml'"
    "python3-packaging|$SYS_PYTHON -c 'import packaging'"
    "bison|command -v bison"
    "flex|command -v flex"
    "glslang-tools|command -v glslangValidator"
    "pkg-config|command -v pkg-config"
    "g++|command -v c++ && command -v cc"
    "zlib1g-dev|pkg-config --exists zlib"
    "libzstd-dev|pkg-config --exists libzstd"
    "libexpat1-dev|pkg-config --exists expat"
    "libdrm-dev|pkg-config --exists libdrm"
    "xz-utils|command -v xz"
)
meson_ok() {
    command -v meson >/dev/null || return 1
    [ "$(printf '%s\n%s\n' "$need_meson" "$(meson --version)" | sort -V | head -n1)" = "$need_meson" ]
}
missing=()
for d in "${deps[@]}"; do
    pkg="${d%%|*}"; check="${d#*|}"
    bash -c "$check" >/dev/null 2>&1 || missing+=("$pkg")
done
meson_ok || missing_meson=1
if [ "${#missing[@]}" -gt 0 ] || [ -n "${missing_meson:-}" ]; then
    log "missing build dependencies: ${missing[*]}${missing_meson:+ meson>=$need_meson}"
    if [ "$IS_ROOT" != 1 ]; then
        msg="missing build dependencies and not root, so apt cannot install them:"
        [ "${#missing[@]}" -gt 0 ] && msg+=$'\n'"  ${missing[*]}  -> sudo apt-get install --no-install-recommends ${missing[*]}"
        [ -n "${missing_meson:-}" ] && msg+=$'\n'"  meson >= $need_meson (have: $(meson --version 2>/dev/null || echo none)) -> sudo apt-get install -t ${codename}-backports meson"
        die "$msg"
    fi
    if [ "${#missing[@]}" -gt 0 ]; then
        # A package whose runtime library is already installed from backports (e.g. libdrm2,
        # pulled in by mesa-vulkan-drivers from ${codename}-backports) must come from there too.
        plain=(); bpo=()
        for pkg in "${missing[@]}"; do
            if apt-get install -s -qq --no-install-recommends "$pkg" >/dev/null 2>&1; then plain+=("$pkg")
            else bpo+=("$pkg/${codename}-backports"); fi
        done
        if [ "${#plain[@]}" -gt 0 ]; then
            log "apt-get install --no-install-recommends ${plain[*]}"
            apt-get install -y -qq --no-install-recommends "${plain[@]}" || die "apt-get install ${plain[*]} failed"
        fi
        if [ "${#bpo[@]}" -gt 0 ]; then
            log "apt-get install --no-install-recommends ${bpo[*]} (to match libraries installed from ${codename}-backports)"
            apt-get install -y -qq --no-install-recommends "${bpo[@]}" || die "apt-get install ${bpo[*]} failed: install them by hand"
        fi
    fi
    if [ -n "${missing_meson:-}" ]; then
        log "apt-get install -t ${codename}-backports meson (mesa needs meson >= $need_meson)"
        apt-get install -y -qq --no-install-recommends -t "${codename}-backports" meson || die "installing meson >= $need_meson from ${codename}-backports failed (is ${codename}-backports enabled in apt?)"
    fi
    for d in "${deps[@]}"; do
        pkg="${d%%|*}"; check="${d#*|}"
        bash -c "$check" >/dev/null 2>&1 || die "build dependency $pkg still not usable after installing it (check: $check)"
    done
    meson_ok || die "meson $(meson --version 2>/dev/null) is older than the $need_meson mesa needs: apt-get install -t ${codename}-backports meson"
fi
log "build dependencies OK (meson $(meson --version), LLVM $($LLVM_CONFIG --version), ninja $(ninja --version))"

# ---------------------------------------------------------------------------------------------
# 3b. glslangValidator new enough for this mesa (bookworm has 12.0; Mesa >= 25.1 wants >= 12.2):
#     otherwise build it from the same suite's `glslang` source into <root>/tools.
# ---------------------------------------------------------------------------------------------
glslang_version() { "$1" --version 2>/dev/null | sed -n '1s/^Glslang Version: *[0-9]*://p'; }
need_glslang="$(sed -n "s/^_glslang_preamble_version *= *'\([0-9.]*\)'.*/\1/p" "$SRC/meson.build" | head -n1)"
GLSLANG="$(command -v glslangValidator)"
have_glslang="$(glslang_version "$GLSLANG")"
if [ "${EXTRANERF_BUILD_GLSLANG:-0}" = 1 ] || { [ -n "$need_glslang" ] && [ "$(printf '%s\n%s\n' "$need_glslang" "$have_glslang" | sort -V | head -n1)" != "$need_glslang" ]; }; then
    if [ -n "$need_glslang" ]; then why="mesa $MESA_VERSION needs glslangValidator >= $need_glslang"; else why="EXTRANERF_BUILD_GLSLANG=1"; fi
    log "$why, system has ${have_glslang:-none}: using glslang built from $SUITE source"
    built=""
    for d in "$CACHE_ROOT"/tools/glslang-*/bin/glslangValidator; do [ -x "$d" ] && built="$d"; done
    if [ -n "$built" ] && { [ -z "$need_glslang" ] || [ "$(printf '%s\n%s\n' "$need_glslang" "$(glslang_version "$built")" | sort -V | head -n1)" = "$need_glslang" ]; }; then
        GLSLANG="$built"
    else
        if ! command -v cmake >/dev/null; then
            [ "$IS_ROOT" = 1 ] || die "building glslang needs cmake: sudo apt-get install --no-install-recommends cmake"
            log "apt-get install --no-install-recommends cmake"
            apt-get install -y -qq --no-install-recommends cmake || die "apt-get install cmake failed"
        fi
        mapfile -t gl_versions < <(suite_versions_of glslang)
        [ "${#gl_versions[@]}" -gt 0 ] || die "apt knows no 'glslang' source package in '$SUITE'"
        gl=""
        cd "$CACHE_ROOT/src"
        for v in "${gl_versions[@]}"; do
            if [ -f ".fetched-glslang-$v" ] || apt-get source --download-only "glslang=$v" >"fetch-glslang-$v.log" 2>&1; then
                touch ".fetched-glslang-$v"; gl="$v"; break
            fi
            log "could not fetch glslang $v from the mirror"
        done
        [ -n "$gl" ] || die "none of the glslang versions in $SUITE (${gl_versions[*]}) could be downloaded; mesa $MESA_VERSION needs glslangValidator >= $need_glslang"
        gsrc="$CACHE_ROOT/src/glslang-${gl#*:}"; gbuild="$CACHE_ROOT/build/glslang-${gl#*:}"; gprefix="$CACHE_ROOT/tools/glslang-$(upstream_of "$gl")"
        if [ ! -f "$gsrc/.extranerf-extracted" ]; then
            rm -rf "$gsrc"
            # --skip-patches: Debian's patches make glslang require the system SPIRV-Tools
            # (its optimizer), which mesa does not need and bookworm's is too old for.
            dpkg-source --skip-patches -x "glslang_${gl#*:}.dsc" "$gsrc" >"extract-glslang-$gl.log" 2>&1 || { tail -n 20 "extract-glslang-$gl.log" >&2; die "dpkg-source -x glslang failed"; }
            touch "$gsrc/.extranerf-extracted"
        fi
        log "building glslang $gl (glslangValidator only) into $gprefix"
        nice -n 19 cmake -S "$gsrc" -B "$gbuild" -G Ninja -DCMAKE_BUILD_TYPE=Release \
            -DCMAKE_INSTALL_PREFIX="$gprefix" -DENABLE_OPT=OFF -DGLSLANG_TESTS=OFF -DBUILD_TESTING=OFF \
            -DENABLE_GLSLANG_BINARIES=ON -DBUILD_EXTERNAL=OFF -DBUILD_SHARED_LIBS=OFF \
            -DPython3_EXECUTABLE="$SYS_PYTHON" >"$CACHE_ROOT/build/glslang-cmake.log" 2>&1 \
            || { tail -n 30 "$CACHE_ROOT/build/glslang-cmake.log" >&2; die "cmake for glslang failed"; }
        nice -n 19 ninja -C "$gbuild" -j"$JOBS" || die "glslang build failed; rerun to resume"
        nice -n 19 ninja -C "$gbuild" install >/dev/null || die "glslang install failed"
        GLSLANG="$gprefix/bin/glslangValidator"
    fi
    [ -x "$GLSLANG" ] || die "no glslangValidator at $GLSLANG"
    if [ -n "$need_glslang" ] && [ "$(printf '%s\n%s\n' "$need_glslang" "$(glslang_version "$GLSLANG")" | sort -V | head -n1)" != "$need_glslang" ]; then
        die "$GLSLANG is $(glslang_version "$GLSLANG"), older than the $need_glslang mesa $MESA_VERSION needs"
    fi
fi
log "glslangValidator: $GLSLANG ($(glslang_version "$GLSLANG"))"

# ---------------------------------------------------------------------------------------------
# 4. Configure (lavapipe only), build at nice 19, install into $PREFIX.
# ---------------------------------------------------------------------------------------------
# /usr/bin first: a pyenv/venv python3 earlier in PATH would not see the Debian python3-mako.
export PATH="/usr/bin:/bin:$PATH"
mkdir -p "$BUILD"
native="$CACHE_ROOT/build/native-llvm${LLVM_VER}.ini"
native_text="[binaries]
llvm-config = '$LLVM_CONFIG'
python = '$SYS_PYTHON'
python3 = '$SYS_PYTHON'
glslangValidator = '$GLSLANG'"
# Rewritten only when it changes: a newer native file makes ninja regenerate the build.
[ "$(cat "$native" 2>/dev/null)" = "$native_text" ] || printf '%s\n' "$native_text" >"$native"

wanted=(
    -Dvulkan-drivers=swrast -Dgallium-drivers=llvmpipe
    -Dplatforms= -Dglx=disabled -Degl=disabled -Dgbm=disabled -Dglvnd=disabled
    -Dgles1=disabled -Dgles2=disabled -Dopengl=false
    -Dvulkan-layers= -Dtools= -Dvideo-codecs=
    -Dgallium-va=disabled -Dgallium-vdpau=disabled -Dgallium-xa=disabled -Dgallium-nine=false
    -Dgallium-opencl=disabled -Dgallium-rusticl=false -Dmicrosoft-clc=disabled
    -Dllvm=enabled -Dshared-llvm=enabled
    -Dvalgrind=disabled -Dlibunwind=disabled -Dlmsensors=disabled -Dzstd=enabled
    -Dbuild-tests=false -Dhtml-docs=disabled
)
# Keep only the options this mesa version knows (meson rejects unknown ones; they change
# between releases).
optfile="$SRC/meson.options"; [ -f "$optfile" ] || optfile="$SRC/meson_options.txt"
known="$("$SYS_PYTHON" -c 'import re,sys; print("\n".join(re.findall(r"option\(\s*[\x27\x22]([^\x27\x22]+)[\x27\x22]", open(sys.argv[1]).read())))' "$optfile")" \
    || die "cannot read mesa's options from $optfile"
opts=()
for o in "${wanted[@]}"; do
    name="${o#-D}"; name="${name%%=*}"
    if grep -qx -- "$name" <<<"$known"; then opts+=("$o"); else log "option $name not in mesa $MESA_VERSION: skipped"; fi
done
setup_args=(--prefix "$PREFIX" --libdir lib --native-file "$native" --wrap-mode nodownload
    -Dbuildtype=release -Db_ndebug=true "${opts[@]}")
stamp="$BUILD/.extranerf-setup-args"
setup_key="${setup_args[*]} $(cat "$native")"
if [ ! -f "$BUILD/build.ninja" ] || [ "$(cat "$stamp" 2>/dev/null)" != "$setup_key" ]; then
    rm -rf "$BUILD"; mkdir -p "$BUILD"
    log "meson setup ${setup_args[*]}"
    nice -n 19 meson setup "$BUILD" "$SRC" "${setup_args[@]}" || die "meson setup failed (see $BUILD/meson-logs/meson-log.txt); a missing dependency named there must be added to this script"
    printf '%s' "$setup_key" >"$stamp"
else
    log "reusing configured build tree $BUILD"
fi
log "building with nice -n 19 ninja -j$JOBS"
nice -n 19 ninja -C "$BUILD" -j"$JOBS" || die "ninja build failed; rerun to resume"
rm -rf "$PREFIX"
nice -n 19 ninja -C "$BUILD" install >"$BUILD/install.log" || { tail -n 20 "$BUILD/install.log" >&2; die "ninja install failed"; }

# ---------------------------------------------------------------------------------------------
# 5. Verify: ICD json -> existing libvulkan_lvp.so, and the loader reports the new driver.
# ---------------------------------------------------------------------------------------------
icd=""
for j in "$PREFIX"/share/vulkan/icd.d/lvp_icd.*.json; do [ -f "$j" ] && icd="$j"; done
[ -n "$icd" ] || die "no lvp_icd.*.json installed under $PREFIX/share/vulkan/icd.d"
lib="$(sed -n 's/.*"library_path"[[:space:]]*:[[:space:]]*"\([^"]*\)".*/\1/p' "$icd")"
[ -f "$lib" ] || die "$icd points to library_path '$lib', which does not exist"
if ldd "$lib" | grep -q 'not found'; then ldd "$lib" | grep 'not found' >&2; die "$lib has unresolved shared libraries"; fi
log "ICD $icd -> $lib"
if command -v vulkaninfo >/dev/null; then
    summary="$(VK_DRIVER_FILES="$icd" vulkaninfo --summary 2>&1)" || { printf '%s\n' "$summary" | tail -n 20 >&2; die "vulkaninfo --summary failed with VK_DRIVER_FILES=$icd"; }
    printf '%s\n' "$summary" | sed -n '/^Devices:/,$p' | grep -E 'apiVersion|deviceName|driverName|driverInfo' >&2
    printf '%s\n' "$summary" | grep -q "driverInfo *= *Mesa $SRC_VERSION" \
        || die "vulkaninfo does not report 'Mesa $SRC_VERSION' for VK_DRIVER_FILES=$icd"
else
    log "vulkaninfo not installed (apt-get install vulkan-tools): skipping the loader check"
fi
touch "$PREFIX/.extranerf-complete"
log "done: mesa $DEBVER lavapipe in $PREFIX ($(( ($(date +%s) - START) / 60 )) min)"
echo "export VK_DRIVER_FILES=$icd"
