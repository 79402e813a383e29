#!/usr/bin/env python3
"""Error versus time, Tessera against Mitsuba 3 `scalar_rgb`, on the scenes that have references.

    cargo build --release && python3 scenes/references/equal_time.py [--spp 4 16 64] [--runs 3]

For each scene and spp, renders with `tessera render` (default settings: mis, Sobol) and with Mitsuba
(path, independent sampler; the scene translation of make_references.py) at the reference's resolution,
takes the median render time (tessera's own report; mi.render() on a loaded scene) over --runs runs (different seeds), and the relMSE against the Mitsuba
reference: mean over pixels and channels of (x − ref)² / (ref² + 0.01). Prints a table and, from a
log-log fit of relMSE against time for each renderer, the time each needs to reach the same error.
"""
import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import make_references as mr  # noqa: E402

ROOT = os.path.dirname(mr.ROOT)
# TESSERA_BIN: another build to measure (e.g. the commit before a change, for before/after figures).
TESSERA = os.environ.get("TESSERA_BIN") or os.path.join(ROOT, "target", "release", "tessera")


def rel_mse(img, ref):
    return float(np.mean((img - ref) ** 2 / (ref ** 2 + 1e-2)))


def main():
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    ap = argparse.ArgumentParser()
    ap.add_argument("--spp", type=int, nargs="+", default=[4, 16, 64])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("scenes", nargs="*", default=list(mr.SCENES))
    a = ap.parse_args()
    for name in a.scenes:
        rel, w, h = mr.SCENES[name]
        ref = np.array(mi.Bitmap(os.path.join(mr.HERE, f"{name}.exr")), dtype=np.float64)[:, :, :3]
        rows = {"tessera": [], "mitsuba": []}
        with tempfile.TemporaryDirectory() as tmp:
            env = mr.ENVIRONMENTS.get(name)
            scene = mi.load_dict(mr.build_scene(os.path.join(mr.ROOT, rel), w, h, 1, tmp, env))
            env_args = mr.tessera_env_args(name)
            for spp in a.spp:
                tt, te, mt, me = [], [], [], []
                for r in range(a.runs):
                    out = os.path.join(tmp, "t.exr")
                    p = subprocess.run([TESSERA, "render", os.path.join(mr.ROOT, rel), "-o", out, "--spp", str(spp),
                                        "--width", str(w), "--height", str(h), "--seed", str(r), *env_args], check=True,
                                       stderr=subprocess.PIPE, text=True)
                    # Render time as tessera reports it (excludes process start, scene load, EXR write),
                    # the counterpart of timing mi.render() on an already loaded scene.
                    tt.append(float(p.stderr.split(" in ")[1].split("s ")[0]))
                    te.append(rel_mse(np.array(mi.Bitmap(out), dtype=np.float64)[:, :, :3], ref))
                    t0 = time.perf_counter()
                    img = np.array(mi.render(scene, seed=1000 + r, spp=spp), dtype=np.float64)[:, :, :3]
                    mt.append(time.perf_counter() - t0)
                    me.append(rel_mse(img, ref))
                rows["tessera"].append((spp, statistics.median(tt), statistics.median(te)))
                rows["mitsuba"].append((spp, statistics.median(mt), statistics.median(me)))
        print(f"\n{name} ({w}x{h}), median of {a.runs} runs")
        print(f"{'spp':>6} | {'tessera s':>10} {'relMSE':>10} | {'mitsuba s':>10} {'relMSE':>10}")
        for (spp, t1, e1), (_, t2, e2) in zip(rows["tessera"], rows["mitsuba"]):
            print(f"{spp:>6} | {t1:>10.3f} {e1:>10.3e} | {t2:>10.3f} {e2:>10.3e}")
        # Fit log(err) = a + b log(t) per renderer; time to reach the error Mitsuba has at its largest spp.
        fits = {}
        for k, v in rows.items():
            t = np.log([x[1] for x in v])
            e = np.log([x[2] for x in v])
            fits[k] = np.polyfit(t, e, 1)
        target = rows["mitsuba"][-1][2]
        if target > rows["tessera"][0][2]:
            # No extrapolation below the measured range: say what was measured.
            print(f"Tessera's {rows['tessera'][0][0]}-spp error ({rows['tessera'][0][2]:.3e}, {rows['tessera'][0][1]:.3f}s) "
                  f"is already below Mitsuba's {rows['mitsuba'][-1][0]}-spp error ({target:.3e}, {rows['mitsuba'][-1][1]:.3f}s)")
            continue
        tt = {k: float(np.exp((np.log(target) - f[1]) / f[0])) for k, f in fits.items()}
        print(f"time to relMSE {target:.3e}: tessera {tt['tessera']:.3f}s, mitsuba {tt['mitsuba']:.3f}s, "
              f"ratio mitsuba/tessera {tt['mitsuba'] / tt['tessera']:.2f}")


if __name__ == "__main__":
    main()
