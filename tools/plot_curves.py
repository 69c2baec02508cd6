#!/usr/bin/env python3
"""Plots the convergence curves of results/curves/SCENE/*.jsonl (written by tools/curve.sh)
into results/curves/SCENE.svg (held-out PSNR and LPIPS-alex against training seconds) and
prints a Markdown table of each curve's last point. Standard library only.

Usage: tools/plot_curves.py SCENE [NAME ...]   (default: every curve of the scene)
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


def panel(curves, key, x0, y0, w, h, label, lower_better):
    pts = [(r["train_seconds"], r[key]) for _, rows in curves for r in rows
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
           'training seconds</text>']
    for i in range(5):
        y = ymin + (ymax - ymin) * i / 4
        out.append(f'<text x="{x0 + 46}" y="{sy(y) + 4:.1f}" text-anchor="end" '
                   f'font-size="10">{y:.3g}</text>')
        x = xmax * i / 4
        out.append(f'<text x="{sx(x):.1f}" y="{y0 + h - 16}" text-anchor="middle" '
                   f'font-size="10">{x:.0f}</text>')
    for ci, (name, rows) in enumerate(curves):
        c = COLOURS[ci % len(COLOURS)]
        p = [(sx(r["train_seconds"]), sy(r[key])) for r in rows if r.get(key) is not None]
        out.append('<polyline fill="none" stroke="%s" stroke-width="1.5" points="%s"/>'
                   % (c, " ".join(f"{x:.1f},{y:.1f}" for x, y in p)))
        for x, y in p:
            out.append(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="2.5" fill="{c}"/>')
    return "\n".join(out)


def main():
    if len(sys.argv) < 2:
        raise SystemExit(__doc__)
    root = pathlib.Path(__file__).resolve().parent.parent / "results" / "curves"
    scene = sys.argv[1]
    names = sys.argv[2:] or sorted(p.stem for p in (root / scene).glob("*.jsonl"))
    if not names:
        raise SystemExit(f"no curves in {root / scene}")
    curves = [(n, load(root / scene / f"{n}.jsonl")) for n in names]
    w, h = 520, 330
    legend = "\n".join(
        f'<rect x="{20 + 200 * (i % 5)}" y="{h + 12 + 18 * (i // 5)}" width="12" height="12" '
        f'fill="{COLOURS[i % len(COLOURS)]}"/><text x="{36 + 200 * (i % 5)}" '
        f'y="{h + 22 + 18 * (i // 5)}" font-size="11">{n}</text>'
        for i, (n, _) in enumerate(curves))
    rows = (len(curves) + 4) // 5
    svg = (f'<svg xmlns="http://www.w3.org/2000/svg" width="{2 * w}" height="{h + 20 + 18 * rows}" '
           'font-family="sans-serif"><rect width="100%" height="100%" fill="white"/>\n'
           + panel(curves, "test_psnr", 0, 0, w, h, f"{scene}: held-out PSNR (dB)", False) + "\n"
           + panel(curves, "test_lpips_alex", w, 0, w, h, f"{scene}: held-out LPIPS-alex", True)
           + "\n" + legend + "\n</svg>\n")
    (root / f"{scene}.svg").write_text(svg)
    print(f"| {scene} | steps | train s | held-out PSNR | SSIM | LPIPS-alex | opacity | batch PSNR |")
    print("|---|---|---|---|---|---|---|---|")
    for n, rows in curves:
        r = rows[-1]
        lp = r.get("test_lpips_alex")
        print(f"| {n} | {r['step']} | {r['train_seconds']:.0f} | {r['test_psnr']:.2f} | "
              f"{r['test_ssim']:.3f} | {'-' if lp is None else f'{lp:.3f}'} | "
              f"{r['test_opacity']:.3f} | {r['batch_psnr']:.2f} |")
    print(f"wrote {root / (scene + '.svg')}", file=sys.stderr)


if __name__ == "__main__":
    main()
