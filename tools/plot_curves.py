#!/usr/bin/env python3
"""Plots the convergence curves of results/curves/SCENE/*.jsonl (written by tools/curve.sh)
into results/curves/SCENE.svg (held-out PSNR and LPIPS-alex against training seconds) and
prints a Markdown table of each curve's last point. Standard library only.

Usage: tools/plot_curves.py SCENE [NAME ...] [--x seconds|steps|samples|paired] [--out STEM]
                            [--ms NAME=MS ...] [--target DB]
  NAME: a curve of the scene (default: every one), or the path of a .jsonl with its
        .config.json beside it (e.g. ../shared/baselines/fern17_c85d100_steps6000.jsonl).
  --x:  the horizontal axis: training seconds (default), steps, or samples processed
        (steps x rays x samples per ray, from the run's config: equal compute whatever the
        machine's speed), or paired: steps x each curve's time per step as measured in
        alternating rounds (tools/bench_step_pairs.sh, tools/proposal_pairs.sh), given by
        --ms NAME=MS for every curve (the time to a quality on one measure, whatever the load
        while the curve ran); it also prints every point of each curve.
  --out: write results/curves/STEM.svg instead of SCENE.svg.
  --target: with --x paired, print the first point of each curve at or above DB held out.
"""
import json
import pathlib
import sys

COLOURS = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2",
           "#7f7f7f", "#bcbd22", "#17becf"]


def load(path):
    rows = [json.loads(l) for l in path.read_text().splitlines() if l.strip()]
    if not rows:
        raise SystemExit(f"{path}: no points")
    return rows


X_LABELS = {"seconds": "training seconds", "steps": "steps",
            "samples": "samples processed (millions)",
            "paired": "training seconds (steps x paired ms per step)"}


def x_of(r, axis):
    if axis == "seconds":
        return r["train_seconds"]
    if axis == "steps":
        return r["step"]
    if axis == "paired":
        return r["step"] * r["_ms"] / 1000
    return r["step"] * r["_per_step"] / 1e6


def panel(curves, key, x0, y0, w, h, label, lower_better, axis="seconds"):
    pts = [(x_of(r, axis), r[key]) for _, rows in curves for r in rows
           if r.get(key) is not None]
    if not pts:
        return ""
    xmax = max(p[0] for p in pts) * 1.05 or 1.0
    ymin = min(p[1] for p in pts)
    ymax = max(p[1] for p in pts)
    pad = (ymax - ymin) * 0.08 or 0.5
    ymin, ymax = ymin - pad, ymax + pad
    sx = lambda x: x0 + 50 + (w - 60) * x / xmax
    sy = lambda y: y0 + h - 30 - (h - 50) * (y - ymin) / (ymax - ymin)
    out = [f'<rect x="{x0 + 50}" y="{y0 + 20}" width="{w - 60}" height="{h - 50}" '
           'fill="none" stroke="#888"/>',
           f'<text x="{x0 + w / 2}" y="{y0 + 14}" text-anchor="middle" font-size="13">{label}'
           f' ({"lower" if lower_better else "higher"} is better)</text>',
           f'<text x="{x0 + w / 2}" y="{y0 + h - 4}" text-anchor="middle" font-size="11">'
           f'{X_LABELS[axis]}</text>']
    for i in range(5):
        y = ymin + (ymax - ymin) * i / 4
        out.append(f'<text x="{x0 + 46}" y="{sy(y) + 4:.1f}" text-anchor="end" '
                   f'font-size="10">{y:.3g}</text>')
        x = xmax * i / 4
        out.append(f'<text x="{sx(x):.1f}" y="{y0 + h - 16}" text-anchor="middle" '
                   f'font-size="10">{x:.4g}</text>')
    for ci, (name, rows) in enumerate(curves):
        c = COLOURS[ci % len(COLOURS)]
        p = [(sx(x_of(r, axis)), sy(r[key])) for r in rows if r.get(key) is not None]
        out.append('<polyline fill="none" stroke="%s" stroke-width="1.5" points="%s"/>'
                   % (c, " ".join(f"{x:.1f},{y:.1f}" for x, y in p)))
        for x, y in p:
            out.append(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="2.5" fill="{c}"/>')
    return "\n".join(out)


def curve(root, scene, name):
    """(label, rows) of a curve named in the scene's folder or by a .jsonl path; each row gets
    `_per_step`, the samples of one step, from the run's config."""
    path = pathlib.Path(name)
    if not name.endswith(".jsonl"):
        path = root / scene / f"{name}.jsonl"
    rows = load(path)
    cfg_path = path.with_name(path.name[:-len(".jsonl")] + ".config.json")
    per_step = None
    if cfg_path.exists():
        t = json.loads(cfg_path.read_text())["train"]
        per_step = t["rays"] * t["samples"]
    for r in rows:
        r["_per_step"] = per_step
    return path.name[:-len(".jsonl")], rows


def main():
    args = sys.argv[1:]
    axis, stem, target, ms = "seconds", None, None, {}
    while any(f in args for f in ("--x", "--out", "--ms", "--target")):
        i = next(i for i, a in enumerate(args) if a in ("--x", "--out", "--ms", "--target"))
        flag = args[i]
        if i + 1 >= len(args):
            raise SystemExit(f"{flag} needs a value")
        v = args[i + 1]
        if flag == "--x":
            axis = v
        elif flag == "--out":
            stem = v
        elif flag == "--target":
            target = float(v)
        else:
            name, _, value = v.partition("=")
            try:
                ms[name] = float(value)
            except ValueError:
                raise SystemExit(f"--ms {v}: use NAME=MS, e.g. defaults=512")
        del args[i:i + 2]
    if not args or axis not in X_LABELS:
        raise SystemExit(__doc__)
    root = pathlib.Path(__file__).resolve().parent.parent / "results" / "curves"
    scene = args[0]
    names = args[1:] or sorted(p.stem for p in (root / scene).glob("*.jsonl"))
    if not names:
        raise SystemExit(f"no curves in {root / scene}")
    curves = [curve(root, scene, n) for n in names]
    if axis == "samples":
        for n, rows in curves:
            if rows[0]["_per_step"] is None:
                raise SystemExit(f"{n}: no .config.json beside the curve to count samples")
    if axis == "paired":
        for n, rows in curves:
            if n not in ms:
                raise SystemExit(f"--x paired: give {n}'s time per step with --ms {n}=MS")
            for r in rows:
                r["_ms"] = ms[n]
    w, h = 520, 330
    legend = "\n".join(
        f'<rect x="{20 + 200 * (i % 5)}" y="{h + 12 + 18 * (i // 5)}" width="12" height="12" '
        f'fill="{COLOURS[i % len(COLOURS)]}"/><text x="{36 + 200 * (i % 5)}" '
        f'y="{h + 22 + 18 * (i // 5)}" font-size="11">{n}</text>'
        for i, (n, _) in enumerate(curves))
    rows = (len(curves) + 4) // 5
    svg = (f'<svg xmlns="http://www.w3.org/2000/svg" width="{2 * w}" height="{h + 20 + 18 * rows}" '
           'font-family="sans-serif"><rect width="100%" height="100%" fill="white"/>\n'
           + panel(curves, "test_psnr", 0, 0, w, h, f"{scene}: held-out PSNR (dB)", False, axis)
           + "\n"
           + panel(curves, "test_lpips_alex", w, 0, w, h, f"{scene}: held-out LPIPS-alex", True,
                   axis)
           + "\n" + legend + "\n</svg>\n")
    out = root / f"{stem or scene}.svg"
    out.write_text(svg)
    print(f"| {scene} | steps | train s | held-out PSNR | SSIM | LPIPS-alex | opacity | batch PSNR |")
    print("|---|---|---|---|---|---|---|---|")
    for n, rows in curves:
        r = rows[-1]
        lp = r.get("test_lpips_alex")
        print(f"| {n} | {r['step']} | {r['train_seconds']:.0f} | {r['test_psnr']:.2f} | "
              f"{r['test_ssim']:.3f} | {'-' if lp is None else f'{lp:.3f}'} | "
              f"{r['test_opacity']:.3f} | {r['batch_psnr']:.2f} |")
    if axis == "paired":
        print()
        print("| curve | ms per step (paired) | step | seconds (paired) | held-out PSNR | LPIPS-alex |")
        print("|---|---|---|---|---|---|")
        for n, rows in curves:
            for r in rows:
                lp = r.get("test_lpips_alex")
                print(f"| {n} | {ms[n]:.0f} | {r['step']} | {x_of(r, axis):.0f} | "
                      f"{r['test_psnr']:.2f} | {'-' if lp is None else f'{lp:.3f}'} |")
        if target is not None:
            print()
            print(f"| curve | first point at {target:.2f} dB or more held out | seconds (paired) |")
            print("|---|---|---|")
            for n, rows in curves:
                hit = next((r for r in rows if r["test_psnr"] >= target), None)
                print(f"| {n} | {'not reached' if hit is None else hit['step']} | "
                      f"{'-' if hit is None else f'{x_of(hit, axis):.0f}'} |")
    print(f"wrote {out}", file=sys.stderr)


if __name__ == "__main__":
    main()
