#!/usr/bin/env python3
"""Where each renderer's time goes, Tessera against Mitsuba 3 `llvm_ad_rgb`, one thread, at each
renderer's own SIMD width: ray queries against everything else, in seconds per render.

    cargo build --release
    apt-get install linux-perf libllvm19; pip install mitsuba
    python3 scenes/references/time_peers.py [--spp 256] [--max-depth N] [scenes...]

Why: `bench_peers.py` gives each renderer's paths/s and `count_peers.py` the instructions both
execute at equal width (eight lanes, under valgrind); neither says, on a host with AVX-512 where
Dr.Jit runs sixteen lanes, whether the time gap lies in the ray queries or in the rest of a path
(sampling, shading, light choice), which call for different remedies. `perf record -e cpu-clock`
(a software event: it works in VMs without hardware counters) samples both at full width.

Tessera: `tessera render … --threads 1` under perf; each sample is counted by the function it
falls in (the kernel's callees are functions of their own: `Accel::intersect_nodes_lanes`, ...):
ray queries are `accel::`, `triangle::`, `ray_bundle::`, `solid_surface::`, `convex_solid::` and
the scene's batch entry points (`Scene::intersect_surface_batch`, `visibility_batch`,
`visibility`); light choice is `light::`, `light_tree::`, `alias::`, `bulb::`; the rest of
`renderer::` is the path (sample sets, shading, film). Samples outside the renderer (loading,
writing the EXR, the kernel) are left out, and the three parts are scaled to the render time
Tessera reports.

Mitsuba: a process loads the scene (make_references.py's translation, as bench_peers.py), renders
once to fill Dr.Jit's kernel cache, then waits; perf attaches to it for `--renders` timed
renders only. Samples in libembree3 are its ray queries, samples in anonymous executable memory
Dr.Jit's compiled kernels, and the rest (Python, Dr.Jit's tracing of the program each render,
libraries) are "other"; OpenBLAS's idle thread is left out. Scaled to the renders' measured time.

The columns "queries" and "rest" then compare like with like: our ray queries against Embree's,
and our path's other work (light choice included) against Dr.Jit's kernels and Mitsuba's
per-render overhead.
"""
import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import make_references as mr  # noqa: E402
from equal_time import TESSERA  # noqa: E402

LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM-19.so"

QUERIES = ("renderer::accel::", "renderer::triangle::", "renderer::ray_bundle::", "renderer::solid_surface::",
           "renderer::convex_solid::", "renderer::wide_node::", "renderer::cwbvh_node::",
           "renderer::scene::Scene::intersect_surface_batch", "renderer::scene::Scene::visibility")
LIGHTS = ("renderer::light::", "renderer::light_tree::", "renderer::alias::", "renderer::bulb::")

# Loads the scene, renders once, says "ready", waits for a line on stdin, renders `renders` times
# on one thread and prints their mean seconds.
MITSUBA_RUN = r"""
import os, sys, tempfile, time
sys.path.insert(0, {here!r})
import drjit as dr, mitsuba as mi
import make_references as mr
from bench_mitsuba_rays import set_vector_width
mi.set_variant("llvm_ad_rgb")
width = set_vector_width(dr, None)
rel, w, h = {rel!r}, {w}, {h}
with tempfile.TemporaryDirectory() as tmp:
    scene = mi.load_dict(mr.build_scene(os.path.join(mr.ROOT, rel), w, h, {spp}, tmp, {env!r},
                                        max_depth={max_depth}))
    # After loading: with one thread set before it, Mitsuba's EXR reading hangs (bench_peers.py).
    dr.set_thread_count(1)
    dr.eval(mi.render(scene, seed=0, spp={spp}))
    print("ready", width, flush=True)
    sys.stdin.readline()
    t0 = time.perf_counter()
    for i in range({renders}):
        dr.eval(mi.render(scene, seed=1 + i, spp={spp}))
    print("seconds", (time.perf_counter() - t0) / {renders}, flush=True)
"""


def perf_samples(data, sort):
    """{key: samples} of a perf.data file, by `sort` (symbol or dso,symbol)."""
    p = subprocess.run(["perf", "report", "-i", data, "--no-children", "--sort", sort, "-F", f"sample,{sort}",
                        "--stdio", "-q"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, check=True)
    rows = Counter()
    for line in p.stdout.splitlines():
        parts = line.split(None, 1)
        if len(parts) == 2 and parts[0].isdigit():
            rows[parts[1].strip()] += int(parts[0])
    return rows


def tessera(name, w, h, spp, max_depth, tmp):
    rel = mr.SCENES[name][0]
    env_args = mr.tessera_env_args(name)
    data = os.path.join(tmp, "tessera.data")
    cmd = [TESSERA, "render", os.path.join(mr.ROOT, rel), "-o", os.path.join(tmp, "t.exr"), "--spp", str(spp),
           "--width", str(w), "--height", str(h), "--threads", "1", "--max-depth", str(max_depth), *env_args]
    p = subprocess.run(["perf", "record", "-q", "-e", "cpu-clock", "-F", "4999", "-o", data, "--", *cmd],
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if p.returncode != 0:
        sys.exit(f"perf record of {TESSERA} failed:\n{p.stderr[-2000:]}")
    seconds = float(p.stderr.split("rendered ")[1].split(" in ")[1].split("s ")[0])
    parts = Counter()
    for sym, n in perf_samples(data, "symbol").items():
        sym = sym.split("] ", 1)[-1]
        if any(q in sym for q in QUERIES):
            parts["queries"] += n
        elif any(q in sym for q in LIGHTS):
            parts["lights"] += n
        elif "renderer::" in sym:
            parts["path"] += n
    total = sum(parts.values())
    if total == 0:
        sys.exit(f"{name}: no samples in the renderer's functions")
    return {k: seconds * parts[k] / total for k in ("queries", "lights", "path")} | {"seconds": seconds}


def mitsuba(name, w, h, spp, max_depth, renders, tmp):
    rel = mr.SCENES[name][0]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    env.setdefault("DRJIT_LIBLLVM_PATH", LLVM)
    code = MITSUBA_RUN.format(here=HERE, rel=rel, w=w, h=h, spp=spp, env=mr.ENVIRONMENTS.get(name),
                              renders=renders, max_depth=max_depth)
    child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             text=True, env=env)
    ready = child.stdout.readline().split()
    if not ready or ready[0] != "ready":
        child.kill()
        sys.exit(f"{name}: the Mitsuba process did not start ({ready})")
    data = os.path.join(tmp, "mitsuba.data")
    perf = subprocess.Popen(["perf", "record", "-q", "-e", "cpu-clock", "-F", "4999", "-o", data, "-p",
                             str(child.pid)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(0.5)  # perf attached before the renders begin
    child.stdin.write("go\n")
    child.stdin.flush()
    line = child.stdout.readline().split()
    child.wait()
    perf.send_signal(signal.SIGINT)
    perf.wait()
    if len(line) != 2 or line[0] != "seconds":
        sys.exit(f"{name}: the Mitsuba renders failed ({line})")
    if not os.path.exists(data):
        sys.exit(f"{name}: perf did not attach to the Mitsuba process (perf_event_paranoid?)")
    seconds = float(line[1])
    parts = Counter()
    for key, n in perf_samples(data, "dso,symbol").items():
        if "blas_thread_server" in key:
            continue
        if key.startswith("libembree"):
            parts["embree"] += n
        elif key.startswith("[JIT]") or key.startswith("[unknown]") or key.startswith("perf-"):
            parts["jit"] += n
        else:
            parts["other"] += n
    total = sum(parts.values())
    return {k: seconds * parts[k] / total for k in ("embree", "jit", "other")} | {
        "seconds": seconds, "width": int(ready[1])}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--renders", type=int, default=3, help="timed Mitsuba renders under perf (default 3)")
    ap.add_argument("--max-depth", type=int, default=mr.TESSERA_MAX_DEPTH,
                    help="bounces for both renderers, as in bench_peers.py (default 64)")
    ap.add_argument("scenes", nargs="*", default=list(mr.SCENES))
    a = ap.parse_args()
    if shutil.which("perf") is None:
        sys.exit("time_peers.py needs perf (Debian: apt-get install linux-perf)")
    if not os.path.exists(TESSERA):
        sys.exit(f"no Tessera binary at {TESSERA} (cargo build --release, or set TESSERA_BIN)")
    depth = "" if a.max_depth == mr.TESSERA_MAX_DEPTH else f", at most {a.max_depth} bounces"
    print(f"seconds per render at each reference's size, {a.spp} spp, one thread{depth} (perf cpu-clock samples); "
          f"Tessera: {TESSERA}")
    print(f"{'scene':<14} {'tessera':>8} {'queries':>8} {'lights':>7} {'path':>7}   {'mitsuba':>8} {'embree':>7} "
          f"{'jit':>7} {'other':>6} {'lanes':>5}   {'ours/theirs':>11} {'queries':>8} {'rest':>6}")
    with tempfile.TemporaryDirectory() as tmp:
        for name in a.scenes:
            _, w, h = mr.SCENES[name]
            t = tessera(name, w, h, a.spp, a.max_depth, tmp)
            m = mitsuba(name, w, h, a.spp, a.max_depth, a.renders, tmp)
            rest_ours, rest_theirs = t["lights"] + t["path"], m["jit"] + m["other"]
            print(f"{name:<14} {t['seconds']:>8.3f} {t['queries']:>8.3f} {t['lights']:>7.3f} {t['path']:>7.3f}   "
                  f"{m['seconds']:>8.3f} {m['embree']:>7.3f} {m['jit']:>7.3f} {m['other']:>6.3f} {m['width']:>5}   "
                  f"{t['seconds'] / m['seconds']:>11.2f} {t['queries'] / m['embree']:>8.2f} "
                  f"{rest_ours / rest_theirs:>6.2f}", flush=True)
    print("ours/theirs: Tessera's seconds over Mitsuba's; queries: our ray queries over Embree's; rest: our "
          "light choice and path over Dr.Jit's kernels and Mitsuba's other per-render work")


if __name__ == "__main__":
    main()
