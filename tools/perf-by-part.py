#!/usr/bin/env python3
"""Join wall-clock samples with exact instruction counts, kernel part by kernel part.

`tools/callgrind-listing.sh` gives each instruction of a kernel with how often it runs per ray;
`tools/listing-groups.py` groups those counts into the kernel's parts (the set-up runs once per
ray, a node test "inner nodes per ray" times, a block test "blocks per ray" times). This script
puts `perf` samples (wall-clock time, `-e cpu-clock`) on the same instructions and prints, per
group, its share of the instructions beside its share of the samples: a part whose sample share
is well above its instruction share waits (on loads, on a division, on a mispredicted branch);
this virtual machine has no hardware counters to say which.

    tools/callgrind-listing.sh SCENE diffuse rebraided 'packets::intersect' > k.lst
    perf record -e cpu-clock -F 4999 -o k.perf target/release/rebraid bench SCENE \\
        --modes rebraided --sets diffuse --threads 1 --reps 15 --width 960 --height 540
    perf script -i k.perf -F ip,sym,symoff > k.samples
    tools/perf-by-part.py k.lst k.samples target/release/rebraid

Both must come from the same binary. The listing's addresses are the binary's; `perf` reports
run-time addresses of the position-independent executable, so the load offset is taken from
the first sample in a symbol that `nm` names exactly once.
"""
import collections
import re
import signal
import subprocess
import sys


def main() -> None:
    signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    listing, samples_path, binary = sys.argv[1:4]
    addrs = collections.defaultdict(list)
    nm = subprocess.run(["nm", "-C", binary], capture_output=True, text=True, check=True)
    for line in nm.stdout.splitlines():
        parts = line.split(" ", 2)
        if len(parts) == 3 and parts[0]:
            addrs[parts[2]].append(int(parts[0], 16))
    runs = {}
    for line in open(listing):
        m = re.match(r"\s*([0-9.]+) ([0-9a-f]+): ", line)
        if m:
            runs[int(m.group(2), 16)] = float(m.group(1))
    if not runs:
        sys.exit(f"{listing}: no listing lines")
    base, ips = None, []
    for line in open(samples_path):
        m = re.match(r"\s*([0-9a-f]+)\s+(.*)\+0x([0-9a-f]+)$", line.rstrip())
        if not m:
            continue
        ip, sym, off = int(m.group(1), 16), m.group(2), int(m.group(3), 16)
        if base is None and len(addrs.get(sym, [])) == 1:
            base = ip - (addrs[sym][0] + off)
        ips.append(ip)
    if base is None:
        sys.exit(f"{samples_path}: no sample in a symbol of {binary}")
    # Grouped by the listing's printed count (two decimals), as listing-groups.py groups.
    instr, samples = collections.Counter(), collections.Counter()
    for count in runs.values():
        instr[count] += count
    for ip in ips:
        count = runs.get(ip - base)
        if count is not None:
            samples[count] += 1
    total_i, total_s = sum(instr.values()), sum(samples.values())
    if total_s == 0:
        sys.exit("no sample fell on a listed instruction (listing and samples of one binary?)")
    print(f"{total_i:.1f} instructions per ray listed; {total_s} of {len(ips)} samples on them")
    print(f"  {'runs/ray':>8} {'instr/ray':>10} {'% instr':>8} {'% samples':>10} {'ratio':>6}")
    for count, n in sorted(instr.items(), key=lambda kv: -kv[1])[:20]:
        pi, ps = 100 * n / total_i, 100 * samples[count] / total_s
        print(f"  {count:8.2f} {n:10.1f} {pi:7.1f}% {ps:9.1f}% {ps / pi:6.2f}")


if __name__ == "__main__":
    main()
