#!/usr/bin/env python3
"""Tessera against Mitsuba 3 `llvm_ad_rgb` in executed instructions, at the same SIMD width, per render.

    cargo build --release
    apt-get install valgrind libllvm19; pip install mitsuba
    python3 scenes/references/count_peers.py [--scale 0.5] [--spp 16] [scenes...]

Why: on a shared machine a few-percent change drowns in the timings' spread, and on a host with
AVX-512 Dr.Jit runs sixteen lanes where our kernel runs eight, so a paths/s ratio mixes three
things: the work each renderer does, how fast the core retires it, and the width. Valgrind
answers the first exactly and on any host: it runs both programs on its own x86 model, which has
AVX2 and no AVX-512, so Dr.Jit's LLVM backend compiles its kernels eight lanes wide, as our
kernel is, and Embree picks its AVX2 code. The counts are the same every run (Tessera's
bit-exact; Mitsuba's within a few percent, its per-render Python and Dr.Jit bookkeeping varies).

Tessera: `valgrind --tool=callgrind tessera render … --threads 1` at the scene's reference size
times --scale and --spp samples; the inclusive count of `render_tile_counted` (every pixel's
paths, without loading, the BVH build, light preparation or writing the file), split into the
ray queries the SPMD kernel makes (closest-hit and occlusion batches and camera bundles), the
light choice, and the rest (sample sets, shading, film).

Mitsuba: a process that loads the scene (the translation of make_references.py, the same as
bench_peers.py) and renders it N times, under callgrind, for N = 1 and N = 3, after one
unmeasured process has filled Dr.Jit's kernel cache (seeds 0–2: a seed is compiled into the
kernel): half the difference is one render, with
scene loading and kernel compilation cancelled out. Split into Embree (its traversal and
intersection code and Mitsuba's rtcIntersect/rtcOccluded wrappers), Dr.Jit's compiled kernels
(code in anonymous executable memory) and the rest (Python, Dr.Jit's tracing of the program).

A ratio here is the instruction ratio at equal width; compare it with bench_peers.py's paths/s at
`--vector-width 8` to see whether a time gap is work (the ratios agree) or the core's rate.
"""
import argparse
import os
import re
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import make_references as mr  # noqa: E402
from equal_time import TESSERA  # noqa: E402

LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM-19.so"

# The ray queries of the SPMD kernel (`spmd::radiance8`); the light choice.
TRACING = ("renderer::scene::Scene::intersect_surface_batch", "renderer::scene::Scene::visibility_batch",
           "renderer::accel::Accel::intersect_bundle")
LIGHT_CHOICE = ("renderer::light::LightSet::select_batch",)

# A process that renders the scene `renders` times with Mitsuba's llvm_ad_rgb on one thread.
MITSUBA_RUN = r"""
import os, sys, tempfile
sys.path.insert(0, {here!r})
import drjit as dr, mitsuba as mi
import make_references as mr
from bench_mitsuba_rays import set_vector_width
mi.set_variant("llvm_ad_rgb")
print("width", set_vector_width(dr, None), flush=True)
rel, w, h = {rel!r}, {w}, {h}
with tempfile.TemporaryDirectory() as tmp:
    scene = mi.load_dict(mr.build_scene(os.path.join(mr.ROOT, rel), w, h, {spp}, tmp, {env!r},
                                        max_depth={max_depth}))
    # After loading: with one thread set before it, Mitsuba's EXR reading (the environment map)
    # hangs (bench_peers.py).
    dr.set_thread_count(1)
    for i in range({renders}):
        dr.eval(mi.render(scene, seed=i, spp={spp}))
"""


def callgrind(cmd, env=None, inclusive=True):
    """Runs `cmd` under callgrind; returns the annotate listing of every function (inclusive
    counts, or each function's own) and the program's output."""
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "cg.out")
        p = subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", *cmd],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        if p.returncode != 0:
            sys.exit(f"{' '.join(cmd[:3])}… failed under valgrind:\n{p.stderr[-2000:]}")
        # Run from "/": from a source tree's root callgrind_annotate shortens paths and then gave
        # other inclusive counts (half of some functions'). No source annotation: its counted
        # lines would read as more functions.
        annotate = ["callgrind_annotate", f"--inclusive={'yes' if inclusive else 'no'}", "--threshold=100",
                    "--auto=no", out]
        listing = subprocess.run(annotate, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                                 check=True, cwd="/").stdout
        return listing, p.stdout


def functions(listing):
    """{row: count} from a callgrind_annotate listing; a row is "source file:function [object]"
    (a function inlined from several files has a row for each)."""
    rows = {}
    for line in listing.splitlines():
        m = re.match(r"\s*([0-9,]+)\s+\([^)]*\)\s+(\S.*)$", line)
        if m:
            rows.setdefault(m.group(2).strip(), int(m.group(1).replace(",", "")))
    return rows


def pick(rows, name):
    """The inclusive count of the function `name`: the largest of its rows (the one that holds
    its calls; the others count only the code inlined from another file)."""
    return max((v for k, v in rows.items() if k.split(":", 1)[-1].startswith(name + " [")), default=0)


def tessera(name, w, h, spp, max_depth=mr.TESSERA_MAX_DEPTH):
    rel = mr.SCENES[name][0]
    env_args = mr.tessera_env_args(name)
    with tempfile.TemporaryDirectory() as tmp:
        listing, _ = callgrind([TESSERA, "render", os.path.join(mr.ROOT, rel), "-o", os.path.join(tmp, "t.exr"),
                                "--spp", str(spp), "--width", str(w), "--height", str(h), "--threads", "1",
                                "--max-depth", str(max_depth), *env_args])
    rows = functions(listing)
    total = pick(rows, "renderer::render::render_tile_counted")
    if total == 0:
        sys.exit(f"{TESSERA}: no render_tile_counted in callgrind's listing (a build without debug info?)")
    # A function the compiler inlined into its caller has no row of its own: say so rather than
    # count it as nothing (a scene whose kernel never calls one, e.g. no shadow rays, is also 0).
    for f in TRACING + LIGHT_CHOICE:
        if pick(rows, f) == 0:
            print(f"{name}: no row for {f} (inlined, or not called)", file=sys.stderr)
    tracing = sum(pick(rows, f) for f in TRACING)
    light = sum(pick(rows, f) for f in LIGHT_CHOICE)
    return {"total": total, "tracing": tracing, "light choice": light, "rest": total - tracing - light}


def mitsuba(name, w, h, spp, max_depth=mr.TESSERA_MAX_DEPTH):
    rel = mr.SCENES[name][0]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    env.setdefault("DRJIT_LIBLLVM_PATH", LLVM)

    def run(renders):
        code = MITSUBA_RUN.format(here=HERE, rel=rel, w=w, h=h, spp=spp, env=mr.ENVIRONMENTS.get(name),
                                  renders=renders, max_depth=max_depth)
        cmd = [sys.executable, "-c", code]
        listing, stdout = callgrind(cmd, env, inclusive=False)
        if "width 8" not in stdout:
            sys.exit(f"Dr.Jit did not run 8 lanes under valgrind ({stdout.strip()})")
        return functions(listing)

    # Fills Dr.Jit's kernel cache for valgrind's CPU model, for each seed the runs use (a seed is
    # part of the compiled kernel); under callgrind itself (a run under valgrind's `none` tool
    # did not fill it for callgrind's).
    run(3)
    one, three = run(1), run(3)
    # Each function's own instructions, so the parts add up to the whole.
    parts = {"embree": 0, "jit": 0, "other": 0}
    for k in set(one) | set(three):
        if k == "PROGRAM TOTALS" or "blas_thread_server" in k:
            continue
        d = (three.get(k, 0) - one.get(k, 0)) / 2
        if "embree" in k or "rtcIntersect" in k or "rtcOccluded" in k:
            parts["embree"] += d
        elif k.startswith("???:0x"):
            parts["jit"] += d
        else:
            parts["other"] += d
    parts["total"] = sum(parts.values())
    return parts


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scale", type=float, default=0.5, help="of each reference's resolution")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--max-depth", type=int, default=mr.TESSERA_MAX_DEPTH,
                    help="bounces for both renderers (Tessera's --max-depth; Mitsuba's max_depth less one): "
                         "0 counts a path's fixed costs (camera ray, first hit, film), 1 adds one bounce's "
                         "shading, light sample and two rays (default 64)")
    ap.add_argument("scenes", nargs="*", default=list(mr.SCENES))
    a = ap.parse_args()
    depth = "" if a.max_depth == mr.TESSERA_MAX_DEPTH else f", at most {a.max_depth} bounces"
    print(f"instructions per render (millions), both renderers eight lanes wide under valgrind, one thread{depth}; "
          f"Tessera: {TESSERA}")
    print(f"{'scene':<14} {'size':>9} {'tessera':>8} {'tracing':>8} {'lights':>7} {'rest':>7}   "
          f"{'mitsuba':>8} {'embree':>7} {'jit':>7} {'other':>6}   {'ours/theirs':>11} {'tracing':>8} "
          f"{'the rest':>8}")
    for name in a.scenes:
        _, rw, rh = mr.SCENES[name]
        w, h = max(8, round(rw * a.scale)), max(8, round(rh * a.scale))
        t = tessera(name, w, h, a.spp, a.max_depth)
        m = mitsuba(name, w, h, a.spp, a.max_depth)
        core = m["embree"] + m["jit"]
        M = 1e6
        print(f"{name:<14} {f'{w}x{h}x{a.spp}':>9} {t['total'] / M:>8.1f} {t['tracing'] / M:>8.1f} "
              f"{t['light choice'] / M:>7.1f} {t['rest'] / M:>7.1f}   {m['total'] / M:>8.1f} {m['embree'] / M:>7.1f} "
              f"{m['jit'] / M:>7.1f} {m['other'] / M:>6.1f}   {t['total'] / core:>11.2f} "
              f"{t['tracing'] / m['embree']:>8.2f} {(t['total'] - t['tracing']) / m['jit']:>8.2f}", flush=True)
    print("ours/theirs: Tessera's total over Mitsuba's Embree and kernels (its per-render Python and Dr.Jit "
          "bookkeeping left out); tracing: our ray queries over Embree; the rest: ours (light choice "
          "included) over Dr.Jit's kernels")


if __name__ == "__main__":
    main()
