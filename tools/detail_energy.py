#!/usr/bin/env python3
"""Detail energy of PNG images: the mean squared discrete Laplacian (4 x centre minus the 4
neighbours) over interior pixels and RGB channels, on values in [0, 1]; the same measure as
stage 3's per-round `detail energy xR` (extranerf_extrapolate::stage3::detail_energy).

With --ref IMAGE each line also gives the ratio to that image's energy and the MSE against it.

Usage: tools/detail_energy.py [--ref PHOTO.png] IMAGE.png...
Needs numpy and Pillow (`pip install numpy pillow`).
"""
import argparse
import sys

try:
    import numpy as np
    from PIL import Image
except ImportError as e:  # pragma: no cover - a missing package is reported, not traced
    sys.exit(f"detail_energy.py needs numpy and Pillow ({e}); pip install numpy pillow")


def load(path):
    try:
        return np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255.0
    except OSError as e:
        sys.exit(f"{path}: cannot read the image ({e})")


def energy(a):
    if a.shape[0] < 3 or a.shape[1] < 3:
        return 0.0
    lap = (
        4 * a[1:-1, 1:-1]
        - a[:-2, 1:-1]
        - a[2:, 1:-1]
        - a[1:-1, :-2]
        - a[1:-1, 2:]
    )
    return float((lap * lap).mean())


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--ref", help="a reference image (e.g. the photo) of the same size")
    p.add_argument("images", nargs="+")
    a = p.parse_args()
    ref = load(a.ref) if a.ref else None
    eref = energy(ref) if ref is not None else None
    for path in a.images:
        img = load(path)
        e = energy(img)
        line = f"{path}: {img.shape[1]}x{img.shape[0]} detail energy {e:.5f}"
        if ref is not None:
            if ref.shape != img.shape:
                sys.exit(f"{path}: {img.shape[1]}x{img.shape[0]}, the reference is {ref.shape[1]}x{ref.shape[0]}")
            mse = float(((img - ref) ** 2).mean())
            line += f", {e / eref:.3f} x the reference's, MSE {mse:.5f}"
        print(line)


if __name__ == "__main__":
    main()
