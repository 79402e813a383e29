#!/usr/bin/env python3
"""relMSE at equal time for Tessera's technique switches, on the scenes that have Mitsuba references.

    cargo build --release && python3 scenes/references/switches.py [--spp 4 16 64] [--runs 3] [scene ...]

For each scene and switch (light sampler uniform/power/tree; environment sampling on/off where the scene
has an environment) it renders at each spp (median render time over --runs seeds, as tessera reports it)
and measures relMSE = mean((x − ref)² / (ref² + 0.01)) against the Mitsuba reference. From a log-log fit
of relMSE against time it prints the relMSE each switch reaches in the time the slowest-converging one
needs at its largest spp: the "equal time" column of docs and notes.
"""
import argparse
import os
import statistics
import subprocess
import sys
import tempfile

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import make_references as mr  # noqa: E402

TESSERA = os.path.join(os.path.dirname(mr.ROOT), "target", "release", "tessera")

SWITCHES = {
    "light sampler": [["--light-sampler", "uniform"], ["--light-sampler", "power"], ["--light-sampler", "tree"]],
    "env sampling": [["--env-sampling", "on"], ["--env-sampling", "off"]],
}


def read(path):
    import mitsuba as mi
    return np.array(mi.Bitmap(path), dtype=np.float64)[:, :, :3]


def main():
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    ap = argparse.ArgumentParser()
    ap.add_argument("--spp", type=int, nargs="+", default=[4, 16, 64])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("scenes", nargs="*", default=["cornell", "veach", "envlit", "many_lights"])
    a = ap.parse_args()
    for name in a.scenes:
        rel, w, h = mr.SCENES[name]
        ref = read(os.path.join(mr.HERE, f"{name}.exr"))
        env = mr.ENVIRONMENTS.get(name)
        base = [os.path.join(mr.ROOT, rel), "--width", str(w), "--height", str(h)]
        if env:
            base += ["--env", os.path.join(mr.ROOT, env[0]), "--env-rotate", str(env[1])]
        groups = ["light sampler"] + (["env sampling"] if env else [])
        for group in groups:
            fits, rows = {}, {}
            for sw in SWITCHES[group]:
                label = sw[1]
                rows[label] = []
                for spp in a.spp:
                    ts, es = [], []
                    with tempfile.TemporaryDirectory() as tmp:
                        for r in range(a.runs):
                            out = os.path.join(tmp, "x.exr")
                            p = subprocess.run([TESSERA, "render", *base, *sw, "--spp", str(spp), "--seed", str(r), "-o", out],
                                               check=True, stderr=subprocess.PIPE, text=True)
                            ts.append(float(p.stderr.split(" in ")[1].split("s ")[0]))
                            img = read(out)
                            es.append(float(np.mean((img - ref) ** 2 / (ref ** 2 + 1e-2))))
                    rows[label].append((spp, statistics.median(ts), statistics.median(es)))
                t = np.log([max(x[1], 1e-3) for x in rows[label]])
                e = np.log([x[2] for x in rows[label]])
                fits[label] = np.polyfit(t, e, 1)
            t_eq = max(v[-1][1] for v in rows.values())
            print(f"\n{name}: {group} ({w}x{h}, median of {a.runs})")
            print(f"{'switch':>10} | " + " | ".join(f"{s:>4} spp: time, relMSE" for s in a.spp) + f" | relMSE at {t_eq:.2f}s")
            for label, v in rows.items():
                cells = " | ".join(f"{tm:>6.3f}s {er:.3e}" for _, tm, er in v)
                at = float(np.exp(np.polyval(fits[label], np.log(t_eq))))
                print(f"{label:>10} | {cells} | {at:.3e}")


if __name__ == "__main__":
    main()
