#!/usr/bin/env bash
# Checks an extrapolate run's RUN/report.html (written by `extranerf eval RUN`) in headless
# Chromium, with the network off: the page's DOM after loading must hold every image as a
# decoded data URI (no broken image, nothing fetched), and a full-page screenshot
# (OUT.png) must show rendered images, not a blank page.
#
# Usage: tools/report_check.sh RUN OUT.png
#   Needs chromium (Debian: apt-get install chromium) and python3 (standard library only).
set -euo pipefail
[ $# -eq 2 ] || { sed -n 2,9p "$0"; exit 2; }
run="$1"; shot="$2"
page="$(realpath "$run/report.html")"
[ -f "$page" ] || { echo "$run/report.html missing: run \`extranerf eval $run\` first" >&2; exit 1; }
browser=$(command -v chromium || command -v chromium-browser || true)
[ -n "$browser" ] || { echo "chromium not found (apt-get install chromium)" >&2; exit 1; }
profile=$(mktemp -d)
trap 'rm -rf "$profile"' EXIT
flags=(--headless --no-sandbox --disable-gpu --user-data-dir="$profile"
       --proxy-server=127.0.0.1:9 --proxy-bypass-list='<-loopback>' --hide-scrollbars)
# Image completeness, evaluated in the page: width > 0 once decoded.
cat > "$profile/probe.html" <<EOF
<!DOCTYPE html><html><body><iframe id="f" src="file://$page" style="width:1400px;height:1000px"></iframe>
<script>
document.getElementById('f').onload = () => {
  const d = document.getElementById('f').contentDocument;
  const imgs = [...d.images];
  const bad = imgs.filter(i => !(i.complete && i.naturalWidth > 0) || !i.src.startsWith('data:'));
  document.body.setAttribute('data-result', 'images=' + imgs.length + ' broken=' + bad.length +
    ' tables=' + d.querySelectorAll('table').length);
};
</script></body></html>
EOF
dom=$("$browser" "${flags[@]}" --allow-file-access-from-files --virtual-time-budget=20000 \
      --dump-dom "file://$profile/probe.html" 2>/dev/null)
result=$(printf '%s' "$dom" | grep -o 'data-result="[^"]*"' | head -1 | cut -d'"' -f2)
echo "report.html in $(basename "$browser"): $result"
case "$result" in
    images=0*|"") echo "no images rendered" >&2; exit 1 ;;
    *" broken=0 "*) ;;
    *) echo "broken images in the report" >&2; exit 1 ;;
esac
"$browser" "${flags[@]}" --window-size=1400,3000 --screenshot="$(realpath -m "$shot")" \
    "file://$page" 2>/dev/null
python3 - "$shot" <<'EOF'
import struct, sys, zlib
data = open(sys.argv[1], 'rb').read()
assert data[:8] == b'\x89PNG\r\n\x1a\n', 'not a PNG'
pos, idat, w, h = 8, b'', 0, 0
while pos < len(data):
    n, kind = struct.unpack('>I4s', data[pos:pos + 8])
    body = data[pos + 8:pos + 8 + n]
    if kind == b'IHDR':
        w, h = struct.unpack('>II', body[:8])
    elif kind == b'IDAT':
        idat += body
    pos += 12 + n
raw = zlib.decompress(idat)
distinct = len(set(raw))
print(f'screenshot {sys.argv[1]}: {w}x{h}, {distinct} distinct byte values')
if distinct < 64:
    sys.exit('the screenshot looks blank')
EOF
