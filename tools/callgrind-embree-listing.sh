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
# EVENT=DLmr (or D1mr, Dr...) lists that event per ray instead of instructions, with callgrind's
# cache model of `tools/cg-sim.sh` (CG_D1 and CG_LL override it). EVENT=Bcm (or Bc, Bim...)
# lists branches and their mispredictions instead.
here=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=tools/cg-sim.sh
. "$here/cg-sim.sh"
event=${EVENT:-Ir}
cg_event_options "$event"
bin=${REBRAID_BIN:-$here/../target/release/rebraid}
scene=$1 set=$2 mode=${3:-embree-flat}
shift 2
if [ $# -gt 0 ]; then shift; fi
d=$(mktemp -d)
trap 'rm -rf "$d"' EXIT
valgrind --tool=callgrind "${cg_options[@]}" --trace-children=yes --dump-instr=yes --compress-pos=no \
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
python3 "$here/cg_listing.py" "$out" "$d/run.json" "$set" --hottest-in embree --event "$event"
