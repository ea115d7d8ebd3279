#!/usr/bin/env python3
"""Instructions per ray of a callgrind listing, attributed by inlined function.

Our kernels inline everything into one function per batch call, so callgrind's per-function
costs say nothing about where inside a ray the instructions go. This tool reads a listing of
`tools/callgrind-listing.sh` ("runs-per-ray address: instruction" lines), asks `addr2line`
for each address's inline chain (debug info: release builds keep it), and sums the runs per ray
by the innermost three functions of the chain (e.g. `test_known < traverse_loop < traverse`)
and by source line.

    tools/callgrind-listing.sh SCENE diffuse rebraided 'packets::intersect' > rb.lst
    tools/listing-by-function.py rb.lst target/release/rebraid [--top 40]

The listing and the binary must come from the same build. Needs `addr2line` (binutils).
"""
import argparse
import collections
import re
import subprocess


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("listing")
    ap.add_argument("binary")
    ap.add_argument("--top", type=int, default=40)
    a = ap.parse_args()
    rows = []
    for line in open(a.listing):
        m = re.match(r"\s*([0-9.]+) ([0-9a-f]+): ", line)
        if m:
            rows.append((float(m.group(1)), m.group(2).lstrip("0")))
    out = subprocess.run(
        ["addr2line", "-e", a.binary, "-a", "-f", "-i", "-C"] + ["0x" + addr for _, addr in rows],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split("\n")
    # Per address: "0xADDR", then (function, file:line) pairs, innermost first.
    frames = collections.defaultdict(list)
    cur = None
    for line in out:
        if line.startswith("0x"):
            cur = line[2:].lstrip("0")
        elif cur is not None and line:
            frames[cur].append(line)
    by_chain = collections.Counter()
    by_line = collections.Counter()
    for runs, addr in rows:
        f = frames.get(addr, [])
        pairs = list(zip(f[0::2], f[1::2]))
        if not pairs:
            continue
        where = re.sub(r" \(discriminator.*", "", re.sub(r".*/src/", "", pairs[0][1]))
        by_line[where] += runs
        chain = " < ".join(re.sub(r"<.*?>", "", fn).split("::")[-1] for fn, _ in pairs[:3])
        by_chain[chain] += runs
    print(f"{sum(r for r, _ in rows):.1f} instructions per ray in the listing")
    for k, v in by_chain.most_common(a.top):
        print(f"{v:8.1f} {k}")
    print("--- by source line")
    for k, v in by_line.most_common(a.top):
        print(f"{v:8.1f} {k}")


if __name__ == "__main__":
    main()
