#!/usr/bin/env python3
"""Issue 61's accounting of the fused training step (kernels/wgsl/render/train_step.wgsl with
common/step.wgsl): per trained sample, each operation's count times its cost measured by
`bench kernels --only micro`, the predicted kernel time beside the measured one (`bench train`'s
"fused step" stage), round by round. tools/fused_accounting.sh runs the rounds and calls this.

Usage: tools/fused_accounting.py OUT   (reads OUT/round*/micro.json and OUT/round*/train.json,
and OUT/callgrind*.txt when present; prints the table in Markdown)

The counts follow the kernel's code for the configuration in train.json (checked: F = 2
features, scalar MLPs, uniform strata, no occupancy grid, every sample valid):
  * encode (pass 1): per level one level_info load (same address in every lane), 8 corners,
    each an index (dense or hashed) and two adjacent 4-byte table loads (table_at(e),
    table_at(e + 1));
  * encode_backward (pass 2): the same level_info loads and corner indices, and per corner F
    f32 atomic adds into d_table (skipped only for an exact zero);
  * forward_recorded: mlp_layer_group computes output rows 4 at a time (pad4(no) rows of ni
    FMAs); backward_recorded: mlp_layer_back_group does no x ni FMAs per layer;
  * records, vec4s at a lane-varying address: forward writes each layer's inputs and the last
    layer's outputs; backward reads and writes ceil(no / 4) per layer; pass 2 reads both MLPs'
    outputs once.
What it does not cost: the strata, contraction, compositing and losses (a few exps and a few
dozen FMAs per sample), and the private-array copies outside the MLP layers.
"""

import glob
import json
import os
import statistics
import sys


def pad4(x):
    return (x + 3) // 4 * 4


def counts(train):
    """(name, count per sample, micro op, 'net' or 'raw', factor, note) for train.json's model."""
    levels = train["grid_levels"]
    feats = train["model"]["features"]
    if feats != 2:
        sys.exit(f"the accounting follows the F = 2 path of encode(); this model has F = {feats}")
    dims_d = train["mlp_dims"]["density"]
    dims_c = train["mlp_dims"]["color"]
    near_bytes = 256 * 1024
    near = [l for l in levels if l["size"] * feats * 4 <= near_bytes]
    far = [l for l in levels if l["size"] * feats * 4 > near_bytes]
    L = len(levels)
    fwd = sum(ni * pad4(no) for d in (dims_d, dims_c) for ni, no in zip(d, d[1:]))
    bwd = sum(ni * no for d in (dims_d, dims_c) for ni, no in zip(d, d[1:]))
    rec_fwd = sum(
        sum(pad4(ni) // 4 for ni in d[:-1]) + pad4(d[-1]) // 4 for d in (dims_d, dims_c)
    )
    rec_bwd = sum(2 * (pad4(no) // 4) for d in (dims_d, dims_c) for no in d[1:]) + 2
    return [
        (
            f"corner reads, {len(near)} levels of <= 256 KiB (2 x 4 B each)",
            8 * len(near),
            "random read 4 B, 256 KiB table",
            "net",
            2,
            "two loads per corner, each costed as a cached random 4 B read",
        ),
        (
            f"corner reads, {len(far)} levels of > 256 KiB (2 x 4 B each)",
            8 * len(far),
            "random read 2 x 4 B adjacent (a corner)",
            "net",
            1,
            "tables of 0.6-1 MiB each, 16 MiB measured",
        ),
        (
            "corner indices (fwd + bwd)",
            2 * 8 * L,
            "random index (baseline)",
            "raw",
            1,
            "an LCG step and a shift: fewer operations than hg_index's hash",
        ),
        (
            "level_info loads (fwd + bwd)",
            2 * L,
            "storage vec4 load, same address in all lanes",
            "raw",
            1,
            "",
        ),
        (
            f"f32 atomic adds into d_table ({feats} per corner)",
            8 * feats * L,
            "f32 atomic add, distinct addresses",
            "net",
            1,
            "distinct addresses; 64 lanes per address measured cheaper",
        ),
        (
            "MLP forward FMAs (4 samples per weight load)",
            fwd,
            "dense 64x64 layer, 4 points/lane",
            "raw",
            1,
            f"{dims_d} + {dims_c}, output rows in fours",
        ),
        (
            "MLP backward FMAs (4 samples per weight load)",
            bwd,
            "dense 64x64 backward, 4 points/lane",
            "raw",
            1,
            "W^T d per layer",
        ),
        (
            "MLP record vec4 accesses",
            rec_fwd + rec_bwd,
            "storage vec4 read-modify-write",
            "raw",
            0.5,
            f"{rec_fwd} writes in pass 1, {rec_bwd} reads and writes in pass 2; half a read-modify-write each",
        ),
    ]


def micro_cost(micro, op, kind, optional=False):
    row = next((r for r in micro["micro"] if r["op"] == op), None)
    if row is None:
        if optional:
            return None
        sys.exit(f"micro.json has no row `{op}`")
    if kind == "net":
        return row["net_ns_per_op"]
    return row["ns_per_op"]


def fused_ms(train):
    runs = [r for r in train["runs"] if r["fused"] and r["mlp"] == "scalar f32"]
    if len(runs) != 1:
        sys.exit("train.json must hold exactly one fused run with scalar f32 MLPs")
    stage = [s for s in runs[0]["stages_ms"] if s["stage"].startswith("fused step")]
    return stage[0]["ms"], runs[0]


def ranked(per_round, rows, measured_ns):
    """The changes the accounting says would remove the most time per sample, each with its
    predicted saving from the same medians (costs the change would have, measured by a micro
    operation, against those it has)."""

    def cost(op, kind):
        vals = [micro_cost(r[4], op, kind, optional=True) for r in per_round]
        vals = [v for v in vals if v is not None]
        return statistics.median(vals) if vals else None

    far = next(n for name, n, *_ in rows if "> 256 KiB" in name)
    atomics = next(n for name, n, *_ in rows if name.startswith("f32 atomic"))
    fwd = next(n for name, n, *_ in rows if name.startswith("MLP forward"))
    bwd = next(n for name, n, *_ in rows if name.startswith("MLP backward"))
    records = next(n for name, n, *_ in rows if name.startswith("MLP record"))
    items = []
    f32_atomic = cost("f32 atomic add, distinct addresses", "net")
    u32_atomic = cost("u32 atomic add, distinct addresses", "net")
    hot_atomic = cost("f32 atomic add, 64 lanes per address", "net")
    pre_atomic = cost("f32 atomic add, distinct addresses, line loaded first", "net")
    if pre_atomic is not None:
        items.append((
            atomics * (f32_atomic - pre_atomic),
            "Load each corner's gradient entries with plain loads (their cache misses overlap; "
            "a locked compare-exchange waits for its own) before the atomic adds, e.g. all 8 "
            "corners of a level first",
            f"{atomics} x ({f32_atomic:.2f} - {pre_atomic:.2f}) ns",
        ))
    if u32_atomic is not None:
        items.append((
            atomics * (f32_atomic - u32_atomic),
            "Accumulate the hash-grid gradient in fixed point with u32 atomic adds (one locked "
            "add per lane) instead of f32 ones (a compare-exchange loop per lane); needs a "
            "per-level scale with headroom and a conversion pass before Adam (not costed)",
            f"{atomics} x ({f32_atomic:.2f} - {u32_atomic:.2f}) ns",
        ))
    items.append((
        atomics * (f32_atomic - hot_atomic),
        "Make the gradient atomics hit cached lines (at most this much: the same atomic when "
        "64 lanes share each address, its line in L1), e.g. samples ordered so that neighbouring "
        "lanes share cells",
        f"{atomics} x ({f32_atomic:.2f} - {hot_atomic:.2f}) ns",
    ))
    pair = cost("random read 2 x 4 B adjacent (a corner)", "net")
    read8 = cost("random read 8 B", "net")
    items.append((
        far * (pair - read8),
        "Read each corner's two features as one vec2 load instead of two f32 loads (the "
        "hashed levels; the cached coarse levels gain little)",
        f"{far} x ({pair:.2f} - {read8:.2f}) ns",
    ))
    d4 = cost("dense 64x64 layer, 4 points/lane", "raw")
    d4b = cost("dense 64x64 backward, 4 points/lane", "raw")
    items.append((
        bwd * (d4b - d4),
        "Run the MLPs' backward data pass at the forward pass's cost per FMA (W^T d as row dot "
        "products over a transposed copy of the weights, instead of 64 accumulators per sample)",
        f"{bwd} x ({d4b:.3f} - {d4:.3f}) ns",
    ))
    fma = cost("FMA, registers", "raw")
    items.append((
        (fwd + bwd) * (statistics.mean([d4, d4b]) - fma),
        "Bring the MLPs to the FMA rate with every operand in registers (at most this much: "
        "the weight loads and activation traffic gone)",
        f"{fwd + bwd} x ({statistics.mean([d4, d4b]):.3f} - {fma:.3f}) ns",
    ))
    store = cost("storage vec4 read-modify-write", "raw")
    wg = cost("workgroup vec4 read-modify-write", "raw")
    items.append((
        records * 0.5 * (store - wg),
        "Keep the MLP records in workgroup memory instead of a storage buffer (they would "
        "not fit: about 1.5 KiB per sample)",
        f"{records} x 0.5 x ({store:.2f} - {wg:.2f}) ns",
    ))
    print("## Ranked list: predicted savings per trained sample")
    print()
    print("Each from this table's medians: the operations' count times the cost difference. "
          "Savings of the same operation do not add up.")
    print()
    print("| rank | change | predicted saving ns per sample | of the measured kernel | from |")
    print("|---:|---|---:|---:|---|")
    for i, (saving, what, how) in enumerate(sorted(items, key=lambda x: -x[0])):
        print(f"| {i + 1} | {what} | {saving:.0f} | {100 * saving / measured_ns:.0f}% | {how} |")
    print()


def main():
    if len(sys.argv) != 2:
        sys.exit("usage: tools/fused_accounting.py OUT")
    out = sys.argv[1]
    rounds = sorted(glob.glob(os.path.join(out, "round*")))
    if not rounds:
        sys.exit(f"{out}: no round*/ folders (run tools/fused_accounting.sh)")
    per_round = []
    for d in rounds:
        micro = json.load(open(os.path.join(d, "micro.json")))
        train = json.load(open(os.path.join(d, "train.json")))
        ms, run = fused_ms(train)
        if run["sampler"] != "uniform" or run.get("occupied_fraction") is not None:
            sys.exit(f"{d}: the accounting is for uniform strata without an occupancy grid")
        samples = train["rays"] * train["samples_per_ray"]
        rows = counts(train)
        costs = [micro_cost(micro, op, kind) * factor for (_, _, op, kind, factor, _) in rows]
        per_round.append((ms, samples, rows, costs, micro, train))
    ms0, samples, rows, _, micro0, train0 = per_round[0]
    med_costs = [statistics.median(r[3][i] for r in per_round) for i in range(len(rows))]
    measured = [r[0] * 1e6 / r[1] for r in per_round]
    predicted = [sum(c * n for c, (_, n, *_) in zip(r[3], r[2])) for r in per_round]
    print(f"# Fused training step: where its time per sample goes ({len(per_round)} rounds)\n")
    print(f"Made by `tools/fused_accounting.sh {out} {len(per_round)}` (with `BASE_BIN`, the base build's rows; "
          "the instruction counts by `tools/callgrind_step.sh`); the findings are in `docs/kernels.md`.\n")
    print(f"Device: {train0['device']} ({train0['driver']}); micro device: {micro0['device']['name']}.")
    print(
        f"Configuration: {train0['rays']} rays x {train0['samples_per_ray']} samples = {samples} samples per step; "
        f"hash grid {len(train0['grid_levels'])} levels x {train0['model']['features']} features x 2^{train0['model']['log2_table']}; "
        f"MLPs {train0['mlp_dims']['density']} + {train0['mlp_dims']['color']}, scalar f32; uniform strata.\n"
    )
    print("Each cost is the median over the rounds of `bench kernels --only micro` (ns per operation, all lanes together; net = less the random index's own cost).\n")
    print("| operation | per sample | cost ns (micro op) | ns per sample | share |")
    print("|---|---:|---|---:|---:|")
    total = sum(c * n for c, (_, n, *_) in zip(med_costs, rows))
    for c, (name, n, op, kind, factor, note) in sorted(
        zip(med_costs, rows), key=lambda x: -x[0] * x[1][1]
    ):
        f = f"{factor} x " if factor != 1 else ""
        extra = f"; {note}" if note else ""
        print(f"| {name} | {n} | {c:.3f} ({f}{op}, {kind}{extra}) | {c * n:.0f} | {100 * c * n / total:.0f}% |")
    print(f"| **predicted** | | | **{total:.0f}** | |")
    med_meas = statistics.median(measured)
    print(f"| **measured** (fused step stage, median of rounds) | | | **{med_meas:.0f}** | {med_meas / total:.2f}x predicted |\n")
    print("| round | measured fused ms | ns per sample | predicted ns per sample | measured / predicted |")
    print("|---:|---:|---:|---:|---:|")
    for i, (r, m, p) in enumerate(zip(per_round, measured, predicted)):
        print(f"| {i + 1} | {r[0]:.2f} | {m:.0f} | {p:.0f} | {m / p:.2f} |")
    print()
    base = []
    for d in rounds:
        path = os.path.join(d, "train_base.json")
        if os.path.exists(path):
            b = json.load(open(path))
            bms, brun = fused_ms(b)
            total = sum(st["ms"] for st in brun["stages_ms"])
            base.append((bms, total, brun["step_ms_wall"]))
    if base:
        mine = [(r[0], sum(st["ms"] for st in r[5]["runs"][0]["stages_ms"]), r[5]["runs"][0]["step_ms_wall"]) for r in per_round]
        print(f"The base build (BASE_BIN, {os.environ.get('BASE_NAME', 'older build')}) in the same rounds, same configuration:\n")
        print("| round | base fused ms | this fused ms | base step GPU ms | this step GPU ms | base wall ms/step | this wall ms/step |")
        print("|---:|---:|---:|---:|---:|---:|---:|")
        for i, (b, m) in enumerate(zip(base, mine)):
            print(f"| {i + 1} | {b[0]:.2f} | {m[0]:.2f} | {b[1]:.2f} | {m[1]:.2f} | {b[2]:.1f} | {m[2]:.1f} |")
        med = lambda xs, k: statistics.median(x[k] for x in xs)
        print(f"| median | {med(base, 0):.2f} | {med(mine, 0):.2f} | {med(base, 1):.2f} | {med(mine, 1):.2f} | {med(base, 2):.1f} | {med(mine, 2):.1f} |\n")
    ranked(per_round, rows, med_meas)
    cg = sorted(glob.glob(os.path.join(out, "callgrind*.txt")))
    for path in cg:
        print(f"Instruction counts ({os.path.basename(path)}):\n")
        print("```")
        print(open(path).read().rstrip())
        print("```\n")


if __name__ == "__main__":
    main()
