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
# Prints "count-per-ray address: instruction" for every instruction that ran, in address
# order, then the function's total per ray. Only the timed batch calls (`Scene::intersect_batch` /
# `occluded_batch`, as in `tools/callgrind-compare.sh`) are counted, at
# 240x135, one thread. Needs `valgrind` and `objdump`.
set -euo pipefail
# EVENT=DLmr (or D1mr, Dr...) lists that event per ray instead of instructions, with callgrind's
# cache model of `tools/cg-sim.sh` (CG_D1 and CG_LL override it). EVENT=Bcm (or Bc, Bim...)
# lists branches and their mispredictions instead.
here=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=tools/cg-sim.sh
. "$here/cg-sim.sh"
event=${EVENT:-Ir}
cg_event_options "$event"
bin=${REBRAID_BIN:-$here/../target/release/rebraid}
scene=$1 set=$2 mode=$3 func=$4
shift 4
d=$(mktemp -d)
trap 'rm -rf "$d"' EXIT
valgrind --tool=callgrind "${cg_options[@]}" --dump-instr=yes --compress-pos=no --compress-strings=no \
    --collect-atstart=no --toggle-collect='rebraid::scene::Scene::intersect_batch' \
    --toggle-collect='rebraid::scene::Scene::occluded_batch' \
    --callgrind-out-file="$d/cg" "$bin" bench "$scene" --modes "$mode" --sets "$set" \
    --threads 1 --reps 1 --width 240 --height 135 --json "$d/run.json" "$@" >/dev/null 2>&1
python3 "$here/cg_listing.py" "$d/cg" "$d/run.json" "$set" --function "$func" --binary "$bin" --event "$event"
