#!/usr/bin/env python3
"""Cycles of one traversal step, modelled by `llvm-mca`, from a per-instruction listing.

A wide BVH walk is a chain: the next node's address is loaded from the node just tested, at
the slot its hit mask names, so on incoherent rays each step costs its latency, which
callgrind's instruction counts do not show and this machine's missing hardware counters cannot
measure. This tool takes the instructions of one step from a listing of
`tools/callgrind-listing.sh` (ours) or `tools/callgrind-embree-listing.sh` (Embree's), picked
by how often they ran per ray (`--counts`, the groups `tools/listing-groups.py` prints: for a
one-hit step, the child-load group, the node test and the child selection), drops the jumps,
and lets `llvm-mca` run them as a loop (the loop-carried dependency is the child index or
pointer, as in the walk). Loads are modelled as first-level hits.

    tools/callgrind-listing.sh SCENE diffuse flat intersect_packets_avx2 > ours.lst
    tools/listing-groups.py < ours.lst          # find the node test's and its neighbours' counts
    tools/node-step-mca.py ours.lst --counts 4.09,5.87,4.41 [--cpu znver3] [--critical]

A caveat measured in session 23 (docs/performance.md): changes that brought our modelled step
from 34 to Embree's 29 cycles (child references as byte offsets plus the folded robust far
product) made diffuse rays only 1-1.5% faster by wall clock, not the ~6% the model implies:
it ranks step latencies with first-level hits; it does not predict time on its own.

The counts are matched as printed (two decimals). Prints the modelled cycles per iteration;
`--critical` adds llvm-mca's critical sequence, `--show` the instructions it ran.
"""
import argparse
import re
import subprocess
import sys
import tempfile


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("listing")
    ap.add_argument("--counts", required=True, help="comma-separated runs-per-ray groups")
    ap.add_argument("--cpu", default="znver3")
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--critical", action="store_true")
    ap.add_argument("--show", action="store_true")
    a = ap.parse_args()
    wanted = {c.strip() for c in a.counts.split(",")}
    body = []
    for line in open(a.listing):
        m = re.match(r"\s*([0-9.]+) ([0-9a-f]+): (.*)", line)
        if not m or m.group(1) not in wanted:
            continue
        ins = re.sub(r"\s*<.*", "", m.group(3))
        ins = re.sub(r"#.*", "", ins).strip()
        if ins.startswith("j"):
            continue
        # RIP-relative constants: the displacement is irrelevant to the model.
        body.append(re.sub(r"\[rip\+0x[0-9a-f]+\]", "[rip]", ins))
    if not body:
        sys.exit(f"no instruction of the listing ran {sorted(wanted)} times per ray")
    with tempfile.NamedTemporaryFile("w", suffix=".s") as f:
        f.write(".intel_syntax noprefix\n" + "\n".join(body) + "\n")
        f.flush()
        args = ["llvm-mca", f"-mcpu={a.cpu}", f"-iterations={a.iterations}", f.name]
        if a.critical:
            args.insert(1, "-bottleneck-analysis")
        out = subprocess.run(args, capture_output=True, text=True, check=True).stdout
    cycles = int(re.search(r"Total Cycles:\s+(\d+)", out).group(1))
    print(f"{len(body)} instructions, {cycles / a.iterations:.1f} cycles per iteration "
          f"({a.cpu}, llvm-mca)")
    if a.show:
        print("\n".join(body))
    if a.critical:
        m = re.search(r"Critical sequence based on the simulation:.*?(?=\nInstruction Info)", out,
                      re.S)
        print(m.group(0) if m else out)


if __name__ == "__main__":
    main()
