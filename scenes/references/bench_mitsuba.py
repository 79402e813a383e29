#!/usr/bin/env python3
"""Times Mitsuba 3 `scalar_rgb` on one of Tessera's scenes, for `tessera bench` comparisons.

    python3 scenes/references/bench_mitsuba.py cornell --spp 64 --width 256 --height 256 --runs 5

Same scene translation as make_references.py (path integrator, max_depth 65 = Tessera's 64 bounces,
rr_depth 5, box filter, independent sampler). Prints per-run and median wall time and Mpaths/s.
"""
import argparse
import os
import statistics
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import make_references as mr  # noqa: E402


def main():
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", choices=list(mr.SCENES))
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--runs", type=int, default=5)
    a = ap.parse_args()
    rel = mr.SCENES[a.scene][0]
    with tempfile.TemporaryDirectory() as tmp:
        scene = mi.load_dict(mr.build_scene(os.path.join(mr.ROOT, rel), a.width, a.height, a.spp, tmp))
        mi.render(scene, spp=a.spp)  # warm-up
        times = []
        for r in range(a.runs):
            t = time.perf_counter()
            mi.render(scene, seed=r, spp=a.spp)
            times.append(time.perf_counter() - t)
            print(f"run {r + 1}: {times[-1]:.3f}s  {a.width * a.height * a.spp / times[-1] / 1e6:.3f} Mpaths/s", flush=True)
    med = statistics.median(times)
    print(f"mitsuba {mi.__version__} scalar_rgb {a.scene} {a.width}x{a.height} {a.spp} spp: median {med:.3f}s "
          f"{a.width * a.height * a.spp / med / 1e6:.3f} Mpaths/s")


if __name__ == "__main__":
    main()
