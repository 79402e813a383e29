#!/usr/bin/env python3
"""Writes Tessera's own test scenes as glTF 2.0 with embedded (data URI) buffers.

    python3 scenes/make_scenes.py        # rewrites scenes/cornell/cornell.gltf and scenes/veach/veach.gltf

Standard library only, so anyone can regenerate them. The geometry is exact (no randomness), so the
files are reproducible byte for byte.
"""
import base64
import json
import math
import os
import struct

HERE = os.path.dirname(os.path.abspath(__file__))


def sub(a, b): return [a[i] - b[i] for i in range(3)]
def add(a, b): return [a[i] + b[i] for i in range(3)]
def mul(a, s): return [a[i] * s for i in range(3)]
def dot(a, b): return sum(a[i] * b[i] for i in range(3))
def cross(a, b): return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
def norm(a):
    l = math.sqrt(dot(a, a))
    return [x / l for x in a]


def quad(c, u, v):
    """Quad centred at c spanning ±u, ±v; front face (counter-clockwise) along u × v."""
    p = [add(add(c, mul(u, -1)), mul(v, -1)), add(add(c, u), mul(v, -1)), add(add(c, u), v), add(add(c, mul(u, -1)), v)]
    return p, [(0, 1, 2), (0, 2, 3)]


def rot_y(deg):
    a = math.radians(deg)
    ca, sa = math.cos(a), math.sin(a)
    return lambda p: [ca * p[0] + sa * p[2], p[1], -sa * p[0] + ca * p[2]]


def cuboid(c, h, deg):
    """Closed box with outward-facing quads, rotated by deg about +Y."""
    R = rot_y(deg)
    X, Y, Z = R([h[0], 0, 0]), R([0, h[1], 0]), R([0, 0, h[2]])
    faces = [(X, Y, Z), (mul(X, -1), Z, Y), (Y, Z, X), (mul(Y, -1), X, Z), (Z, X, Y), (mul(Z, -1), Y, X)]
    pos, idx = [], []
    for off, u, v in faces:
        p, t = quad(add(c, off), u, v)
        base = len(pos)
        pos += p
        idx += [(a + base, b + base, d + base) for a, b, d in t]
    return pos, idx


def icosphere(center, radius, level):
    t = (1 + math.sqrt(5)) / 2
    verts = [norm(v) for v in [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6), (7, 1, 8),
             (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    for _ in range(level):
        cache = {}

        def mid(a, b):
            k = (min(a, b), max(a, b))
            if k not in cache:
                verts.append(norm(mul(add(verts[a], verts[b]), 0.5)))
                cache[k] = len(verts) - 1
            return cache[k]
        nf = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            nf += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = nf
    return [add(center, mul(v, radius)) for v in verts], faces


def uv_sphere(center, radius, segments, rings):
    """Blender-style UV sphere: single-vertex poles with triangle fans, flat triangles, front faces
    outwards; 2·segments·(rings − 1) triangles (as renderer/src/testing.rs `uv_sphere`)."""
    p = [add(center, [0, radius, 0])]
    for r in range(1, rings):
        th = math.pi * r / rings
        for s in range(segments):
            ph = 2 * math.pi * s / segments
            p.append(add(center, mul([math.sin(th) * math.cos(ph), math.cos(th), -math.sin(th) * math.sin(ph)], radius)))
    p.append(add(center, [0, -radius, 0]))
    ring = lambda r, s: 1 + (r - 1) * segments + s % segments
    bottom = len(p) - 1
    t = []
    for s in range(segments):
        t.append((0, ring(1, s), ring(1, s + 1)))
        for r in range(1, rings - 1):
            a, b, c, d = ring(r, s), ring(r + 1, s), ring(r + 1, s + 1), ring(r, s + 1)
            t += [(a, b, c), (a, c, d)]
        t.append((ring(rings - 1, s), bottom, ring(rings - 1, s + 1)))
    return p, t


class Gltf:
    def __init__(self):
        self.blob = bytearray()
        self.doc = {"asset": {"version": "2.0", "generator": "tessera scenes/make_scenes.py"},
                    "extensionsUsed": ["KHR_materials_specular", "KHR_materials_emissive_strength"],
                    "scene": 0, "scenes": [{"nodes": []}], "nodes": [], "meshes": [], "materials": [],
                    "accessors": [], "bufferViews": [], "buffers": []}

    def material(self, name, base=(0.8, 0.8, 0.8), metallic=0.0, roughness=1.0, lambert=True, emission=None, glass_ior=None,
                 attenuation=None):
        m = {"name": name, "pbrMetallicRoughness": {"baseColorFactor": list(base) + [1.0], "metallicFactor": metallic, "roughnessFactor": roughness}}
        if lambert:
            m["extensions"] = {"KHR_materials_specular": {"specularFactor": 0.0}}
        if glass_ior is not None:
            for ext in ("KHR_materials_transmission", "KHR_materials_ior"):
                if ext not in self.doc["extensionsUsed"]:
                    self.doc["extensionsUsed"].append(ext)
            m["extensions"] = {"KHR_materials_transmission": {"transmissionFactor": 1.0}, "KHR_materials_ior": {"ior": glass_ior}}
        if attenuation is not None:
            # KHR_materials_volume: (attenuationColor, attenuationDistance), absorption only.
            if "KHR_materials_volume" not in self.doc["extensionsUsed"]:
                self.doc["extensionsUsed"].append("KHR_materials_volume")
            color, distance = attenuation
            m["extensions"]["KHR_materials_volume"] = {"thicknessFactor": 1.0, "attenuationColor": list(color),
                                                       "attenuationDistance": distance}
        if emission is not None:
            s = max(emission)
            m["emissiveFactor"] = [e / s for e in emission]
            m.setdefault("extensions", {})["KHR_materials_emissive_strength"] = {"emissiveStrength": s}
        self.doc["materials"].append(m)
        return len(self.doc["materials"]) - 1

    def _view(self, data, target):
        while len(self.blob) % 4:
            self.blob.append(0)
        off = len(self.blob)
        self.blob += data
        self.doc["bufferViews"].append({"buffer": 0, "byteOffset": off, "byteLength": len(data), "target": target})
        return len(self.doc["bufferViews"]) - 1

    def mesh(self, name, positions, tris, material, normals=False):
        prim = {"material": material, "mode": 4, "attributes": {}}
        if normals:
            # Flat shading: split vertices per triangle with the face normal.
            pos, nrm, idx = [], [], []
            for a, b, c in tris:
                n = norm(cross(sub(positions[b], positions[a]), sub(positions[c], positions[a])))
                for v in (a, b, c):
                    pos.append(positions[v])
                    nrm.append(n)
                idx.append((len(pos) - 3, len(pos) - 2, len(pos) - 1))
            positions, tris = pos, idx
            nv = self._view(b"".join(struct.pack("<3f", *n) for n in nrm), 34962)
            self.doc["accessors"].append({"bufferView": nv, "componentType": 5126, "count": len(nrm), "type": "VEC3"})
            prim["attributes"]["NORMAL"] = len(self.doc["accessors"]) - 1
        pv = self._view(b"".join(struct.pack("<3f", *p) for p in positions), 34962)
        lo = [min(p[i] for p in positions) for i in range(3)]
        hi = [max(p[i] for p in positions) for i in range(3)]
        # min/max must be the float32 values actually stored.
        f32 = lambda x: struct.unpack("<f", struct.pack("<f", x))[0]
        self.doc["accessors"].append({"bufferView": pv, "componentType": 5126, "count": len(positions), "type": "VEC3",
                                      "min": [f32(x) for x in lo], "max": [f32(x) for x in hi]})
        prim["attributes"]["POSITION"] = len(self.doc["accessors"]) - 1
        iv = self._view(b"".join(struct.pack("<3I", *t) for t in tris), 34963)
        self.doc["accessors"].append({"bufferView": iv, "componentType": 5125, "count": 3 * len(tris), "type": "SCALAR"})
        prim["indices"] = len(self.doc["accessors"]) - 1
        self.doc["meshes"].append({"name": name, "primitives": [prim]})
        self.doc["nodes"].append({"name": name, "mesh": len(self.doc["meshes"]) - 1})
        self.doc["scenes"][0]["nodes"].append(len(self.doc["nodes"]) - 1)

    def camera(self, eye, target, yfov_deg, aspect):
        f = norm(sub(target, eye))
        r = norm(cross(f, [0, 1, 0]))
        u = cross(r, f)
        m = r + [0] + u + [0] + mul(f, -1) + [0] + eye + [1]
        self.doc.setdefault("cameras", []).append({"type": "perspective", "perspective": {"yfov": math.radians(yfov_deg), "aspectRatio": aspect, "znear": 0.01}})
        self.doc["nodes"].append({"name": "camera", "camera": len(self.doc["cameras"]) - 1, "matrix": m})
        self.doc["scenes"][0]["nodes"].append(len(self.doc["nodes"]) - 1)

    def write(self, path):
        self.doc["buffers"] = [{"byteLength": len(self.blob), "uri": "data:application/octet-stream;base64," + base64.b64encode(bytes(self.blob)).decode()}]
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as f:
            json.dump(self.doc, f, indent=1)
            f.write("\n")


def write_glb(g, path):
    """The same document as a binary .glb (buffer 0 in the BIN chunk)."""
    doc = dict(g.doc)
    doc["buffers"] = [{"byteLength": len(g.blob)}]
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    blob = bytes(g.blob) + b"\0" * (-len(g.blob) % 4)
    out = struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(js) + 8 + len(blob))
    out += struct.pack("<I4s", len(js), b"JSON") + js + struct.pack("<I4s", len(blob), b"BIN\0") + blob
    with open(path, "wb") as f:
        f.write(out)


def cornell():
    g = Gltf()
    white = g.material("white", (0.725, 0.71, 0.68))
    red = g.material("red", (0.63, 0.065, 0.05))
    green = g.material("green", (0.14, 0.45, 0.091))
    light = g.material("light", (0.0, 0.0, 0.0), emission=(17.0, 12.0, 4.0))
    X, Y, Z = [1, 0, 0], [0, 1, 0], [0, 0, 1]
    for name, (c, u, v), m in [
        ("floor", ([0, -1, 0], Z, X), white),
        ("ceiling", ([0, 1, 0], X, Z), white),
        ("back", ([0, 0, -1], X, Y), white),
        ("left", ([-1, 0, 0], Y, Z), red),
        ("right", ([1, 0, 0], Z, Y), green),
    ]:
        p, t = quad(c, u, v)
        g.mesh(name, p, t, m, normals=True)
    p, t = quad([0, 0.98, 0], mul(X, 0.25), mul(Z, 0.2))
    g.mesh("light", p, t, light, normals=True)
    p, t = cuboid([0.35, -0.7, 0.35], [0.3, 0.3, 0.3], -17)
    g.mesh("short_box", p, t, white, normals=True)
    p, t = cuboid([-0.35, -0.4, -0.3], [0.3, 0.6, 0.3], 17)
    g.mesh("tall_box", p, t, white, normals=True)
    g.camera([0, 0, 3.9], [0, 0, 0], 39.3, 1.0)
    g.write(os.path.join(HERE, "cornell", "cornell.gltf"))
    write_glb(g, os.path.join(HERE, "cornell", "cornell.glb"))


def veach():
    """Veach 1997 fig. 9.2 in spirit: four metal plates of rising roughness reflecting four spherical
    lights of equal power and falling size, on a black background (no normals: flat shading)."""
    g = Gltf()
    eye, target = [0, 2.0, 12.0], [0, 1.3, 0]
    lights_y, lights_z = 3.6, -2.5
    radii = [0.6, 0.2, 0.067, 0.022]
    xs = [-3.3, -1.1, 1.1, 3.3]
    for i, (r, x) in enumerate(zip(radii, xs)):
        radiance = 0.8 * (radii[0] / r) ** 2  # equal power: radiance ∝ 1 / area
        m = g.material(f"light{i}", (0, 0, 0), emission=(radiance, radiance, radiance))
        p, t = icosphere([x, lights_y, lights_z], r, 2)
        g.mesh(f"light{i}", p, t, m)
    roughness = [0.05, 0.12, 0.25, 0.45]
    light_c = [0, lights_y, lights_z]
    for i, rgh in enumerate(roughness):
        c = [0, -0.6 + 0.55 * i, 3.0 - 1.5 * i]
        n = norm(add(norm(sub(eye, c)), norm(sub(light_c, c))))
        u = [4.0, 0, 0]
        v = mul(norm(cross(n, [1, 0, 0])), 0.55)
        # quad(c, u, v) faces along u × v; make that the plate normal.
        if dot(cross(u, v), n) < 0:
            v = mul(v, -1)
        m = g.material(f"plate{i}", (1, 1, 1), metallic=1.0, roughness=rgh, lambert=False)
        p, t = quad(c, u, v)
        g.mesh(f"plate{i}", p, t, m)
    g.camera(eye, target, 32.0, 4 / 3)
    g.write(os.path.join(HERE, "veach", "veach.gltf"))


def envlit():
    """Lit only by scenes/env/sunset.exr (sun ≈ 6e3): a white Lambert sphere, a rough white metal sphere
    and a grey Lambert ground, seen slightly from above."""
    g = Gltf()
    ground = g.material("ground", (0.5, 0.5, 0.5))
    white = g.material("white", (0.8, 0.8, 0.8))
    metal = g.material("metal", (1, 1, 1), metallic=1.0, roughness=0.3, lambert=False)
    p, t = quad([0, 0, 0], [0, 0, 3.0], [3.0, 0, 0])
    g.mesh("ground", p, t, ground, normals=True)
    p, t = icosphere([-0.6, 0.5, 0], 0.5, 3)
    g.mesh("lambert_sphere", p, t, white)
    p, t = icosphere([0.6, 0.5, 0], 0.5, 3)
    g.mesh("metal_sphere", p, t, metal)
    g.camera([0, 1.6, 3.6], [0, 0.4, 0], 35.0, 4 / 3)
    g.write(os.path.join(HERE, "envlit", "envlit.gltf"))


def glass(absorbing=False):
    """A smooth and a rough (0.3) glass sphere of ior 1.5 on a two-tone Lambert floor before a wall,
    lit by one area light: refraction, total internal reflection, caustics. `absorbing`: the same
    with both spheres tinted inside (KHR_materials_volume, Beer–Lambert), scenes/glass_absorb."""
    g = Gltf()
    floor_a = g.material("floor_a", (0.7, 0.7, 0.7))
    floor_b = g.material("floor_b", (0.2, 0.3, 0.6))
    wall = g.material("wall", (0.6, 0.4, 0.3))
    light = g.material("light", (0, 0, 0), emission=(30.0, 28.0, 24.0))
    tint = ((0.9, 0.6, 0.4), 0.8) if absorbing else None
    smooth = g.material("smooth_glass", (1, 1, 1), roughness=0.0, lambert=False, glass_ior=1.5, attenuation=tint)
    rough = g.material("rough_glass", (1, 1, 1), roughness=0.3, lambert=False, glass_ior=1.5, attenuation=tint)
    X, Y, Z = [1, 0, 0], [0, 1, 0], [0, 0, 1]
    for i in range(4):  # floor stripes, so refraction shows
        p, t = quad([-1.5 + i, 0, 0], mul(Z, 3.0), mul(X, 0.5))
        g.mesh(f"floor{i}", p, t, floor_a if i % 2 == 0 else floor_b, normals=True)
    p, t = quad([0, 1.5, -2.0], mul(X, 2.0), mul(Y, 1.5))
    g.mesh("wall", p, t, wall, normals=True)
    p, t = quad([0.5, 2.5, 1.0], mul(X, 0.4), mul(Z, 0.4))
    g.mesh("light", p, t, light, normals=True)
    p, t = icosphere([-0.6, 0.5, 0.2], 0.5, 3)
    g.mesh("smooth_sphere", p, t, smooth)
    p, t = icosphere([0.6, 0.5, 0.2], 0.5, 3)
    g.mesh("rough_sphere", p, t, rough)
    g.camera([0, 1.4, 4.0], [0, 0.5, 0], 35.0, 4 / 3)
    name = "glass_absorb" if absorbing else "glass"
    os.makedirs(os.path.join(HERE, name), exist_ok=True)
    g.write(os.path.join(HERE, name, f"{name}.gltf"))


def many_lights():
    """1024 small emissive quads (0.08 × 0.08, facing down, colours and strengths varying) over a
    40 × 40 grey floor with a few white boxes: from any shading point almost every light is far away,
    so power-proportional selection wastes most samples and the light tree pays off."""
    g = Gltf()
    floor = g.material("floor", (0.5, 0.5, 0.5))
    white = g.material("white", (0.8, 0.8, 0.8))
    X, Y, Z = [1, 0, 0], [0, 1, 0], [0, 0, 1]
    p, t = quad([0, 0, 0], mul(Z, 20.0), mul(X, 20.0))
    g.mesh("floor", p, t, floor, normals=True)
    for k, (x, z, h) in enumerate([(-3, -2, 1.0), (2, 1, 0.6), (6, -6, 1.4), (-8, 5, 0.8)]):
        p, t = cuboid([x, h / 2, z], [0.5, h / 2, 0.5], 20 * k)
        g.mesh(f"box{k}", p, t, white, normals=True)
    palette = [(1.0, 0.6, 0.3), (0.3, 0.6, 1.0), (1.0, 1.0, 1.0), (0.6, 1.0, 0.4)]
    pos, idx, mats = [], [], {}
    for i in range(32):
        for j in range(32):
            c = palette[(i * 7 + j * 3) % 4]
            strength = 40.0 * (1 + ((i * 13 + j * 5) % 5))
            key = (c, strength)
            if key not in mats:
                mats[key] = g.material(f"lamp{len(mats)}", (0, 0, 0), emission=tuple(strength * x for x in c))
            x, z = -19.0 + i * 38.0 / 31, -19.0 + j * 38.0 / 31
            qp, qt = quad([x, 2.0, z], mul(X, 0.04), mul(Z, 0.04))  # X × Z = −Y: facing down
            g.mesh(f"lamp_{i}_{j}", qp, qt, mats[key])
    g.camera([0, 3.0, 14.0], [0, 0.5, 0], 45.0, 4 / 3)
    g.write(os.path.join(HERE, "many_lights", "many_lights.gltf"))


def sphere_light():
    """Issue 10's case: a Lambert floor (0.4) at y = −4.2 under a one-sided UV-sphere light (radius 0.3,
    48 × 24, flat triangles, emissive 11.11) at the origin; camera at (0, 3, 6) looking at the floor."""
    g = Gltf()
    floor = g.material("floor", (0.4, 0.4, 0.4))
    light = g.material("bulb", (0, 0, 0), emission=(11.11, 11.11, 11.11))
    p, t = quad([0, -4.2, 0], [0, 0, 5.0], [5.0, 0, 0])  # Z × X = +Y: facing up
    g.mesh("floor", p, t, floor)
    p, t = uv_sphere([0, 0, 0], 0.3, 48, 24)
    g.mesh("bulb", p, t, light)
    g.camera([0, 3, 6], [0, -4.2, 0], 50.0, 1.0)
    g.write(os.path.join(HERE, "sphere_light", "sphere_light.gltf"))


def sphere_lights():
    """Four one-sided UV-sphere bulbs of 1152 flat triangles each (32 × 19) over a Lambert floor with a
    white box: mesh emitters as modellers make them, for the light samplers' cost (issue 10)."""
    g = Gltf()
    floor = g.material("floor", (0.5, 0.5, 0.5))
    white = g.material("white", (0.8, 0.8, 0.8))
    p, t = quad([0, 0, 0], [0, 0, 6.0], [6.0, 0, 0])
    g.mesh("floor", p, t, floor)
    p, t = cuboid([0.3, 0.4, -0.5], [0.4, 0.4, 0.4], 25)
    g.mesh("box", p, t, white)
    for i, (x, z, e) in enumerate([(-2.0, -1.0, 30.0), (1.8, -1.6, 20.0), (-0.8, 1.4, 40.0), (2.2, 1.2, 25.0)]):
        m = g.material(f"bulb{i}", (0, 0, 0), emission=(e, 0.9 * e, 0.75 * e))
        p, t = uv_sphere([x, 1.2 + 0.3 * i, z], 0.15 + 0.05 * i, 32, 19)
        g.mesh(f"bulb{i}", p, t, m)
    g.camera([0, 4.0, 7.0], [0, 0.4, 0], 45.0, 4 / 3)
    g.write(os.path.join(HERE, "sphere_lights", "sphere_lights.gltf"))


if __name__ == "__main__":
    cornell()
    veach()
    envlit()
    glass()
    glass(absorbing=True)
    many_lights()
    sphere_light()
    sphere_lights()
