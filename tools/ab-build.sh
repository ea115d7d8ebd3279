#!/usr/bin/env bash
# Build-time A/B of `rebraid` binaries, with the baseline run again as a control.
#
#   tools/ab-build.sh ROUNDS "SCENE..." BASE OTHER... [BASE]
#   e.g. tools/ab-build.sh 6 "../shared/scenes/nexuiz_ons_reborn.obj library" \
#            base/rebraid new/rebraid base/rebraid
#
# Each round runs every binary once per scene, in the order given: one `rebraid bench` process
# per run, which builds the scene `--reps 5` times (after an untimed warm-up build) and reports
# the median. Prints per scene and mode the median over rounds of each binary's build time
# divided by the first binary's in the same round, and each binary's median build time
# (objects + top level) in milliseconds. A binary may be a wrapper script that adds options
# (`exec rebraid "$@" --merge-placed`). Why the control: see `tools/ab-wall.sh`; a change is
# resolved only where its ratio stands clear of the control's. Environment: MODES (default
# rebraided), THREADS (1), PIN (a command prefix), EXTRA (more `rebraid bench` options, e.g.
# "--scale 3" for the built-in library scene).
set -euo pipefail
# shellcheck source=tools/ab-runs.sh
. "$(dirname "$0")/ab-runs.sh"
rounds=$1 scenes=$2
shift 2
bins=("$@")
modes=${MODES:-rebraided} threads=${THREADS:-1}
d=$(mktemp -d)
trap 'rm -rf "$d"' EXIT
ab_runs "$d" "$rounds" "$scenes" --modes "$modes" --sets diffuse --threads "$threads" --reps 5 \
    --width 16 --height 16
python3 - "$d" "${#bins[@]}" <<'PY'
import collections, glob, json, os, statistics, sys

d, nb = sys.argv[1], int(sys.argv[2])
runs = collections.defaultdict(dict)  # (scene, mode, round) -> binary -> (total, objects, top)
for f in glob.glob(os.path.join(d, "*.json")):
    k, i, _ = os.path.basename(f).split(".", 2)
    for line in open(f):
        j = json.loads(line)
        runs[(j["scene"], j["mode"], i)][int(k)] = (
            j["build_ms_total"], j["build_ms_objects"], j["build_ms_top"])
by_scene = collections.defaultdict(list)
for (scene, mode, _), v in runs.items():
    by_scene[(scene, mode)].append(v)
print(f"{'scene':<25}{'mode':<11}" + "".join(f"bin{k}/bin0  " for k in range(1, nb))
      + "  median ms (objects + top) per binary")
for (scene, mode), rs in sorted(by_scene.items()):
    ratios = [statistics.median(r[k][0] / r[0][0] for r in rs) for k in range(1, nb)]
    ms = [tuple(statistics.median(r[k][c] for r in rs) for c in range(3)) for k in range(nb)]
    print(f"{scene:<25}{mode:<11}" + "".join(f"{x:<11.3f}" for x in ratios) + "  "
          + "  ".join(f"{a:.1f} ({b:.1f} + {c:.1f})" for a, b, c in ms))
PY
