#!/usr/bin/env python3
"""Group a per-instruction listing by how often each instruction runs per ray.

Reads the output of `tools/callgrind-listing.sh` or `tools/callgrind-embree-listing.sh` on
stdin ("count-per-ray address: instruction" lines) and prints, for each distinct count, the
number of instructions that run that often and their cost per ray, largest first. A kernel's
parts separate by their counts: the node test's instructions all run "inner nodes per ray"
times, a leaf's entry "leaves per ray" times, a block test "blocks per ray" times, the ray's
set-up once. So the two kernels can be compared part by part:

    tools/callgrind-listing.sh SCENE diffuse flat intersect_packets_avx2 | tools/listing-groups.py
    tools/callgrind-embree-listing.sh SCENE diffuse embree-flat | tools/listing-groups.py
"""
import collections
import re
import signal
import sys


def main() -> None:
    # Piped into `head`: stop quietly when the reader closes the pipe.
    signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    top = int(sys.argv[1]) if len(sys.argv) > 1 else 16
    cost, count = collections.Counter(), collections.Counter()
    total = 0.0
    for line in sys.stdin:
        m = re.match(r"\s*([0-9.]+) [0-9a-f]+: ", line)
        if not m:
            continue
        c = float(m.group(1))
        cost[c] += c
        count[c] += 1
        total += c
    print(f"{total:.1f} instructions per ray")
    print(f"  {'runs per ray':>12} {'instructions':>12} {'per ray':>8}")
    for c, v in cost.most_common(top):
        print(f"  {c:12.2f} {count[c]:12d} {v:8.1f}")


if __name__ == "__main__":
    main()
