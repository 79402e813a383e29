#!/usr/bin/env python3
"""Tessera's ray queries against Embree 4 on the same triangles and the same rays, one thread.

    cargo build --release
    pip install embreex numpy
    python3 scenes/references/bench_embree.py [--level 8] [--rays 1000000] [--runs 5]
    python3 scenes/references/bench_embree.py --scene scenes/glass/glass.gltf [--rays ...] [--runs ...]

Runs `tessera bench rays --dump DIR` (icosphere of 20·4^level triangles, incoherent rays from
inside it; Tessera's build time and Mrays/s for obvhs' CWBVH, wide and compressed nodes, and the own BVH2,
and for the obvhs rows the same rays traced as batches, as renders of large scenes trace them), then loads the
dumped vertices and rays into Embree 4 through embreex (rtcIntersect1 / rtcOccluded1 per ray in
embreex's Cython loop, one thread) and prints Embree's build time and Mrays/s beside Tessera's,
with their ratio. With `--scene` the workload is `tessera bench rays --scene`'s instead: a path
tracer's rays off the scene's surfaces (closest-hit rays in cosine directions, occlusion rays toward
points on other triangles, each with its own length), so small scenes' ray queries are compared
too. It also checks that both engines found the same hits: the closest-hit distances must agree
to 1e-4 relative, and a ray one engine finds no hit for must be a miss in the other; disagreeing
rays are counted and the first five printed, and more than one in 10⁴ fails the script (it did
on scenes/veach/veach.gltf until rays were lifted off their triangle's plane, `SurfacePoint::
plane_error`: 1 019 rays off its large tilted plate hit that plate again at t ≈ 10⁻⁷ for Tessera,
behind the origin in exact arithmetic; now all 10⁶ agree; see ARCHITECTURE.md, Correctness).
(With Möller-Trumbore, at level 8, 7 of 10⁶ rays slipped between two triangles that Embree
reports as hit; the watertight test agrees on all.)
The Embree figures include embreex's per-ray cost in its Cython loop; bench_embree_packets.py times
Embree from C++ (one ray at a time and in packets) on `--scene` workloads.
Embree's build time is scene and mesh creation plus a first one-ray query (embreex commits, i.e.
builds, the scene lazily there), with Embree's default build quality and its own threads.
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


def main():
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    ap = argparse.ArgumentParser()
    ap.add_argument("--level", type=int, default=8)
    ap.add_argument("--rays", type=int, default=1_000_000)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--scene", help="a glTF scene: its surface rays instead of the icosphere's")
    a = ap.parse_args()
    workload = ["--scene", a.scene] if a.scene else ["--level", str(a.level)]
    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run([TESSERA, "bench", "rays", *workload, "--rays", str(a.rays),
                              "--runs", str(a.runs), "--dump", tmp], check=True, capture_output=True, text=True)
        print(out.stdout, end="")
        tess = {}
        kind = None
        for line in out.stdout.splitlines():
            f = line.split()
            if f and f[0] in ("obvhs", "obvhs-compressed", "own"):
                kind = f[0]
                tess[kind] = (float(f[1]), float(f[2]), float(f[3]))
            elif kind and f[:2] == ["batch", "of"]:
                # Rays traced as a batch (what renders of large scenes do): no build of their own.
                tess[f"{kind}, batch of {f[2]}"] = (None, float(f[3]), float(f[4]))
        verts = np.fromfile(os.path.join(tmp, "vertices.f32"), dtype="<f4").reshape(-1, 3, 3)
        orig = np.fromfile(os.path.join(tmp, "origins.f32"), dtype="<f4").reshape(-1, 3)
        dirs = np.fromfile(os.path.join(tmp, "directions.f32"), dtype="<f4").reshape(-1, 3)
        t_tess = np.fromfile(os.path.join(tmp, "t_closest.f32"), dtype="<f4")
        if a.scene:
            shadow_dirs = np.fromfile(os.path.join(tmp, "shadow_directions.f32"), dtype="<f4").reshape(-1, 3)
            shadow_tmax = np.fromfile(os.path.join(tmp, "shadow_tmax.f32"), dtype="<f4")
        else:
            # From inside the sphere every ray reaches it before 10.
            shadow_dirs, shadow_tmax = dirs, np.full(len(orig), 10.0, dtype=np.float32)

    t0 = time.perf_counter()
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, verts)
    scene.run(orig[:1], dirs[:1], output=1)  # commits (builds) the BVH
    build = time.perf_counter() - t0
    closest, occluded = [], []
    res = None
    for run in range(a.runs + 1):
        t0 = time.perf_counter()
        res = scene.run(orig, dirs, output=1)
        s = time.perf_counter() - t0
        t0 = time.perf_counter()
        scene.run(orig, shadow_dirs, dists=shadow_tmax, query="OCCLUDED")
        s_occ = time.perf_counter() - t0
        if run > 0:
            closest.append(len(orig) / s / 1e6)
            occluded.append(len(orig) / s_occ / 1e6)
    emb = (build, statistics.median(closest), statistics.median(occluded))
    print(f"{'embree 4':<16} {emb[0]:>10.3f} {emb[1]:>16.3f} {emb[2]:>16.3f}")

    t_emb = np.asarray(res["tfar"], dtype=np.float64)
    hit = np.asarray(res["primID"]) >= 0
    bad = disagreeing(hit, t_emb, t_tess)
    print(f"hits agree: {len(orig) - bad.sum()} of {len(orig)} rays (both miss, or closest t within 1e-4 relative;"
          f" {int(hit.sum())} hits)")
    for k, (b, c, o) in tess.items():
        build_ratio = f"build time {b / emb[0]:.2f}x, " if b is not None else ""
        print(f"tessera {k:<16} over embree: {build_ratio}closest-hit rays/s {c / emb[1]:.2f}x, "
              f"occlusion rays/s {o / emb[2]:.2f}x")
    finish(bad, t_emb, t_tess, "embree")


if __name__ == "__main__":
    main()
