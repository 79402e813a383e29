#!/usr/bin/env python3
"""Regenerates docs/speed-vs-accuracy.md and everything it shows, in one command:

    pip install mitsuba bpy==4.5.4 matplotlib numpy
    python3 docs/make_speed_vs_accuracy.py [--time-cap 4] [--runs 1]

1. `tessera bench convergence` over the scene suite (every technique switch; CSV, PNG, summary) into
   docs/speed-vs-accuracy/.
2. The same scenes rendered by Mitsuba 3 `scalar_rgb` (the scene translation of
   scenes/references/make_references.py) and by Blender Cycles (scenes/references/cycles_scene.py) at
   spp 1, 2, 4, ... under the same time cap, their relMSE measured against the same references with
   the same metric (luminance relMSE, ε = 0.01, renderer/src/noise.rs).
3. Equal-time tables and plots of the three renderers, and the markdown page around them.
Run it from anywhere; it works in the repository it lives in.
"""
import argparse
import csv
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

DOCS = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(DOCS)
OUT = os.path.join(DOCS, "speed-vs-accuracy")
sys.path.insert(0, os.path.join(ROOT, "scenes", "references"))
import make_references as mr  # noqa: E402

SUITE = ["cornell", "veach", "envlit", "many_lights", "glass"]
LUM = np.array([0.2126, 0.7152, 0.0722])


def rel_mse(img, ref):
    y, r = img @ LUM, ref @ LUM
    return float(np.mean((y - r) ** 2 / (r ** 2 + 0.01)))


def reference(mi, name):
    """The reference's RGB and its own expected relMSE (variance channel, same metric): subtracted
    from every measurement, since E[(x - r)^2] = var x + var r + bias^2."""
    b = mi.Bitmap(os.path.join(mr.HERE, f"{name}.exr"))
    a = np.array(b, dtype=np.float64)
    names = [b.struct_()[i].name for i in range(b.channel_count())]
    rgb = a[:, :, :3]
    y = rgb @ LUM
    own = float(np.mean(a[:, :, names.index("variance")] / (y ** 2 + 0.01)))
    return rgb, own


def resolved(points, own):
    """(spp, seconds, relMSE) points whose floor-subtracted relMSE stands clear of the reference's
    own noise (>= 1/4 of it), as tessera bench convergence marks them."""
    return [(s, t, e) for s, t, e in points if e > 0 and e >= 0.25 * own]


def ladder(render, cap, runs):
    """render(spp, seed) -> (seconds, image); spp doubles while the next render should fit in cap."""
    points, spp = [], 1
    while True:
        ts, imgs = [], []
        for r in range(runs):
            t, img = render(spp, r)
            ts.append(t)
            imgs.append(img)
        points.append((spp, statistics.median(ts), imgs))
        if 2 * points[-1][1] > cap or spp >= 1 << 16:
            return points
        spp *= 2


def error_at(points, t):
    """log-log interpolation of relMSE at time t over [(seconds, relMSE)], None outside."""
    for (t0, e0), (t1, e1) in zip(points, points[1:]):
        if t0 <= t <= t1:
            f = 0.0 if t1 <= t0 else (np.log(t) - np.log(t0)) / (np.log(t1) - np.log(t0))
            return float(np.exp(np.log(e0) * (1 - f) + np.log(e1) * f))
    return None


def time_to(points, err):
    """log-log interpolation of the time at which relMSE falls to err, None outside the range."""
    for (t0, e0), (t1, e1) in zip(points, points[1:]):
        if min(e0, e1) <= err <= max(e0, e1) and e0 != e1:
            f = (np.log(err) - np.log(e0)) / (np.log(e1) - np.log(e0))
            return float(np.exp(np.log(t0) * (1 - f) + np.log(t1) * f))
    return None


def fmt(x, spec=".3e"):
    return "-" if x is None else format(x, spec)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--time-cap", type=float, default=4.0)
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--skip-tessera", action="store_true", help="reuse docs/speed-vs-accuracy/convergence.csv")
    a = ap.parse_args()
    os.makedirs(OUT, exist_ok=True)
    tessera = os.path.join(ROOT, "target", "release", "tessera")
    if not a.skip_tessera:
        subprocess.run(["cargo", "build", "--release", "-p", "tessera-cli"], cwd=ROOT, check=True)
        subprocess.run([tessera, "bench", "convergence", "--time-cap", str(a.time_cap), "--runs", str(a.runs),
                        "--scenes-dir", os.path.join(ROOT, "scenes"), "-o", OUT], check=True)
    rows = list(csv.DictReader(open(os.path.join(OUT, "convergence.csv"))))

    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    import cycles_scene
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    results = {}  # scene -> renderer -> [(spp, seconds, relMSE less the reference's own)]
    floors = {}
    for name in SUITE:
        rel, w, h = mr.SCENES[name]
        gltf = os.path.join(mr.ROOT, rel)
        ref, own = reference(mi, name)
        floors[name] = own
        env = mr.ENVIRONMENTS.get(name)
        res = {}
        # Tessera: the defaults (mis, Sobol, auto light sampler, env sampling on) from the benchmark.
        res["Tessera"] = [(int(r["spp"]), float(r["seconds"]), float(r["rel_mse"])) for r in rows
                          if r["scene"] == name and r["switch"] == "integrator" and r["value"] == "mis"
                          and r["resolved"] == "true"]
        with tempfile.TemporaryDirectory() as tmp:
            scene = mi.load_dict(mr.build_scene(gltf, w, h, 1, tmp, env))

            def mitsuba(spp, seed):
                t0 = time.perf_counter()
                img = np.array(mi.render(scene, seed=1000 + seed, spp=spp), dtype=np.float64)[:, :, :3]
                return time.perf_counter() - t0, img

            pts = ladder(mitsuba, a.time_cap, a.runs)
            res["Mitsuba 3"] = resolved([(s, t, statistics.median(rel_mse(i, ref) for i in imgs) - own)
                                         for s, t, imgs in pts], own)
        cy = cycles_scene.CyclesScene(gltf, w, h, env=os.path.join(mr.ROOT, env[0]) if env else None)
        # Cycles' per-render overhead (scene sync, BVH build) is inside its times.
        pts = ladder(cy.render, a.time_cap, a.runs)
        res["Cycles"] = resolved([(s, t, statistics.median(rel_mse(i, ref) for i in imgs) - own)
                                  for s, t, imgs in pts], own)
        results[name] = res
        print(name, {k: v[-1] for k, v in res.items()}, flush=True)

    with open(os.path.join(OUT, "renderers.csv"), "w") as f:
        f.write("scene,renderer,spp,seconds,rel_mse\n")
        for name, res in results.items():
            for r, pts in res.items():
                for s, t, e in pts:
                    f.write(f"{name},{r},{s},{t:.6f},{e:.6e}\n")

    fig, axes = plt.subplots(1, len(SUITE), figsize=(4.2 * len(SUITE), 3.8))
    for ax, name in zip(axes, SUITE):
        for r, pts in results[name].items():
            ax.loglog([p[1] for p in pts], [p[2] for p in pts], "o-", ms=3, label=r)
        ax.set_title(name)
        ax.set_xlabel("render time, s")
        ax.grid(True, which="major", alpha=0.3)
    axes[0].set_ylabel("relMSE vs Mitsuba reference")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(os.path.join(OUT, "renderers.png"), dpi=90)

    write_page(a, rows, results, floors)


def write_page(a, rows, results, floors):
    L = []
    add = L.append
    add("# Speed against accuracy\n")
    add("What each rendering technique buys, on which kind of scene, and where Tessera stands against "
        "Mitsuba 3 and Cycles at equal time. Every number and plot on this page is regenerated by\n")
    add("```\npython3 docs/make_speed_vs_accuracy.py" + (f" --time-cap {a.time_cap:g}" if a.time_cap != 4 else "")
        + (f" --runs {a.runs}" if a.runs != 1 else "") + "\n```\n")
    add(f"(this machine: 2 cores, shared; time cap {a.time_cap:g} s per render, {a.runs} run(s) per point; "
        f"generated {time.strftime('%Y-%m-%d')}). Error is the relMSE of luminance against the Mitsuba "
        "reference of the scene (8192 spp, `scenes/references/`): mean over pixels of (Y − Y_ref)² / (Y_ref² + 0.01), "
        "the metric of `renderer/src/noise.rs`, less the reference's own expected relMSE (from its variance channel; "
        + ", ".join(f"{k} {v:.1e}" for k, v in floors.items())
        + "). Points within 4× of that floor are not resolvable and are left out (they stay in the CSVs). Efficiency = 1 / (relMSE × seconds): higher is better, and "
        "for an unbiased estimator it is roughly constant along a ladder, so it is the number to compare.\n")
    add("Raw data: [`convergence.csv`](speed-vs-accuracy/convergence.csv) (every technique switch), "
        "[`renderers.csv`](speed-vs-accuracy/renderers.csv) (Tessera, Mitsuba, Cycles), "
        "[`summary.md`](speed-vs-accuracy/summary.md).\n")

    add("## Tessera, Mitsuba 3 and Cycles at equal time\n")
    add("Tessera with its defaults (MIS, Owen-scrambled Sobol, auto light selection, environment sampling on); "
        "Mitsuba 3.9 `scalar_rgb` `path` integrator (independent sampler, its default); Cycles 4.5 (bpy) CPU, "
        "no denoising, no adaptive sampling, no clamping (scenes/references/cycles_scene.py). All use both cores. "
        "Times: Tessera's render call; `mi.render()` on a loaded scene; Cycles' `render.render()`, which also "
        "synchronises the scene and builds its BVH on every call (visible as its flat start at 1–4 spp).\n")
    add("![relMSE against time: Tessera, Mitsuba, Cycles](speed-vs-accuracy/renderers.png)\n")
    add("| scene | equal time | Tessera relMSE | Mitsuba relMSE | Cycles relMSE | target (reached by all) | "
        "time to target: Tessera | Mitsuba | Cycles | Tessera speed-up vs Mitsuba | vs Cycles |")
    add("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, res in results.items():
        tp = {r: [(p[1], p[2]) for p in pts] for r, pts in res.items()}
        t_eq = min(pts[-1][0] for pts in tp.values() if pts)
        errs = {r: error_at(p, t_eq) for r, p in tp.items()}
        # The error every renderer reached: the largest of their last resolved points.
        target = max(pts[-1][2] for pts in res.values() if pts)
        tt = {r: time_to(p, target) for r, p in tp.items()}
        def ratio(o):
            if tt[o] and tt["Tessera"]:
                return f"{tt[o] / tt['Tessera']:.2f}×"
            return "Tessera below it at 1 spp" if res["Tessera"][0][2] <= target else "-"
        add(f"| {name} | {t_eq:.2f} s | {fmt(errs['Tessera'])} | {fmt(errs['Mitsuba 3'])} | {fmt(errs['Cycles'])} | "
            f"{target:.3e} | {fmt(tt['Tessera'], '.2f')} s | {fmt(tt['Mitsuba 3'], '.2f')} s | "
            f"{fmt(tt['Cycles'], '.2f')} s | {ratio('Mitsuba 3')} | {ratio('Cycles')} |")
    add("\nA '-' is a point outside what was measured (no extrapolation). Cycles' relMSE floors where its image "
        "differs from Mitsuba's beyond noise (its Principled BSDF is not Mitsuba's `roughconductor`/`dielectric` "
        "for the rough metals and glass); Tessera's and Mitsuba's agree per pixel (renderer/tests/reference.rs).\n")

    add("## What each technique buys\n")
    add("Per scene, `tessera bench convergence` renders every switch value with the other settings at their "
        "defaults. The plots show relMSE (top) and efficiency (bottom) against time; the tables give relMSE at "
        "the longest time every value of a switch reached (interpolated log-log), and the ratio of the noise "
        "estimate to the true error at the largest spp.\n")
    by = {}
    for r in rows:
        if r["resolved"] != "true":
            continue
        by.setdefault(r["scene"], {}).setdefault(r["switch"], {}).setdefault(r["value"], []).append(
            (float(r["seconds"]), float(r["rel_mse"]), int(r["spp"]), r["est_rel_mse"]))
    best_lines = []
    for scene, switches in by.items():
        add(f"### {scene}\n")
        add(f"![{scene}](speed-vs-accuracy/{scene}.png)\n")
        add("| switch | value | relMSE at equal time | vs best | estimate / true at largest spp |")
        add("|---|---|---|---|---|")
        for sw, values in switches.items():
            t_eq = min(v[-1][0] for v in values.values())
            errs = {val: error_at([(p[0], p[1]) for p in pts], t_eq) for val, pts in values.items()}
            known = {k: e for k, e in errs.items() if e}
            best = min(known, key=known.get) if known else None
            for val, pts in values.items():
                last = pts[-1]
                ratio = f"{float(last[3]) / last[1]:.2f}" if last[3] else "-"
                vs = f"{errs[val] / known[best]:.2f}×" if errs[val] and best else "-"
                add(f"| {sw} | {val} | {fmt(errs[val])} (at {t_eq:.2f} s) | {vs} | {ratio} |")
            if best:
                best_lines.append((scene, sw, best, known))
        add("")

    add("## Findings and recommended defaults\n")
    add("Best value of each switch per scene at equal time (relMSE of the others relative to it):\n")
    add("| scene | switch | best | others |")
    add("|---|---|---|---|")
    for scene, sw, best, known in best_lines:
        others = ", ".join(f"{k} {e / known[best]:.2f}×" for k, e in known.items() if k != best)
        add(f"| {scene} | {sw} | {best} | {others} |")
    add("")
    add(open(os.path.join(DOCS, "speed-vs-accuracy.notes.md")).read())
    with open(os.path.join(DOCS, "speed-vs-accuracy.md"), "w") as f:
        f.write("\n".join(L) + "\n")
    print("wrote docs/speed-vs-accuracy.md")


if __name__ == "__main__":
    main()
