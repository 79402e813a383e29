#!/usr/bin/env python3
"""A function's own instructions by source line, through inlining: where the SPMD kernel's time goes.

    valgrind --tool=callgrind --dump-instr=yes --toggle-collect='*render_tile_counted*' \\
        --callgrind-out-file=/tmp/cg.out target/release/tessera render scenes/cornell/cornell.gltf \\
        -o /tmp/x.exr --width 64 --height 48 --spp 16 --threads 1
    python3 scenes/references/callgrind_lines.py /tmp/cg.out target/release/tessera \\
        'spmd::radiance8' 'spmd.rs' [top]

`callgrind_annotate` charges an inlined helper's instructions to the helper's own file and line
(`lanes.rs`, `avx.rs`), which says nothing about which of the kernel's steps ran them. This charges
each instruction address of the functions whose name matches the third argument (their own cost,
not their callees') to the innermost frame of `addr2line -i` whose file matches the fourth: the
kernel's line that called the helper. Needs `addr2line` (binutils) and a build with line tables
(the release profile keeps them).
"""
import collections
import re
import subprocess
import sys


def own_cost_by_address(path, function):
    """{address: own instruction count} of the functions whose name matches `function`."""
    names, cost = {}, collections.Counter()
    current, address, call_cost_next = None, 0, False

    def name_of(spec):
        m = re.match(r"\((\d+)\)(?: (.*))?", spec)
        if not m:
            return spec
        if m.group(2):
            names[m.group(1)] = m.group(2)
        return names.get(m.group(1), spec)

    for line in open(path):
        line = line.rstrip("\n")
        if line.startswith("cfn="):
            name_of(line[4:])
            continue
        if line.startswith("fn="):
            current = name_of(line[3:])
            continue
        if line.startswith("calls="):
            # The next cost line is the call's inclusive cost: not this function's own.
            call_cost_next = True
            continue
        if not line or line[0] not in "+-*0":
            continue
        tokens = line.split()
        a = tokens[0]
        if a.startswith("0x"):
            address = int(a, 16)
        elif a[0] == "+":
            address += int(a[1:])
        elif a[0] == "-":
            address -= int(a[1:])
        elif a != "*":
            continue
        if call_cost_next:
            call_cost_next = False
            continue
        if current and re.search(function, current) and len(tokens) >= 3 and tokens[2].isdigit():
            cost[address] += int(tokens[2])
    return cost


def main():
    path, binary, function, source = sys.argv[1:5]
    top = int(sys.argv[5]) if len(sys.argv) > 5 else 40
    cost = own_cost_by_address(path, function)
    addresses = sorted(cost)
    out = subprocess.run(
        ["addr2line", "-a", "-i", "-e", binary] + [hex(a) for a in addresses], capture_output=True, text=True
    ).stdout
    by_line = collections.Counter()
    current, frames = None, []

    def charge():
        if current is None:
            return
        pick = next((f for f in frames if re.search(source, f)), frames[-1] if frames else "?")
        by_line[pick] += cost[current]

    for line in out.splitlines():
        if line.startswith("0x"):
            charge()
            current, frames = int(line, 16), []
        else:
            frames.append(line.split(" (discriminator")[0])
    charge()
    total = sum(cost.values())
    print(f"own instructions of /{function}/: {total}")
    for where, n in by_line.most_common(top):
        print(f"{n:12d} {100 * n / max(total, 1):5.1f} %  {where}")


if __name__ == "__main__":
    main()
