#!/usr/bin/env bash
# Where the tracing time of one workload goes, by kernel part.
#
#   tools/profile-trace.sh SCENE MODE SET [more `rebraid bench` options]
#   e.g. tools/profile-trace.sh ../shared/scenes/samurai_monastery.obj rebraided shadow
#
# Records `rebraid bench --sets SET --modes MODE --threads 1` under `perf`
# with DWARF call stacks and sorts every sample taken while tracing by its
# innermost rebraid frame (inlined frames included): triangle tests, box
# tests, the traversal loop, top-level entry into objects, per-ray setup.
# Needs `perf` and a release build (`cargo build --release -p rebraid-cli`).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
bin=${REBRAID_BIN:-$here/../target/release/rebraid}
scene=$1 mode=$2 set=$3
shift 3
data=$(mktemp --suffix=.perf.data)
trap 'rm -f "$data"' EXIT
perf record -q -o "$data" --call-graph dwarf,8192 -F 1999 \
    "$bin" bench "$scene" --threads 1 --modes "$mode" --sets "$set" --reps 3 "$@" >/dev/null 2>&1
perf script -i "$data" -F ip,sym --inline 2>/dev/null | python3 "$here/classify_perf.py"
