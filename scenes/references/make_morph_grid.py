#!/usr/bin/env python3
"""An animated scene whose geometry is posed every frame: a wavy floor of N×N quads (2·N² world
triangles) with one morph target (a ripple) whose weight goes 0 → 1 over 24 frames, a lamp and a
camera. Its BVH is built anew at every frame (posed vertices are world triangles), so it measures
what a frame's pose costs a farm worker.

    python3 scenes/references/make_morph_grid.py --quads 300 -o grid.gltf
    TESSERA_LOG=renderer=debug tessera render grid.gltf --frames 1-4 --width 64 --height 48 --spp 1
"""
import argparse
import base64
import json
import math
import struct


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quads", type=int, default=300, help="quads a side (2·N² triangles)")
    ap.add_argument("-o", "--output", required=True)
    a = ap.parse_args()
    n = a.quads
    pos, delta, idx = [], [], []
    for j in range(n + 1):
        for i in range(n + 1):
            x, z = -2 + 4 * i / n, -2 + 4 * j / n
            pos += [x, 0.05 * math.sin(3 * x) * math.cos(2 * z), z]
            delta += [0.0, 0.15 * math.sin(7 * x + 5 * z), 0.0]
    for j in range(n):
        for i in range(n):
            v = j * (n + 1) + i
            idx += [v, v + n + 1, v + 1, v + 1, v + n + 1, v + n + 2]
    # The lamp: a quad above, facing down.
    lamp = [-0.5, 2.0, -0.5, 0.5, 2.0, -0.5, 0.5, 2.0, 0.5, -0.5, 2.0, 0.5]
    lamp_idx = [0, 1, 2, 0, 2, 3]
    times = [0.0, 1.0]
    weights = [0.0, 1.0]
    blobs = [
        struct.pack(f"<{len(pos)}f", *pos),
        struct.pack(f"<{len(delta)}f", *delta),
        struct.pack(f"<{len(idx)}I", *idx),
        struct.pack(f"<{len(lamp)}f", *lamp),
        struct.pack(f"<{len(lamp_idx)}I", *lamp_idx),
        struct.pack("<2f", *times),
        struct.pack("<2f", *weights),
    ]
    data, views, offset = b"", [], 0
    for b in blobs:
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(b)})
        data += b + b"\0" * ((-len(b)) % 4)
        offset = len(data)
    nv = (n + 1) ** 2
    lo = [min(pos[k::3]) for k in range(3)]
    hi = [max(pos[k::3]) for k in range(3)]
    dlo = [min(delta[k::3]) for k in range(3)]
    dhi = [max(delta[k::3]) for k in range(3)]
    acc = [
        {"bufferView": 0, "componentType": 5126, "count": nv, "type": "VEC3", "min": lo, "max": hi},
        {"bufferView": 1, "componentType": 5126, "count": nv, "type": "VEC3", "min": dlo, "max": dhi},
        {"bufferView": 2, "componentType": 5125, "count": len(idx), "type": "SCALAR"},
        {"bufferView": 3, "componentType": 5126, "count": 4, "type": "VEC3", "min": [-0.5, 2.0, -0.5], "max": [0.5, 2.0, 0.5]},
        {"bufferView": 4, "componentType": 5125, "count": 6, "type": "SCALAR"},
        {"bufferView": 5, "componentType": 5126, "count": 2, "type": "SCALAR", "min": [0.0], "max": [1.0]},
        {"bufferView": 6, "componentType": 5126, "count": 2, "type": "SCALAR"},
    ]
    g = {
        "asset": {"version": "2.0", "generator": "make_morph_grid.py"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [
            {"name": "grid", "mesh": 0},
            {"name": "lamp", "mesh": 1},
            {"name": "camera", "camera": 0, "translation": [0.0, 2.5, 4.0], "rotation": [-0.2588, 0.0, 0.0, 0.9659]},
        ],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.01}}],
        "meshes": [
            {"primitives": [{"attributes": {"POSITION": 0}, "indices": 2, "material": 0, "targets": [{"POSITION": 1}]}], "weights": [0.0]},
            {"primitives": [{"attributes": {"POSITION": 3}, "indices": 4, "material": 1}]},
        ],
        "materials": [
            {"pbrMetallicRoughness": {"baseColorFactor": [0.7, 0.7, 0.7, 1], "metallicFactor": 0, "roughnessFactor": 1}},
            {"emissiveFactor": [1, 1, 1], "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 10}}, "doubleSided": True},
        ],
        "extensionsUsed": ["KHR_materials_emissive_strength"],
        "animations": [{"channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}],
                        "samplers": [{"input": 5, "output": 6, "interpolation": "LINEAR"}]}],
        "buffers": [{"byteLength": len(data), "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode()}],
        "bufferViews": views,
        "accessors": acc,
    }
    with open(a.output, "w") as f:
        json.dump(g, f)


if __name__ == "__main__":
    main()
