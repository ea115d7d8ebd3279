#!/usr/bin/env bash
# Embree's side of `tools/callgrind-listing.sh`: the per-instruction cost, per ray, of Embree's
# hottest function (its single-ray kernel: `libembree3` ships without symbols, so the function
# is found by its instruction count and named by its address) in one Embree row of
# `rebraid bench --embree`, with Embree capped at AVX2 (valgrind cannot run AVX-512).
#
#   tools/callgrind-embree-listing.sh SCENE SET [embree-flat|embree-two-level] [bench options]
#   e.g. tools/callgrind-embree-listing.sh ../shared/scenes/samurai_monastery.obj diffuse embree-flat
#
# Prints "count-per-ray address: instruction" for every instruction of that function that ran,
# in address order, then the function's total per ray; pipe either listing into
# `tools/listing-groups.py` to see the instructions grouped by how often they run (node tests,
# leaves, blocks, set-up). Only the timed batch calls are counted (`EmbreeScene::*_batch_with`,
# as in `tools/callgrind-compare.sh`), at 240x135, one thread. Needs `valgrind` and `objdump`,
# and a build with `--features embree`.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
bin=${REBRAID_BIN:-$here/../target/release/rebraid}
scene=$1 set=$2 mode=${3:-embree-flat}
shift 2
if [ $# -gt 0 ]; then shift; fi
d=$(mktemp -d)
trap 'rm -rf "$d"' EXIT
valgrind --tool=callgrind --trace-children=yes --dump-instr=yes --compress-pos=no \
    --compress-strings=no --collect-atstart=no \
    --toggle-collect='rebraid_cli::embree::EmbreeScene::intersect_batch_with' \
    --toggle-collect='rebraid_cli::embree::EmbreeScene::occluded_batch_with' \
    --callgrind-out-file="$d/cg.%p" "$bin" bench "$scene" --modes flat --sets "$set" \
    --threads 1 --reps 1 --width 240 --height 135 --embree --embree-isa avx2 \
    --json "$d/run.json" "$@" >/dev/null 2>&1
out=
for f in "$d"/cg.*; do
    if [ "$(grep -m1 -o -- '--mode [a-z-]*' "$f" | cut -d' ' -f2 || true)" = "$mode" ]; then out=$f; fi
done
[ -n "$out" ] || { echo "no callgrind output for $mode" >&2; exit 1; }
python3 - "$out" "$d/run.json" "$set" <<'PY'
import collections, json, re, subprocess, sys
path, run, ray_set = sys.argv[1:4]
rays = next(json.loads(l)[ray_set]["rays"] for l in open(run))
cost, obj_of, fn_total = collections.Counter(), {}, collections.Counter()
fn, obj, after_call = None, None, False
for line in open(path):
    if line.startswith("ob="):
        obj = line[3:].strip()
    elif line.startswith("fn="):
        fn = line[3:].strip()
    elif line.startswith("calls="):
        after_call = True  # the next cost line is the call's inclusive cost
    else:
        m = re.match(r"^(0x[0-9a-f]+)\s+\d+\s+(\d+)", line)
        if m:
            if after_call:
                after_call = False
                continue
            cost[(fn, int(m.group(1), 16))] += int(m.group(2))
            fn_total[fn] += int(m.group(2))
            obj_of[fn] = obj
hot = next((f for f, _ in fn_total.most_common() if "embree" in (obj_of[f] or "")), None)
if hot is None:
    sys.exit("no Embree function ran")
lib = obj_of[hot].split()[-1] if " " in obj_of[hot] else obj_of[hot]
addrs = sorted(a for (f, a) in cost if f == hot)
asm = subprocess.run(
    ["objdump", "-d", "--no-show-raw-insn", "-M", "intel", lib,
     f"--start-address={addrs[0]}", f"--stop-address={addrs[-1] + 16}"],
    capture_output=True, text=True, check=True).stdout
total = 0
for line in asm.splitlines():
    m = re.match(r"^\s+([0-9a-f]+):\s+(.*)", line)
    c = m and cost.get((hot, int(m.group(1), 16)))
    if c:
        total += c
        print(f"{c / rays:7.2f} {m.group(1)}: {m.group(2)[:100]}")
print(f"{total / rays:.1f} instructions per ray in {hot.split()[0]} of {lib} ({rays} rays)")
PY
