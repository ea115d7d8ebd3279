#!/usr/bin/env bash
# Deterministic per-ray cost of our flat and re-braided modes against Embree's (AVX2) flat and
# two-level modes: instructions, data reads and writes (memory operands included), mispredicted
# branches and cache misses per ray, from callgrind.
#
#   tools/callgrind-compare.sh SCENE SET [more `rebraid bench` options]
#   e.g. tools/callgrind-compare.sh ../shared/scenes/samurai_monastery.obj diffuse
#
# Why: on a shared machine, wall-clock A/B runs of the same binary stray from 1.0 by several
# percent (docs/performance.md, session 9), while these counts are exact. What is counted is
# each side's timed region, the batch call `rebraid bench` times: ours `Scene::intersect_batch`
# / `Scene::occluded_batch`, Embree's `EmbreeScene::intersect_batch_with` /
# `occluded_batch_with` (`rtcIntersect1` per ray with its ray and hit conversions). Both read the
# ray array and write the answer array. (Before session 15 Embree's side counted `rtcIntersect1`
# alone, without its ray and hit conversions, and ours all of `trace_sets`, with the answers'
# summary after the clock stops.) The cache model is `tools/cg-sim.sh`'s (CG_D1 and CG_LL
# override it). Valgrind cannot run AVX-512, so Embree is capped at AVX2 (as our
# kernels are). Needs `valgrind` and a build with `--features embree`. Default image: 240x135.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=tools/cg-sim.sh
. "$here/cg-sim.sh"
bin=${REBRAID_BIN:-$here/../target/release/rebraid}
scene=$1 set=$2
shift 2
d=$(mktemp -d)
trap 'rm -rf "$d"' EXIT
valgrind --tool=callgrind --trace-children=yes --branch-sim=yes --cache-sim=yes \
    "${cg_cache[@]}" --collect-atstart=no \
    --toggle-collect='rebraid::scene::Scene::intersect_batch' \
    --toggle-collect='rebraid::scene::Scene::occluded_batch' \
    --toggle-collect='rebraid_cli::embree::EmbreeScene::intersect_batch_with' \
    --toggle-collect='rebraid_cli::embree::EmbreeScene::occluded_batch_with' \
    --callgrind-out-file="$d/cg.%p" \
    "$bin" bench "$scene" --modes flat --sets "$set" --threads 1 --reps 1 --width 240 --height 135 \
    --embree --embree-isa avx2 --json "$d/flat.json" "$@" >/dev/null 2>&1
# One output per process, named by pid: every row runs in a worker process whose command line
# names its mode (`bench --embree` traces ours in workers too); the parent traces nothing.
for f in "$d"/cg.*; do
    mode=$(grep -m1 -o -- '--mode [a-z-]*' "$f" | cut -d' ' -f2 || true)
    if [ -n "$mode" ]; then mv "$f" "$d/$mode.cg"; else rm "$f"; fi
done
valgrind --tool=callgrind --branch-sim=yes --cache-sim=yes \
    "${cg_cache[@]}" --collect-atstart=no \
    --toggle-collect='rebraid::scene::Scene::intersect_batch' \
    --toggle-collect='rebraid::scene::Scene::occluded_batch' --callgrind-out-file="$d/rebraided.cg" \
    "$bin" bench "$scene" --modes rebraided --sets "$set" --threads 1 --reps 1 --width 240 \
    --height 135 "$@" >/dev/null 2>&1
python3 - "$d" "$set" "$(basename "$scene")" <<'PY'
import json, re, sys
d, ray_set, scene = sys.argv[1:4]
rays = next(json.loads(l)[ray_set]["rays"] for l in open(f"{d}/flat.json"))
print(f"{scene} {ray_set}: {rays} rays; per ray:")
print(f"  {'mode':<20} {'instr':>8} {'reads':>8} {'writes':>8} {'mispred':>8} {'L1D miss':>9} {'LL miss':>8}")
for mode in ["flat", "rebraided", "embree-flat", "embree-two-level"]:
    txt = open(f"{d}/{mode}.cg").read()
    ev = re.search(r"^events:\s+(.*)", txt, re.M).group(1).split()
    tot = dict(zip(ev, map(int, re.search(r"^summary:\s+(.*)", txt, re.M).group(1).split())))
    per = lambda k: tot.get(k, 0) / rays
    print(f"  {mode:<20} {per('Ir'):8.1f} {per('Dr'):8.1f} {per('Dw'):8.1f} {per('Bcm') + per('Bim'):8.2f} "
          f"{per('D1mr') + per('D1mw'):9.2f} {per('DLmr') + per('DLmw'):8.2f}")
PY
