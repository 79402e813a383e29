#!/usr/bin/env python3
"""Writes moving_light.gltf: an emissive 0.2-wide square moving from x = -1 (t = 0) to x = +1 (t = 1)
above a grey floor, seen by a camera that rises from y = 0 to y = 0.5 over the same second (two
animations, "move" and "crane", LINEAR). The farm's frame tests render it (issue 13).

    python3 scenes/animation/make_moving_light.py
"""
import base64
import json
import os
import struct

HERE = os.path.dirname(os.path.abspath(__file__))


def f32(*v):
    return struct.pack(f"<{len(v)}f", *v)


def main():
    bin = b"".join([
        f32(-0.1, -0.1, 0, 0.1, -0.1, 0, 0.1, 0.1, 0, -0.1, 0.1, 0),       # 0: square
        f32(-5, -1, -5, 5, -1, -5, 5, -1, 2, -5, -1, 2),                  # 48: floor
        f32(0, 1),                                                         # 96: key times
        f32(-1, 0, 0, 1, 0, 0),                                            # 104: square path
        f32(0, 0, 5, 0, 0.5, 5),                                           # 128: camera path
        struct.pack("<6I", 0, 1, 2, 0, 2, 3),                              # 152: indices
    ])
    views = [(0, 48), (48, 48), (96, 8), (104, 24), (128, 24), (152, 24)]
    doc = {
        "asset": {"version": "2.0", "generator": "scenes/animation/make_moving_light.py"},
        "scene": 0,
        "scenes": [{"nodes": [0, 1, 2]}],
        "nodes": [{"mesh": 0, "name": "light"}, {"mesh": 1, "name": "floor"},
                  {"camera": 0, "translation": [0, 0, 5], "name": "camera"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 5, "material": 0}]},
                   {"primitives": [{"attributes": {"POSITION": 1}, "indices": 5, "material": 1}]}],
        "materials": [{"emissiveFactor": [1, 1, 1], "doubleSided": True,
                       "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 20}},
                       "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1]}},
                      {"pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1], "metallicFactor": 0}}],
        "extensionsUsed": ["KHR_materials_emissive_strength"],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "aspectRatio": 1.0, "znear": 0.1}}],
        "animations": [
            {"name": "move", "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}],
             "samplers": [{"input": 2, "output": 3, "interpolation": "LINEAR"}]},
            {"name": "crane", "channels": [{"sampler": 0, "target": {"node": 2, "path": "translation"}}],
             "samplers": [{"input": 2, "output": 4, "interpolation": "LINEAR"}]},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [-0.1, -0.1, 0], "max": [0.1, 0.1, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC3", "min": [-5, -1, -5], "max": [5, -1, 2]},
            {"bufferView": 2, "componentType": 5126, "count": 2, "type": "SCALAR", "min": [0], "max": [1]},
            {"bufferView": 3, "componentType": 5126, "count": 2, "type": "VEC3"},
            {"bufferView": 4, "componentType": 5126, "count": 2, "type": "VEC3"},
            {"bufferView": 5, "componentType": 5125, "count": 6, "type": "SCALAR"},
        ],
        "bufferViews": [{"buffer": 0, "byteOffset": o, "byteLength": n} for o, n in views],
        "buffers": [{"byteLength": len(bin),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(bin).decode()}],
    }
    with open(os.path.join(HERE, "moving_light.gltf"), "w") as f:
        json.dump(doc, f, indent=1)


if __name__ == "__main__":
    main()
