#!/usr/bin/env python3
"""How much of fern's held-out error a learned sharpening could remove at all (issue 18).

Fits the best linear filter (a KxK neighbourhood of the render's three channels plus a constant,
per output channel, least squares with a small ridge) that maps renders to photos, and reports
the PSNR it reaches against doing nothing:
  1. fitted on the enhancer's training triplets (RUN/stage3-data) of every training view but
     one and scored on that view's triplets (what the enhancer could learn, and whether it
     carries to a view it did not see);
  2. fitted on all the triplets and scored on the held-out views' renders of a stage-2 variant
     (RUN/stage2-NAME/test_*.png, halved to the virtual views' scale as stage 3 sees them);
  3. the oracle: fitted on those held-out renders and their own photos (no filter of that
     size can do better on them).
A filter is a crude enhancer, but one that the triplets teach and that cannot add noise: where
even the oracle gains little, the held-out error is not blur that sharpening removes.

Usage: tools/enhancer_bound_fern.py RUN [--k 5] [--stage2 harmonic] [--data ../shared/data/llff/fern]
Needs numpy and Pillow; CI does not run it.
"""
import argparse
import json
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from enhancer_check_fern import half, load, photos, psnr  # noqa: E402


def features(img, k):
    r = k // 2
    p = np.pad(img, ((r, r), (r, r), (0, 0)), mode="edge")
    h, w, _ = img.shape
    cols = [p[i : i + h, j : j + w] for i in range(k) for j in range(k)]
    return np.concatenate(cols + [np.ones((h, w, 1))], 2).reshape(h * w, -1)


def fit(pairs, ridge=1e-3):
    a = sum(x.T @ x for x, _ in pairs)
    b = sum(x.T @ y for x, y in pairs)
    n = a.shape[0]
    return np.linalg.solve(a + ridge * np.trace(a) / n * np.eye(n), b)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--k", type=int, default=5, help="filter side (odd)")
    ap.add_argument("--stage2", default="harmonic")
    ap.add_argument("--data", default="../shared/data/llff/fern")
    a = ap.parse_args()
    data_dir = os.path.join(a.run, "stage3-data")
    test_dir = os.path.join(a.run, f"stage2-{a.stage2}")
    for p in (data_dir, test_dir):
        if not os.path.isdir(p):
            sys.exit(f"{p}: missing (run `extranerf extrapolate` with stage 3 first)")
    with open(os.path.join(data_dir, "triplets.json")) as f:
        triplets = json.load(f)
    truth = photos(os.path.join(data_dir, "triplets.safetensors"))
    files = {f[:4]: f for f in os.listdir(data_dir) if f.startswith("t") and f.endswith(".png")}
    items = []
    for t in triplets:
        render = load(os.path.join(data_dir, files[t["key"]]))
        items.append((t["slot"], t["source"], features(render, a.k), truth[t["slot"]].reshape(-1, 3), render))
    views = sorted({s for s, *_ in items})
    print(f"{a.k}x{a.k} linear filter, {len(items)} triplets of {len(views)} training views, {a.run}")
    print()
    print("| training view left out | source | PSNR render | PSNR filtered |")
    print("|---|---|---|---|")
    for v in views:
        w = fit([(x, y) for s, _, x, y, _ in items if s != v])
        for s, src, x, y, r in items:
            if s == v:
                out = np.clip(x @ w, 0.0, 1.0)
                print(f"| {v} | {src} | {psnr(r.reshape(-1, 3), y):.2f} | {psnr(out, y):.2f} |")
    w_all = fit([(x, y) for _, _, x, y, _ in items])
    names = sorted(os.listdir(os.path.join(a.data, "images_8")))
    tests = []
    for f in sorted(os.listdir(test_dir)):
        if f.startswith("test_") and f.endswith(".png"):
            i = int(f[5:8])
            r = half(load(os.path.join(test_dir, f)))
            g = half(load(os.path.join(a.data, "images_8", names[i])))
            tests.append((i, features(r, a.k), g.reshape(-1, 3), r))
    w_oracle = fit([(x, y) for _, x, y, _ in tests])
    print()
    print(f"| held-out view (stage2-{a.stage2}, halved) | PSNR render | fitted on the triplets | oracle |")
    print("|---|---|---|---|")
    gains = []
    for i, x, y, r in tests:
        base = psnr(r.reshape(-1, 3), y)
        t = psnr(np.clip(x @ w_all, 0.0, 1.0), y)
        o = psnr(np.clip(x @ w_oracle, 0.0, 1.0), y)
        gains.append((t - base, o - base))
        print(f"| {i} | {base:.2f} | {t:.2f} | {o:.2f} |")
    g = np.mean(gains, 0)
    print(f"| mean gain | | {g[0]:+.2f} dB | {g[1]:+.2f} dB |")


if __name__ == "__main__":
    main()
