#!/usr/bin/env python3
"""Tessera's ray queries against Embree's one-ray and packet queries, from C++, on the same rays, one thread.

    cargo build --release
    pip install mitsuba          # ships libembree3 and its headers; g++ builds the C++ side
    python3 scenes/references/bench_embree_packets.py [--scene scenes/glass/glass.gltf] [--rays 500000]
                                                      [--runs 3] [--pairs 3]

Runs `tessera bench rays --scene S --accel obvhs --no-batches --dump DIR` (a path tracer's incoherent
rays off the scene's surfaces: closest-hit rays in cosine directions, occlusion rays toward points on other triangles),
builds `embree_packets.cpp` against the Embree 3 that Mitsuba 3 ships (the library its llvm_ad_rgb
wavefronts call, in packets of the JIT's width) and traces the same rays through it one at a time
(rtcIntersect1, rtcOccluded1) and in packets of 8 and 16 consecutive rays. --pairs alternations of
the two programs; medians. Closest-hit counts are checked equal.

Why: `bench_embree.py` times Embree through embreex's Cython loop, whose per-ray cost is part of its
figure, and `bench_mitsuba_rays.py` times Mitsuba's wavefront, which adds Dr.Jit's kernels. This is
Embree alone. On rays this incoherent, Embree's packets of 8 run its hybrid kernel's one-ray walk
(`perf` shows `BVHNIntersectorKHybrid::intersect1`), so the packet-of-8 column is Embree's one-ray
walk without `rtcIntersect1`'s per-call cost: the figure for Tessera's own one-ray walk to meet
(docs/performance-journal.md, ninth round).
"""
import argparse
import os
import statistics
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from equal_time import TESSERA  # noqa: E402


def build(out_dir):
    import mitsuba
    lib = os.path.dirname(mitsuba.__file__)
    if not os.path.exists(os.path.join(lib, "libembree3.so")):
        sys.exit(f"no libembree3.so in {lib}: this Mitsuba build has no Embree")
    exe = os.path.join(out_dir, "embree_packets")
    subprocess.run(["g++", "-O2", "-std=c++17", "-o", exe, os.path.join(HERE, "embree_packets.cpp"),
                    "-I", os.path.join(lib, "include"), "-L", lib, "-l:libembree3.so", f"-Wl,-rpath,{lib}"],
                   check=True)
    return exe


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default=os.path.join(HERE, "..", "glass", "glass.gltf"))
    ap.add_argument("--rays", type=int, default=500_000)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--pairs", type=int, default=3)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        exe = build(tmp)
        ours = {"closest": [], "occluded": []}
        embree = {}
        hits = {}
        for p in range(a.pairs):
            out = subprocess.run([TESSERA, "bench", "rays", "--scene", a.scene, "--rays", str(a.rays),
                                  "--runs", str(a.runs), "--accel", "obvhs", "--no-batches"] + (["--dump", tmp] if p == 0 else []),
                                 check=True, capture_output=True, text=True).stdout
            for line in out.splitlines():
                f = line.split()
                if f and f[0] == "obvhs":
                    ours["closest"].append(float(f[2]))
                    ours["occluded"].append(float(f[3]))
                    hits["tessera"] = int(line.split("(")[1].split()[0])
            got = subprocess.run([exe, tmp, str(a.runs)], check=True, capture_output=True, text=True).stdout
            for line in got.splitlines():
                name, rate, count = line.split()
                embree.setdefault(name, []).append(float(rate))
                hits[name] = int(count)
    if not ours["closest"]:
        sys.exit("no obvhs row in tessera bench rays' output")
    bad = [k for k in ("closest1", "closest8", "closest16") if hits.get(k) != hits.get("tessera")]
    med = {k: statistics.median(v) for k, v in {**ours, **embree}.items()}
    print(f"{os.path.basename(a.scene)}: {a.rays} rays off its surfaces, 1 thread, medians of {a.pairs} "
          f"alternations of {a.runs} runs")
    print(f"{'query':<10} {'tessera':>9} {'embree 1':>9} {'embree 8':>9} {'embree 16':>10}   "
          f"tessera over embree 1 / 8 / 16")
    for q in ("closest", "occluded"):
        t, e1, e8, e16 = med[q], med[q + "1"], med[q + "8"], med[q + "16"]
        print(f"{q:<10} {t:>9.3f} {e1:>9.3f} {e8:>9.3f} {e16:>10.3f}   {t / e1:.2f}x / {t / e8:.2f}x / {t / e16:.2f}x")
    print(f"closest hits: tessera {hits.get('tessera')}, embree {hits.get('closest1')} / {hits.get('closest8')} / "
          f"{hits.get('closest16')}")
    if bad:
        sys.exit(f"closest-hit counts differ from Tessera's for {bad}")


if __name__ == "__main__":
    main()
