#!/usr/bin/env python3
"""Per-instruction cost per ray of one function, from a callgrind output with `--dump-instr=yes`.

The shared half of `tools/callgrind-listing.sh` (ours: the function named by a substring) and
`tools/callgrind-embree-listing.sh` (Embree's: the hottest function of a shared object whose
path contains a substring, since `libembree3` has no symbols). Prints
"count-per-ray address: instruction" for every instruction of the function that ran, in address
order (objdump's disassembly), then the function's total per ray.

    cg_listing.py CALLGRIND_OUT RUN_JSON SET --function SUBSTR --binary BIN
    cg_listing.py CALLGRIND_OUT RUN_JSON SET --hottest-in OBJECT_SUBSTR
"""
import argparse
import collections
import json
import re
import subprocess
import sys


def read_costs(path, event="Ir"):
    """Self cost of one event per (function, address), and each function's object file."""
    cost, obj_of = collections.Counter(), {}
    fn, obj, after_call, column = None, None, False, 0
    for line in open(path):
        if line.startswith("events:"):
            names = line.split()[1:]
            if event not in names:
                sys.exit(f"event {event!r} not recorded (have: {' '.join(names)})")
            column = names.index(event)
        elif line.startswith("ob="):
            obj = line[3:].strip()
        elif line.startswith("fn="):
            fn = line[3:].strip()
            obj_of.setdefault(fn, obj)
        elif line.startswith("calls="):
            after_call = True  # the next cost line is the call's inclusive cost
        else:
            m = re.match(r"^(0x[0-9a-f]+)\s+\d+((?:\s+\d+)+)", line)
            if m:
                if after_call:
                    after_call = False
                    continue
                values = m.group(2).split()  # trailing zero events may be left off
                if column < len(values):
                    cost[(fn, int(m.group(1), 16))] += int(values[column])
    return cost, obj_of


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("callgrind_out")
    ap.add_argument("run_json")
    ap.add_argument("ray_set")
    which = ap.add_mutually_exclusive_group(required=True)
    which.add_argument("--function", help="substring of our function's name (needs --binary)")
    which.add_argument("--hottest-in", help="substring of a shared object's path")
    ap.add_argument("--binary")
    ap.add_argument("--event", default="Ir",
                    help="callgrind event to list (Ir; with --cache-sim=yes also DLmr, D1mr...)")
    a = ap.parse_args()
    if a.function and not a.binary:
        ap.error("--function needs --binary")
    rays = next(json.loads(l)[a.ray_set]["rays"] for l in open(a.run_json))
    cost, obj_of = read_costs(a.callgrind_out, a.event)
    if a.hottest_in:
        totals = collections.Counter()
        for (f, _), c in cost.items():
            if a.hottest_in in (obj_of.get(f) or ""):
                totals[f] += c
        if not totals:
            sys.exit(f"no function of an object matching {a.hottest_in!r} ran")
        hot = totals.most_common(1)[0][0]
        funcs, binary, name = {hot}, obj_of[hot], f"{hot.split()[0]} of {obj_of[hot]}"
    else:
        funcs = {f for (f, _) in cost if a.function in (f or "")}
        binary, name = a.binary, f"functions matching {a.function!r}"
    per_addr = collections.Counter()
    for (f, addr), c in cost.items():
        if f in funcs:
            per_addr[addr] += c
    if not per_addr:
        sys.exit(f"no instruction of {name} ran")
    addrs = sorted(per_addr)
    asm = subprocess.run(
        ["objdump", "-d", "--no-show-raw-insn", "-M", "intel", binary,
         f"--start-address={addrs[0]}", f"--stop-address={addrs[-1] + 16}"],
        capture_output=True, text=True, check=True).stdout
    total = 0
    for line in asm.splitlines():
        m = re.match(r"^\s+([0-9a-f]+):\s+(.*)", line)
        c = m and per_addr.get(int(m.group(1), 16))
        if c:
            total += c
            print(f"{c / rays:7.2f} {m.group(1)}: {m.group(2)[:100]}")
    what = "instructions" if a.event == "Ir" else a.event
    print(f"{total / rays:.2f} {what} per ray in {name} ({rays} rays)")


if __name__ == "__main__":
    main()
