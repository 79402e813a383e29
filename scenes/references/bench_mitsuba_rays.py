#!/usr/bin/env python3
"""Tessera's ray queries against Mitsuba 3's on the same triangles and the same rays, one thread.

    cargo build --release
    pip install mitsuba numpy; apt-get install libllvm19
    python3 scenes/references/bench_mitsuba_rays.py [--scene scenes/glass/glass.gltf] [--rays 1000000] [--runs 3]

Runs `tessera bench rays --scene S --accel obvhs --no-batches --dump DIR` (a path tracer's rays off the
scene's surfaces: closest-hit rays in cosine directions, occlusion rays toward points on other
triangles), then loads the dumped triangles into a Mitsuba 3 scene (one mesh, variant llvm_ad_rgb, one
Dr.Jit thread) and traces all the rays as one wavefront, as Mitsuba's path tracer does:
`Scene.ray_intersect_preliminary` (distance, triangle and barycentrics, what Tessera's closest-hit
query returns) and `Scene.ray_test`, timed after a warm-up (the LLVM backend compiles its kernels on
the first call), median of --runs. Mitsuba hands such wavefronts to Embree in packets;
bench_embree.py's embreex loop is Embree one ray at a time.

`--vector-width N` (4, 8 or 16) sets Dr.Jit's LLVM vector width, and with it the packet width Mitsuba hands
Embree (`rtcIntersect4/8/16`); by default Dr.Jit takes the host's widest (16 with AVX-512).

Why: issue 15 compares whole renders with Mitsuba's llvm_ad_rgb; this splits off the ray engine. It
prints both engines' Mrays/s, the ratio, and checks that they found the same hits (ray_agreement.py).
"""
import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from equal_time import TESSERA  # noqa: E402
from ray_agreement import disagreeing, finish  # noqa: E402

LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM-19.so"
if os.path.exists(LLVM):
    os.environ.setdefault("DRJIT_LIBLLVM_PATH", LLVM)


def set_vector_width(dr, width):
    """Sets Dr.Jit's LLVM vector width (None: leave it), keeping the host's CPU and features, through
    drjit-core's C entry points (Python exposes no setter; the names are its C++ symbols, so another
    Dr.Jit may lack them); returns the width in force, or None where it cannot be read and none was
    asked for."""
    import ctypes
    try:
        lib = ctypes.CDLL(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so"))
        lib._Z19jit_llvm_target_cpuv.restype = ctypes.c_char_p
        lib._Z24jit_llvm_target_featuresv.restype = ctypes.c_char_p
        lib._Z21jit_llvm_vector_widthv.restype = ctypes.c_uint32
        if width is not None:
            lib._Z19jit_llvm_set_targetPKcS0_j(lib._Z19jit_llvm_target_cpuv(), lib._Z24jit_llvm_target_featuresv(),
                                               ctypes.c_uint32(width))
        return lib._Z21jit_llvm_vector_widthv()
    except (OSError, AttributeError) as e:
        if width is not None:
            raise RuntimeError(f"cannot set Dr.Jit's vector width with this drjit ({e})") from e
        return None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default=os.path.join(HERE, "..", "glass", "glass.gltf"))
    ap.add_argument("--rays", type=int, default=1_000_000)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--vector-width", type=int, choices=[4, 8, 16],
                    help="Dr.Jit's LLVM vector width = Embree's packet width (default: the host's widest)")
    a = ap.parse_args()

    import drjit as dr
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    dr.set_thread_count(1)
    width = set_vector_width(dr, a.vector_width)
    print(f"Dr.Jit LLVM vector width {width} (Embree packets of {width})")

    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run([TESSERA, "bench", "rays", "--scene", a.scene, "--rays", str(a.rays),
                              "--runs", str(a.runs), "--accel", "obvhs", "--no-batches", "--dump", tmp],
                             check=True, capture_output=True, text=True)
        print(out.stdout, end="")
        tess = None
        for line in out.stdout.splitlines():
            f = line.split()
            if f and f[0] == "obvhs":
                tess = (float(f[2]), float(f[3]))
        if tess is None:
            sys.exit("no obvhs row in tessera bench rays' output")
        load = lambda name, cols: np.fromfile(os.path.join(tmp, name), dtype="<f4").reshape(-1, cols)  # noqa: E731
        verts, orig, dirs = load("vertices.f32", 3), load("origins.f32", 3), load("directions.f32", 3)
        shadow_dirs, shadow_tmax = load("shadow_directions.f32", 3), load("shadow_tmax.f32", 1).ravel()
        t_tess = load("t_closest.f32", 1).ravel()

    # The dump lists each triangle's three corners: one mesh of unshared vertices.
    mesh = mi.Mesh("dump", vertex_count=len(verts), face_count=len(verts) // 3,
                   has_vertex_normals=False, has_vertex_texcoords=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(verts.ravel())
    params["faces"] = mi.UInt32(np.arange(len(verts), dtype=np.uint32))
    params.update()
    scene = mi.load_dict({"type": "scene", "mesh": mesh})
    col = lambda v: [v[:, 0], v[:, 1], v[:, 2]]  # noqa: E731
    ray = mi.Ray3f(mi.Point3f(*col(orig)), mi.Vector3f(*col(dirs)))
    shadow = mi.Ray3f(mi.Point3f(*col(orig)), mi.Vector3f(*col(shadow_dirs)))
    shadow.maxt = mi.Float(shadow_tmax)
    dr.eval(ray, shadow)
    dr.sync_thread()

    closest, occluded = [], []
    for run in range(a.runs + 1):
        c0 = time.process_time()
        t0 = time.perf_counter()
        si = scene.ray_intersect_preliminary(ray)
        dr.eval(si.t, si.prim_index, si.prim_uv)
        dr.sync_thread()
        s = time.perf_counter() - t0
        t1 = time.perf_counter()
        blocked = scene.ray_test(shadow)
        dr.eval(blocked)
        dr.sync_thread()
        s_occ = time.perf_counter() - t1
        cpu = time.process_time() - c0
        if run > 0:
            closest.append(len(orig) / s / 1e6)
            occluded.append(len(orig) / s_occ / 1e6)
            if cpu > 1.5 * (s + s_occ):
                print(f"warning: run {run} used {cpu:.3f} s of CPU in {s + s_occ:.3f} s: more than one thread")
    t_mi = np.asarray(si.t, dtype=np.float64)  # the last run's distances (every run finds the same)
    mit = (statistics.median(closest), statistics.median(occluded))
    print(f"{'mitsuba llvm':<16} {'':>10} {mit[0]:>16.3f} {mit[1]:>16.3f}  (wavefront of {len(orig)} rays)")

    hit = np.isfinite(t_mi) & (t_mi < 1e30)
    bad = disagreeing(hit, t_mi, t_tess)
    print(f"hits agree: {len(orig) - bad.sum()} of {len(orig)} rays ({int(hit.sum())} Mitsuba hits, "
          f"{int(np.isfinite(t_tess).sum())} Tessera hits)")
    print(f"tessera obvhs over mitsuba llvm: closest-hit rays/s {tess[0] / mit[0]:.2f}x, "
          f"occlusion rays/s {tess[1] / mit[1]:.2f}x")
    finish(bad, t_mi, t_tess, "mitsuba")


if __name__ == "__main__":
    main()
