#!/usr/bin/env bash
# Wall-clock A/B of `rebraid` binaries, with the baseline run again as a control.
#
#   tools/ab-wall.sh ROUNDS "SCENE..." BASE OTHER... [BASE]
#   e.g. tools/ab-wall.sh 20 "../shared/scenes/samurai_monastery.obj ../shared/scenes/2CylinderEngine.glb" \
#            base/rebraid new/rebraid base/rebraid
#
# Each round runs every binary once per scene, in the order given (one `rebraid bench` process
# per run, one thread unless THREADS says otherwise), and prints per scene, mode and ray set the
# median over rounds of each binary's Mrays/s divided by the first binary's in the same round,
# and the ratio of the best runs. Why the control: on this shared machine the same binary
# against itself strays from 1.0 by up to 10% in such medians, and a binary's position in the
# round biases it (docs/performance.md, session 23); a change is resolved only where its ratio
# stands clear of the control's. Environment: MODES (default rebraided,flat), SETS (diffuse), W
# and H (480x270), REPS (1, repetitions inside each process, median), THREADS (1), PIN (a
# command prefix, e.g. "taskset -c 1"), EXTRA (more `rebraid bench` options, e.g. "--scale 3"
# for the built-in library scene).
set -euo pipefail
# shellcheck source=tools/ab-runs.sh
. "$(dirname "$0")/ab-runs.sh"
rounds=$1 scenes=$2
shift 2
bins=("$@")
modes=${MODES:-rebraided,flat} sets=${SETS:-diffuse} w=${W:-480} h=${H:-270} reps=${REPS:-1}
threads=${THREADS:-1}
d=$(mktemp -d)
trap 'rm -rf "$d"' EXIT
ab_runs "$d" "$rounds" "$scenes" --modes "$modes" --sets "$sets" --threads "$threads" \
    --reps "$reps" --width "$w" --height "$h"
python3 - "$d" "$sets" "${#bins[@]}" <<'PY'
import collections, glob, json, os, statistics, sys
d, sets, nb = sys.argv[1], sys.argv[2].split(","), int(sys.argv[3])
runs = collections.defaultdict(dict)  # (scene, mode, set) -> {(bin, round): Mrays/s}
for f in glob.glob(d + "/*.json"):
    k, i, _ = os.path.basename(f).split(".", 2)
    for line in open(f):
        j = json.loads(line)
        for s in sets:
            runs[(j["scene"], j["mode"], s)][(int(k), int(i))] = j[s]["mrays_per_s"]
print(f"{'scene':24} {'mode':10} {'set':8} " + "  ".join(f"bin{b}/bin0 median (best)" for b in range(1, nb)))
for key in sorted(runs):
    r = runs[key]
    rounds = sorted({i for (_, i) in r})
    cols = []
    for b in range(1, nb):
        q = [r[(b, i)] / r[(0, i)] for i in rounds if (b, i) in r and (0, i) in r]
        best = max(v for (k, _), v in r.items() if k == b) / max(v for (k, _), v in r.items() if k == 0)
        cols.append(f"{statistics.median(q):.3f} ({best:.3f})".ljust(24))
    print(f"{key[0][:24]:24} {key[1]:10} {key[2]:8} " + "  ".join(cols))
PY
