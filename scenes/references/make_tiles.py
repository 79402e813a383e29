#!/usr/bin/env python3
"""A floor under a grid of small square tiles, as a glTF for `tessera bench rays --scene`.

    python3 scenes/references/make_tiles.py OUT.gltf [--grid 100] [--tilt 0.0]

The scene `accel::tests::floor_and_tiles` builds in memory (docs/performance-journal.md, thirtieth round): a
20 × 20 floor of two triangles facing up, and `grid`² tiles, each two triangles facing down, at
height 3 + tilt·((7i + 3j) mod 5). It is the shape of scene (a ground under many small objects)
where obvhs' medium PLOC build makes a poor tree and another build's is clearly cheaper by the
SAH cost (`accel::build_candidates`): `bench rays --scene OUT.gltf` times the rays on the tree the
build chose. Not a suite scene: nothing in it is lit.
"""
import argparse
import base64
import json
import struct


def tiles(grid, tilt):
    lo, hi = -10.0, 10.0
    # Counter-clockwise seen from above: the floor's normal is +y.
    tris = [[(lo, 0, lo), (lo, 0, hi), (hi, 0, hi)], [(lo, 0, lo), (hi, 0, hi), (hi, 0, lo)]]
    step = (hi - lo) / grid
    for i in range(grid):
        for j in range(grid):
            x, z = lo + (i + 0.5) * step, lo + (j + 0.5) * step
            y, h = 3.0 + tilt * ((i * 7 + j * 3) % 5), step * 0.2

            def corner(a, b):
                return (x + a * h, y, z + b * h)

            # Clockwise seen from above: the tiles face down, towards the floor.
            tris.append([corner(-1, -1), corner(1, 1), corner(-1, 1)])
            tris.append([corner(-1, -1), corner(1, -1), corner(1, 1)])
    return tris


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--grid", type=int, default=100)
    ap.add_argument("--tilt", type=float, default=0.0)
    a = ap.parse_args()
    tris = tiles(a.grid, a.tilt)
    data = b"".join(struct.pack("<3f", *v) for t in tris for v in t)
    lows = [min(v[k] for t in tris for v in t) for k in range(3)]
    highs = [max(v[k] for t in tris for v in t) for k in range(3)]
    gltf = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1]}],
        "nodes": [{"mesh": 0}, {"camera": 0, "translation": [0, 1.5, 12]}],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.01}}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [0.7, 0.7, 0.7, 1], "metallicFactor": 0,
                                                "roughnessFactor": 1}}],
        "buffers": [{"byteLength": len(data),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode()}],
        "bufferViews": [{"buffer": 0, "byteLength": len(data)}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3 * len(tris), "type": "VEC3",
                       "min": lows, "max": highs}],
    }
    with open(a.out, "w") as f:
        json.dump(gltf, f)
    print(f"{a.out}: {len(tris)} triangles")


if __name__ == "__main__":
    main()
