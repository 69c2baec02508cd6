#!/usr/bin/env python3
"""The stage-3 enhancer of an `extrapolate` run against doing nothing (issue 18).

Runs `extranerf diffusion enhance` (stage 3's settings: strength 0.3, 10 DDIM steps) on
  - the run's own training triplets (RUN/stage3-data: corrupted renders of training views,
    scored against the photo stored with them in triplets.safetensors), and
  - the held-out views' renders of a stage-2 variant (RUN/stage2-NAME/test_*.png, halved to
    the virtual views' scale, as the enhancer was trained; scored against the photo halved
    the same way),
and prints, per image, the PSNR of the render and of its enhancement against the photo and
the enhancement's mean colour shift (and, for comparison, the mean of photo - render over all
the triplets it was trained on). An enhancer that helps raises the PSNR.

Usage: tools/enhancer_check_fern.py RUN [--bin BIN] [--triplets t000,t012] [--tests 0,9]
       [--stage2 harmonic] [--data ../shared/data/llff/fern] [--strength 0.3] [--steps 10]
Needs numpy and Pillow (pip install numpy pillow); CI does not run it.
"""
import argparse
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile

import numpy as np
from PIL import Image


def load(path):
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255.0


def save(path, img):
    Image.fromarray((np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)).save(path)


def half(img):
    h, w = img.shape[0] // 2 * 2, img.shape[1] // 2 * 2
    return img[:h, :w].reshape(h // 2, 2, w // 2, 2, 3).mean((1, 3))


def psnr(a, b):
    return -10.0 * np.log10(((a - b) ** 2).mean())


def photos(path):
    """photo_NNN tensors of triplets.safetensors, [h, w, 3] f32."""
    raw = open(path, "rb").read()
    n = struct.unpack("<Q", raw[:8])[0]
    header = json.loads(raw[8 : 8 + n])
    out = {}
    for key, v in header.items():
        if key.startswith("photo_"):
            s, e = v["data_offsets"]
            a = np.frombuffer(raw[8 + n + s : 8 + n + e], dtype=np.float32)
            out[int(key[6:])] = a.reshape(v["shape"]).astype(np.float64)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--bin", default=os.environ.get("EXTRANERF_BIN", "target/release/extranerf"))
    ap.add_argument("--triplets", default="t000,t012")
    ap.add_argument("--tests", default="0,9")
    ap.add_argument("--stage2", default="harmonic")
    ap.add_argument("--data", default="../shared/data/llff/fern")
    ap.add_argument("--strength", default="0.3", help="noise strength (stage 3's --stage3-t)")
    ap.add_argument("--steps", default="10", help="DDIM steps (stage 3's --stage3-ddim-steps)")
    a = ap.parse_args()
    data_dir = os.path.join(a.run, "stage3-data")
    model = os.path.join(a.run, "stage3-enhancer")
    for p in (data_dir, model):
        if not os.path.isdir(p):
            sys.exit(f"{p}: missing (run `extranerf extrapolate` with stage 3 first)")
    with open(os.path.join(data_dir, "triplets.json")) as f:
        triplets = {t["key"]: t for t in json.load(f)}
    truth = photos(os.path.join(data_dir, "triplets.safetensors"))
    names = sorted(os.listdir(os.path.join(a.data, "images_8")))
    work = tempfile.mkdtemp(prefix="enhancer_check_")
    rows = []

    def triplet_png(key):
        return os.path.join(data_dir, next(f for f in os.listdir(data_dir) if f.startswith(key + "_")))

    def enhance(src, label, photo):
        out = os.path.join(work, label + "_enhanced.png")
        subprocess.run(
            [a.bin, "diffusion", "enhance", "--model", model, "--image", src, "--out", out,
             "--diffusion-backend", "cpu", "--strength", a.strength, "--steps", a.steps],
            check=True, stdout=subprocess.DEVNULL,
        )
        r, e = load(src), load(out)
        shift = (e - r).mean((0, 1))
        rows.append((label, psnr(r, photo), psnr(e, photo), shift))

    for key in [k for k in a.triplets.split(",") if k]:
        t = triplets.get(key)
        if t is None:
            sys.exit(f"{data_dir}/triplets.json: no triplet {key}")
        src = triplet_png(key)
        enhance(src, f"triplet {os.path.basename(src)[:-4]}", truth[t["slot"]])
    for i in [int(k) for k in a.tests.split(",") if k]:
        render = load(os.path.join(a.run, f"stage2-{a.stage2}", f"test_{i:03}.png"))
        src = os.path.join(work, f"test_{i:03}.png")
        save(src, half(render))
        # The photo goes through the same 8-bit PNG as the render.
        gt = os.path.join(work, f"test_{i:03}_photo.png")
        save(gt, half(load(os.path.join(a.data, "images_8", names[i]))))
        enhance(src, f"held-out view {i} (stage2-{a.stage2}, halved)", load(gt))
    # What the enhancer was trained to add on average: photo - render over all its triplets.
    diffs = []
    for key, t in sorted(triplets.items()):
        diffs.append((truth[t["slot"]] - load(triplet_png(key))).mean((0, 1)))
    d = np.mean(diffs, 0)
    shutil.rmtree(work)
    print(f"enhancer {model}, strength {a.strength}, {a.steps} DDIM steps")
    print(f"photo - render over its {len(diffs)} triplets: {d[0]:+.4f}, {d[1]:+.4f}, {d[2]:+.4f}")
    print("| image | PSNR render | PSNR enhanced | mean shift (r, g, b) |")
    print("|---|---|---|---|")
    for label, pr, pe, s in rows:
        print(f"| {label} | {pr:.2f} | {pe:.2f} | {s[0]:+.4f}, {s[1]:+.4f}, {s[2]:+.4f} |")


if __name__ == "__main__":
    main()
