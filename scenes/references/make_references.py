#!/usr/bin/env python3
"""Renders reference images of Tessera's test scenes with Mitsuba 3 (an independent renderer).

    pip install mitsuba numpy
    python3 scenes/references/make_references.py [--spp 4096] [--passes 16] [scene ...]

For each scene (default: cornell, veach) it reads the glTF itself (the subset our scenes use: node
matrices/TRS, triangle meshes, Lambert = KHR_materials_specular specularFactor 0, white metal =
metallic 1 + baseColor 1, emissive + KHR_materials_emissive_strength, perspective camera) and builds
the equivalent Mitsuba scene, following ../shared/guide: `path` integrator, `hdrfilm` with a box
filter, `perspective` with fov_axis y, Lambert = `diffuse`, white metal = `roughconductor`
(material none, GGX, alpha = roughness²), every non-dielectric BSDF wrapped in `twosided` (glTF surfaces
reflect on both faces), one-sided `area` emitters, `face_normals`.

It renders `--passes` independent passes (different seeds) and writes
`scenes/references/<scene>.exr` with channels R, G, B (the mean) and `variance` (the variance of the
mean *luminance*, estimated from the spread between passes), the same layout as `tessera render`.
The resolution and depth are those the reference tests use (see `SCENES` below).
"""
import argparse
import base64
import json
import math
import os
import struct
import sys
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

# scene name -> (gltf path, width, height). Tessera's max_depth 64 = Mitsuba's max_depth 65.
SCENES = {
    "cornell": ("cornell/cornell.gltf", 128, 128),
    "veach": ("veach/veach.gltf", 128, 96),
    "envlit": ("envlit/envlit.gltf", 128, 96),
    "glass": ("glass/glass.gltf", 128, 96),
    "glass_absorb": ("glass_absorb/glass_absorb.gltf", 128, 96),
    "many_lights": ("many_lights/many_lights.gltf", 128, 96),
    "sphere_light": ("sphere_light/sphere_light.gltf", 128, 128),
    "sphere_lights": ("sphere_lights/sphere_lights.gltf", 128, 96),
}
# scene name -> (environment map under scenes/, Tessera --env-rotate degrees). Tessera's mapping equals
# Mitsuba's envmap with to_world = rotate(Y, 90° + rotate) (../shared/guide; checked with a probe render).
ENVIRONMENTS = {
    "envlit": ("env/sunset.exr", 0.0),
}
TESSERA_MAX_DEPTH = 64


def tessera_env_args(name):
    """`tessera render`'s flags for scene `name`'s environment (`ENVIRONMENTS`), [] for none."""
    env = ENVIRONMENTS.get(name)
    return ["--env", os.path.join(ROOT, env[0]), "--env-rotate", str(env[1])] if env else []


def mat_from_trs(node):
    if "matrix" in node:
        return np.array(node["matrix"], dtype=np.float64).reshape(4, 4).T  # column-major
    t = node.get("translation", [0, 0, 0])
    x, y, z, w = node.get("rotation", [0, 0, 0, 1])
    s = node.get("scale", [1, 1, 1])
    r = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    m = np.eye(4)
    m[:3, :3] = r @ np.diag(s)
    m[:3, 3] = t
    return m


def load_buffers(doc, base):
    out = []
    for b in doc["buffers"]:
        uri = b["uri"]
        if uri.startswith("data:"):
            out.append(base64.b64decode(uri.split(",", 1)[1]))
        else:
            with open(os.path.join(base, uri), "rb") as f:
                out.append(f.read())
    return out


def read_accessor(doc, buffers, idx):
    a = doc["accessors"][idx]
    v = doc["bufferViews"][a["bufferView"]]
    ncomp = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[a["type"]]
    dtype = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}[a["componentType"]]
    start = v.get("byteOffset", 0) + a.get("byteOffset", 0)
    size = np.dtype(dtype).itemsize * ncomp
    stride = v.get("byteStride", size)
    raw = buffers[v["buffer"]]
    rows = [np.frombuffer(raw, dtype=dtype, count=ncomp, offset=start + i * stride) for i in range(a["count"])]
    return np.array(rows).reshape(a["count"], ncomp)


def write_ply(path, pos, faces):
    with open(path, "wb") as f:
        f.write(("ply\nformat binary_little_endian 1.0\nelement vertex %d\nproperty float x\nproperty float y\n"
                 "property float z\nelement face %d\nproperty list uchar int vertex_indices\nend_header\n" % (len(pos), len(faces))).encode())
        f.write(np.asarray(pos, dtype="<f4").tobytes())
        for t in faces:
            f.write(struct.pack("<B3i", 3, *[int(i) for i in t]))


def material_dict(m):
    """The Mitsuba BSDF of a glTF material. glTF surfaces reflect on both faces (Tessera turns the
    shading frame to the side a ray arrives from), so every non-dielectric BSDF is wrapped in
    `twosided`: a one-sided Mitsuba BSDF is black from behind (issue 10: a thin plate's underside)."""
    d = _material_dict(m)
    return d if d["type"] in ("dielectric", "roughdielectric") else {"type": "twosided", "bsdf": d}


def _material_dict(m):
    ext = m.get("extensions", {})
    pbr = m.get("pbrMetallicRoughness", {})
    base = pbr.get("baseColorFactor", [1, 1, 1, 1])[:3]
    metallic = pbr.get("metallicFactor", 1.0)
    rough = pbr.get("roughnessFactor", 1.0)
    spec = ext.get("KHR_materials_specular", {}).get("specularFactor", 1.0)
    if ext.get("KHR_materials_transmission", {}).get("transmissionFactor", 0.0) == 1.0 and metallic == 0.0 and base == [1, 1, 1]:
        ior = ext.get("KHR_materials_ior", {}).get("ior", 1.5)
        alpha = rough * rough
        if alpha < 1e-3:
            return {"type": "dielectric", "int_ior": ior, "ext_ior": 1.0}
        return {"type": "roughdielectric", "int_ior": ior, "ext_ior": 1.0, "distribution": "ggx", "alpha": alpha, "sample_visible": True}
    if metallic == 0.0 and spec == 0.0:
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": base}}
    if metallic == 1.0 and base == [1, 1, 1]:
        alpha = rough * rough
        if alpha < 1e-3:  # Tessera's delta threshold (microfacet.rs)
            return {"type": "conductor", "material": "none"}
        return {"type": "roughconductor", "material": "none", "distribution": "ggx", "alpha": alpha, "sample_visible": True}
    sys.exit(f"material {m.get('name')}: not in the subset this script maps to Mitsuba")


def absorption(m):
    """KHR_materials_volume's absorption coefficient σ = −ln(attenuationColor) / attenuationDistance
    (Tessera's `Material::absorption`), or None where the material has no volume (none, or a thin
    wall: thicknessFactor 0, its default)."""
    vol = m.get("extensions", {}).get("KHR_materials_volume")
    if vol is None or "attenuationDistance" not in vol or not vol.get("thicknessFactor", 0.0) > 0.0:
        return None
    color = vol.get("attenuationColor", [1.0, 1.0, 1.0])
    return [-math.log(max(c, 1e-30)) / vol["attenuationDistance"] for c in color]


def build_scene(gltf_path, width, height, spp, tmp, env=None, rr_depth=5, max_depth=TESSERA_MAX_DEPTH):
    """The Mitsuba scene of a suite glTF. `rr_depth`: the bounce from which Russian roulette may end
    paths (Tessera's `--rr-depth`; 5, both renderers' default; `TESSERA_MAX_DEPTH + 1` or more: none).
    `max_depth`: Tessera's `--max-depth` (bounces: 0 emission only, 1 direct light), Mitsuba's
    max_depth less one (its 1 is emission only)."""
    with open(gltf_path) as f:
        doc = json.load(f)
    buffers = load_buffers(doc, os.path.dirname(gltf_path))
    scene = {"type": "scene",
             "integrator": {"type": "path", "max_depth": max_depth + 1, "rr_depth": rr_depth,
                            "hide_emitters": False}}
    if env is not None:
        import mitsuba as mi
        scene["environment"] = {"type": "envmap", "filename": os.path.join(ROOT, env[0]),
                                "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], 90.0 + env[1])}
    stack = [(n, np.eye(4)) for n in doc["scenes"][doc.get("scene", 0)]["nodes"]]
    k = 0
    while stack:
        ni, parent = stack.pop()
        node = doc["nodes"][ni]
        world = parent @ mat_from_trs(node)
        if "camera" in node:
            cam = doc["cameras"][node["camera"]]["perspective"]
            # glTF camera: right, up, looks down -Z. Mitsuba camera: x = left, y = up, looks down +Z.
            to_world = world @ np.diag([-1.0, 1.0, -1.0, 1.0])
            scene["sensor"] = {"type": "perspective", "fov": math.degrees(cam["yfov"]), "fov_axis": "y",
                               "to_world": __import__("mitsuba").ScalarTransform4f(to_world.tolist()),
                               "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
                                        "pixel_format": "rgb"},
                               "sampler": {"type": "independent", "sample_count": spp}}
        if "mesh" in node:
            for prim in doc["meshes"][node["mesh"]]["primitives"]:
                pos = read_accessor(doc, buffers, prim["attributes"]["POSITION"]).astype(np.float64)
                pos = (world @ np.c_[pos, np.ones(len(pos))].T).T[:, :3]
                idx = read_accessor(doc, buffers, prim["indices"]).reshape(-1, 3) if "indices" in prim else np.arange(len(pos)).reshape(-1, 3)
                if np.linalg.det(world[:3, :3]) < 0:
                    idx = idx[:, [0, 2, 1]]
                path = os.path.join(tmp, f"m{k}.ply")
                write_ply(path, pos, idx)
                m = doc["materials"][prim["material"]]
                shape = {"type": "ply", "filename": path, "face_normals": True, "bsdf": material_dict(m)}
                sigma = absorption(m)
                if sigma is not None:
                    # Beer–Lambert inside: a medium that absorbs and never scatters, which
                    # Mitsuba's volumetric path tracer (not `path`) attenuates by.
                    # (An RGB σ must lie in [0, 1]: it is given over its largest channel, times `scale`.)
                    top = max(max(sigma), 1e-30)
                    shape["interior"] = {"type": "homogeneous", "scale": top,
                                         "sigma_t": {"type": "rgb", "value": [c / top for c in sigma]},
                                         "albedo": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
                    scene["integrator"]["type"] = "volpath"
                em = m.get("emissiveFactor", [0, 0, 0])
                strength = m.get("extensions", {}).get("KHR_materials_emissive_strength", {}).get("emissiveStrength", 1.0)
                if max(em) > 0:
                    shape["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": [e * strength for e in em]}}
                    shape["bsdf"] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}} if _material_dict(m)["type"] == "diffuse" else shape["bsdf"]
                scene[f"shape{k}"] = shape
                k += 1
        for c in node.get("children", []):
            stack.append((c, world))
    return scene


def main():
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    ap = argparse.ArgumentParser()
    ap.add_argument("--spp", type=int, default=4096, help="samples per pixel in total")
    ap.add_argument("--passes", type=int, default=16)
    ap.add_argument("scenes", nargs="*", default=list(SCENES))
    args = ap.parse_args()
    import time
    for name in args.scenes:
        rel, w, h = SCENES[name]
        per = args.spp // args.passes
        with tempfile.TemporaryDirectory() as tmp:
            scene = mi.load_dict(build_scene(os.path.join(ROOT, rel), w, h, per, tmp, ENVIRONMENTS.get(name)))
            imgs = []
            t0 = time.time()
            for p in range(args.passes):
                imgs.append(np.array(mi.render(scene, seed=p, spp=per), dtype=np.float64)[:, :, :3])
                print(f"{name}: pass {p + 1}/{args.passes} ({time.time() - t0:.0f}s)", flush=True)
        stack = np.stack(imgs)  # passes × h × w × 3
        mean = stack.mean(axis=0)
        lum = stack @ np.array([0.2126, 0.7152, 0.0722])
        var_mean = lum.var(axis=0, ddof=1) / args.passes
        out = os.path.join(HERE, f"{name}.exr")
        bmp = mi.Bitmap(np.dstack([mean, var_mean]).astype(np.float32), pixel_format=mi.Bitmap.PixelFormat.MultiChannel,
                        channel_names=["R", "G", "B", "variance"])
        bmp.write(out)
        print(f"{name}: wrote {out} ({args.spp} spp, {time.time() - t0:.0f}s, mitsuba {mi.__version__} scalar_rgb)")


if __name__ == "__main__":
    main()
