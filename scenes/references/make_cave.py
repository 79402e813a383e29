#!/usr/bin/env python3
"""A large enclosed scene for measuring ray throughput in whole renders: the inside of a bumpy
icosphere (`tessera bench rays --level L`'s mesh, 20·4^L triangles, displaced radially) lit by a
small quad light, camera inside. Paths stay in it (~10 rays a path at level 7), so most rays
traverse a BVH that does not fit in cache — the case `accel::BATCH_RAYS_ABOVE` batches rays for.

    python3 scenes/references/make_cave.py --level 7 -o /tmp/cave.gltf
    tessera render /tmp/cave.gltf --spp 8 --width 160 --height 90 --threads 1

(ARCHITECTURE.md, "Rays traced in batches", quotes renders of the level-7 cave.)
"""
import argparse
import base64
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from equal_time import TESSERA  # noqa: E402  (the binary the other scripts use)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--level", type=int, default=7, help="icosphere subdivision level (7: 327 680 triangles)")
    ap.add_argument("-o", "--output", required=True, help="glTF file to write (buffers embedded)")
    ap.add_argument("--mask", action="store_true",
                    help="every material alphaMode MASK (alpha 1: nothing is cut away, but every ray takes the "
                         "cut-out code path)")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([TESSERA, "bench", "rays", "--level", str(a.level), "--rays", "1", "--runs", "1",
                        "--accel", "obvhs", "--no-batches", "--dump", tmp], check=True, capture_output=True)
        v = np.fromfile(os.path.join(tmp, "vertices.f32"), dtype="<f4").reshape(-1, 3)
    n = v / np.linalg.norm(v, axis=1, keepdims=True)
    bump = 1.0 + 0.08 * np.sin(9 * n[:, 0:1]) * np.sin(7 * n[:, 1:2]) * np.sin(11 * n[:, 2:3])
    v = (n * bump * 2.0).astype("<f4")
    light = np.array([[-0.3, 1.5, -0.3], [0.3, 1.5, -0.3], [0.3, 1.5, 0.3],
                      [-0.3, 1.5, -0.3], [0.3, 1.5, 0.3], [-0.3, 1.5, 0.3]], dtype="<f4")
    data = v.tobytes() + light.tobytes()

    def accessor(view, arr):
        return {"bufferView": view, "componentType": 5126, "count": len(arr), "type": "VEC3",
                "min": arr.min(0).tolist(), "max": arr.max(0).tolist()}

    gltf = {
        "asset": {"version": "2.0", "generator": "scenes/references/make_cave.py"},
        "buffers": [{"byteLength": len(data),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": v.nbytes},
                        {"buffer": 0, "byteOffset": v.nbytes, "byteLength": light.nbytes}],
        "accessors": [accessor(0, v), accessor(1, light)],
        "materials": [
            {"name": "rock", "pbrMetallicRoughness": {"baseColorFactor": [0.7, 0.7, 0.7, 1],
                                                      "metallicFactor": 0, "roughnessFactor": 1}},
            {"name": "light", "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1]},
             "emissiveFactor": [1, 1, 1],
             "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 20}}},
        ],
        "extensionsUsed": ["KHR_materials_emissive_strength"],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "material": 0}]},
                   {"primitives": [{"attributes": {"POSITION": 1}, "material": 1}]}],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 1.0, "znear": 0.01, "aspectRatio": 1.777}}],
        "nodes": [{"mesh": 0}, {"mesh": 1}, {"camera": 0, "translation": [0, -0.5, 1.2]}],
        "scenes": [{"nodes": [0, 1, 2]}],
        "scene": 0,
    }
    if a.mask:
        for m in gltf["materials"]:
            m["alphaMode"] = "MASK"
    with open(a.output, "w") as f:
        json.dump(gltf, f)
    print(f"{a.output}: {len(v) // 3} cave triangles + a 2-triangle light")


if __name__ == "__main__":
    main()
