#!/usr/bin/env bash
# Per-instruction cost of one traced function, per ray: callgrind's exact instruction counts,
# mapped onto the disassembly, so that a kernel's loops can be read with how often each
# instruction runs (a node test's instructions run "nodes per ray" times, a ray's set-up once).
#
#   tools/callgrind-listing.sh SCENE SET MODE FUNCTION [more `rebraid bench` options]
#   e.g. tools/callgrind-listing.sh ../shared/scenes/samurai_monastery.obj diffuse rebraided \
#            'packets::intersect'
#
# FUNCTION is a substring of the (demangled) function name; the hot loops of our modes are
# `toplevel::packets::intersect` (re-braided and two-level closest hits),
# `bvh::simd::intersect_packets_avx2` (flat closest hits) and their `occluded` counterparts.
# Prints "count-per-ray address: instruction" for every instruction that ran, in address order, then the
# function's total per ray. Only the timed batch calls (`Scene::intersect_batch` /
# `occluded_batch`, as in `tools/callgrind-compare.sh`) are counted, at
# 240x135, one thread. Needs `valgrind` and `objdump`.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
bin=${REBRAID_BIN:-$here/../target/release/rebraid}
scene=$1 set=$2 mode=$3 func=$4
shift 4
d=$(mktemp -d)
trap 'rm -rf "$d"' EXIT
valgrind --tool=callgrind --dump-instr=yes --compress-pos=no --compress-strings=no \
    --collect-atstart=no --toggle-collect='rebraid::scene::Scene::intersect_batch' \
    --toggle-collect='rebraid::scene::Scene::occluded_batch' \
    --callgrind-out-file="$d/cg" "$bin" bench "$scene" --modes "$mode" --sets "$set" \
    --threads 1 --reps 1 --width 240 --height 135 --json "$d/run.json" "$@" >/dev/null 2>&1
python3 - "$d" "$bin" "$set" "$func" <<'PY'
import collections, json, re, subprocess, sys
d, binary, ray_set, func = sys.argv[1:5]
rays = next(json.loads(l)[ray_set]["rays"] for l in open(f"{d}/run.json"))
cost, fn_of = collections.Counter(), {}
fn, after_call = None, False
for line in open(f"{d}/cg"):
    if line.startswith("fn="):
        fn = line[3:].strip()
        continue
    if line.startswith("calls="):
        after_call = True  # the next cost line is the call's inclusive cost
        continue
    m = re.match(r"^(0x[0-9a-f]+)\s+\d+\s+(\d+)", line)
    if m:
        if after_call:
            after_call = False
            continue
        a = int(m.group(1), 16)
        cost[a] += int(m.group(2))
        fn_of[a] = fn
addrs = sorted(a for a in cost if func in (fn_of[a] or ""))
if not addrs:
    sys.exit(f"no instruction of a function matching {func!r} ran")
asm = subprocess.run(
    ["objdump", "-d", "--no-show-raw-insn", "-M", "intel", binary,
     f"--start-address={addrs[0]}", f"--stop-address={addrs[-1] + 16}"],
    capture_output=True, text=True, check=True).stdout
total = 0
for line in asm.splitlines():
    m = re.match(r"^\s+([0-9a-f]+):\s+(.*)", line)
    if m and cost.get(int(m.group(1), 16)):
        c = cost[int(m.group(1), 16)]
        total += c
        print(f"{c / rays:7.2f} {m.group(1)}: {m.group(2)[:100]}")
print(f"{total / rays:.1f} instructions per ray in functions matching {func!r} ({rays} rays)")
PY
