#!/usr/bin/env python3
"""Instructions per trained sample of the fused training step's kernel and of all the step's
kernels, from callgrind's per-thread files of one `bench train` run (tools/callgrind_step.sh).

lavapipe JIT-compiles each kernel into anonymous memory, where callgrind knows no symbols: it
names each function by its address ("0x...") in object "???". Each kernel's entry function is
called by lavapipe (libvulkan_lvp) once per workgroup, so its inclusive cost per call is one
workgroup's instructions. The fused step's kernel is the entry with the largest cost per call
(a workgroup trains 64 rays x all their samples; no other kernel of the step comes near), and
it runs once per step with RAYS / 64 workgroups, which gives the steps run. A run also
dispatches kernels outside its steps (the data's upload, the parameters' initialisation), so
the whole step's figure is the difference between two runs that differ only in their step
count, over the steps between them.

Usage: tools/callgrind_step.py DIR_A DIR_B RAYS SAMPLES
  (each DIR holds one run's callgrind.out.* files; B ran more steps than A)
"""

import glob
import os
import re
import sys
from collections import defaultdict

NAME = re.compile(r"^\((\d+)\)(?: (.*))?$")


def parse(path, calls, incl):
    """Adds, per callee name of a call from libvulkan_lvp into code without an object, the
    call count and the inclusive Ir to calls / incl."""
    names = {"fn": {}, "ob": {}}
    cur_ob = cur_fn = cob = cfn = None
    pending = None
    with open(path, errors="replace") as f:
        for line in f:
            line = line.rstrip("\n")
            if pending is not None:
                # The line after calls=: "<position> <inclusive cost>".
                parts = line.split()
                if parts:
                    if cur_ob and "lvp" in cur_ob and cob == "???":
                        calls[cfn] += pending
                        incl[cfn] += int(parts[-1])
                pending = None
                continue
            key, sep, val = line.partition("=")
            if not sep:
                continue
            if key in ("ob", "cob", "fn", "cfn"):
                table = names["ob" if key in ("ob", "cob") else "fn"]
                m = NAME.match(val)
                if m:
                    if m.group(2) is not None:
                        table[m.group(1)] = m.group(2)
                    val = table.get(m.group(1), val)
                if key == "ob":
                    cur_ob = val
                elif key == "cob":
                    cob = val
                elif key == "fn":
                    cur_fn = val
                    cob = cur_ob
                else:
                    cfn = val
            elif key == "calls":
                pending = int(val.split()[0])
    return cur_fn


def kernels(d):
    """(name -> (workgroups, inclusive Ir)) of every JIT-compiled kernel of one run."""
    files = sorted(glob.glob(os.path.join(d, "callgrind.out.*")))
    if not files:
        sys.exit(f"{d}: no callgrind.out.* files")
    calls, incl = defaultdict(int), defaultdict(int)
    for p in files:
        parse(p, calls, incl)
    entries = {n: (calls[n], incl[n]) for n in calls if n and n.startswith("0x") and calls[n]}
    if not entries:
        sys.exit(f"{d}: no calls from lavapipe into JIT-compiled code")
    return entries


def fused_of(entries, groups, d):
    fused = max(entries, key=lambda n: entries[n][1] / entries[n][0])
    c = entries[fused][0]
    if c % groups:
        sys.exit(f"{d}: the largest kernel per call ran {c} workgroups, not a multiple of {groups}")
    return fused, c // groups


def main():
    if len(sys.argv) != 5:
        sys.exit("usage: tools/callgrind_step.py DIR_A DIR_B RAYS SAMPLES")
    da, db, rays, samples = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    groups = (rays + 63) // 64
    ea, eb = kernels(da), kernels(db)
    fa, sa = fused_of(ea, groups, da)
    fb, sb = fused_of(eb, groups, db)
    if sb <= sa:
        sys.exit(f"{db} ran {sb} steps, {da} {sa}: B must run more")
    per_step = rays * samples
    f_calls, f_ir = eb[fb]
    fused_ps = f_ir / (sb * per_step)
    total_a = sum(ir for _, ir in ea.values())
    total_b = sum(ir for _, ir in eb.values())
    step = (total_b - total_a) / (sb - sa)
    print(f"runs: {sa} and {sb} steps (the fused kernel's workgroups / {groups} per step); "
          f"{len(eb)} kernels")
    print(f"fused step kernel: {fused_ps:,.0f} instructions per trained sample "
          f"({f_ir / f_calls:,.0f} per workgroup of 64 rays)")
    print(f"whole step, all kernels: {step / per_step:,.0f} instructions per trained sample "
          f"({step:,.0f} per step, from the difference of the two runs; the fused kernel "
          f"{100 * fused_ps * per_step / step:.1f}%)")
    print("the five largest kernels of the longer run (instructions per step, workgroups per step):")
    for n in sorted(eb, key=lambda n: -eb[n][1])[:5]:
        c, ir = eb[n]
        tag = "  <- fused step" if n == fb else ""
        print(f"  {n}: {ir / sb:,.0f} ({c / sb:g}){tag}")


if __name__ == "__main__":
    main()
