#!/usr/bin/env python3
"""A bush of alpha-masked leaves: the cut-out case of Blender and game assets (foliage, fences),
where a ray passes many cut-away layers before it stops. Leaf quads at random places and
orientations in a 3 × 2.4 × 3 box over a grey floor, lit by a quad lamp above, each leaf an
ellipse drawn in a 64² RGBA texture whose alpha is 0 outside it (about a third of the quad is
leaf); `alphaMode` MASK, BLEND with `--blend` (the leaf's alpha `--leaf-alpha`, 255 by default, so
that the two modes render the same image), or OPAQUE with `--opaque` (every quad solid).

    python3 scenes/references/make_foliage.py --leaves 3000 -o /tmp/foliage.gltf
    tessera render /tmp/foliage.gltf --width 128 --height 96 --spp 256 --threads 1

(docs/performance-journal.md, thirty-ninth round, quotes renders of 3 000 and 40 000 leaves.)
"""
import argparse
import base64
import json
import math
import struct
import zlib

import numpy as np


def png_rgba(a):
    """An 8-bit RGBA PNG of the array `a` (rows × columns × 4)."""
    raw = b"".join(b"\0" + a[y].tobytes() for y in range(a.shape[0]))

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", a.shape[1], a.shape[0], 8, 6, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--leaves", type=int, default=3000, help="leaf quads (two triangles each)")
    ap.add_argument("--opaque", action="store_true", help="OPAQUE leaves: every quad solid")
    ap.add_argument("--blend", action="store_true", help="BLEND leaves (stochastic transparency) instead of MASK")
    ap.add_argument("--leaf-alpha", type=int, default=255, help="the leaf's alpha inside its ellipse, 0-255")
    ap.add_argument("--copies", type=int, default=1,
                    help="the bush placed this many times side by side, as instances of one mesh (two-level BVH)")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("-o", "--output", required=True, help="glTF file to write (buffers and texture embedded)")
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    pos, uv, idx = [], [], []
    for _ in range(a.leaves):
        c = rng.uniform([-1.5, 0.3, -1.5], [1.5, 2.7, 1.5])
        e1 = rng.normal(size=3)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(e1, rng.normal(size=3))
        e2 /= np.linalg.norm(e2)
        base = len(pos)
        for (s, t) in [(0, 0), (1, 0), (1, 1), (0, 1)]:
            pos.append(c + (s - 0.5) * 0.3 * e1 + (t - 0.5) * 0.3 * e2)
            uv.append((s, t))
        idx += [base, base + 1, base + 2, base, base + 2, base + 3]
    pos, uv, idx = np.array(pos, "<f4"), np.array(uv, "<f4"), np.array(idx, "<u4")
    side = 64
    yy, xx = np.mgrid[0:side, 0:side]
    leaf = ((xx - 31.5) / 30) ** 2 + ((yy - 31.5) / 14) ** 2 <= 1
    img = np.zeros((side, side, 4), np.uint8)
    img[..., 0], img[..., 1], img[..., 2] = 60, 140, 40
    img[..., 3] = 255 if a.opaque else np.where(leaf, a.leaf_alpha, 0)
    quad = np.array([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], "<f4")
    quad_idx = np.array([0, 2, 1, 0, 3, 2], "<u4")

    blobs, views, accessors = [], [], []

    def view(data, target=None):
        offset = sum(len(b) for b in blobs)
        blobs.append(data + b"\0" * (-len(data) % 4))
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(data), **({"target": target} if target else {})})
        return len(views) - 1

    def accessor(arr, kind, component, target, bounds=False):
        acc = {"bufferView": view(arr.tobytes(), target), "componentType": component,
               "count": int(arr.size if kind == "SCALAR" else arr.shape[0]), "type": kind}
        if bounds:
            acc["min"], acc["max"] = arr.min(0).tolist(), arr.max(0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    leaf_pos = accessor(pos, "VEC3", 5126, 34962, True)
    leaf_uv = accessor(uv, "VEC2", 5126, 34962)
    leaf_idx = accessor(idx, "SCALAR", 5125, 34963)
    quad_pos = accessor(quad, "VEC3", 5126, 34962, True)
    quad_tris = accessor(quad_idx, "SCALAR", 5125, 34963)
    image = view(png_rgba(img))
    leaf_material = {"name": "leaf", "doubleSided": True,
                     "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0, "roughnessFactor": 1}}
    if not a.opaque:
        leaf_material["alphaMode"] = "BLEND" if a.blend else "MASK"
    tilt = math.atan2(1.5, 6.0)
    data = b"".join(blobs)
    gltf = {
        "asset": {"version": "2.0", "generator": "scenes/references/make_foliage.py"},
        "extensionsUsed": ["KHR_materials_emissive_strength"],
        "buffers": [{"byteLength": len(data),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode()}],
        "bufferViews": views,
        "accessors": accessors,
        "images": [{"bufferView": image, "mimeType": "image/png"}],
        "textures": [{"source": 0}],
        "materials": [
            {"name": "floor", "pbrMetallicRoughness": {"baseColorFactor": [0.7, 0.7, 0.7, 1],
                                                       "metallicFactor": 0, "roughnessFactor": 1}},
            leaf_material,
            {"name": "lamp", "emissiveFactor": [1, 1, 1], "pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1]},
             "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 10}}},
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": quad_pos}, "indices": quad_tris, "material": 0}]},
                   {"primitives": [{"attributes": {"POSITION": leaf_pos, "TEXCOORD_0": leaf_uv},
                                    "indices": leaf_idx, "material": 1}]},
                   {"primitives": [{"attributes": {"POSITION": quad_pos}, "indices": quad_tris, "material": 2}]}],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.01}}],
        "nodes": [{"mesh": 0, "scale": [4 * a.copies, 1, 4]}]
        + [{"mesh": 1, "translation": [3.2 * (k - (a.copies - 1) / 2), 0, 0]} for k in range(a.copies)]
        + [{"mesh": 2, "translation": [0, 5, 0], "rotation": [1, 0, 0, 0], "scale": [a.copies, 1, 1]},
           {"camera": 0, "translation": [0, 3, 6 * a.copies],
            "rotation": [-math.sin(tilt / 2), 0, 0, math.cos(tilt / 2)]}],
        "scenes": [{"nodes": list(range(3 + a.copies))}],
        "scene": 0,
    }
    with open(a.output, "w") as f:
        json.dump(gltf, f)
    mode = "opaque" if a.opaque else "BLEND" if a.blend else "MASK"
    print(f"{a.output}: {a.leaves} leaves ({2 * a.leaves} triangles), {mode}")


if __name__ == "__main__":
    main()
