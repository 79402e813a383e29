#!/usr/bin/env python3
"""Renders Tessera's test scenes with Blender Cycles (`pip install bpy==4.5.4`), for comparisons at
equal time. Not a reference maker: the references are Mitsuba's (make_references.py); this gives a
second production renderer's error-against-time on the same scenes.

The scene comes in through Blender's own glTF importer; then, so that Cycles renders the image the
other renderers render:
- emission is made one-sided (Cycles' mesh lights emit from both faces; glTF's and Tessera's, and
  Mitsuba's `area`, from the front only): the back face is black, emission sampling FRONT;
- no denoising, no adaptive sampling, no clamping, box pixel filter of 1 pixel, 64 bounces of every
  kind (Tessera's max_depth 64), caustics on, no glossy blur ("filter glossy" 0);
- the environment, where the scene has one, as a world Environment Texture rotated to the
  convention Tessera shares with Mitsuba (see ENV_ROTATION_Z).

`render(...)` returns the linear RGB image and the wall time of `bpy.ops.render.render`, which includes
Cycles' per-render scene synchronisation and BVH build (measured separately by `sync_overhead`).
"""
import math
import os
import tempfile
import time

import numpy as np

# Rotation about Blender's +Z (degrees) of the world texture that reproduces Tessera's/Mitsuba's
# lat-long mapping after the importer's Y-up -> Z-up conversion. Found by probe renders of envlit at
# 32 spp against the Mitsuba reference: relMSE 6.0e-3 at 0°, 0.33 at 90°, 1.33 at 180°, 3.8 at 270°.
ENV_ROTATION_Z = 0.0


def _load(gltf_path, width, height, env=None, env_rotation_z=None):
    import bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=gltf_path)
    sc = bpy.context.scene
    cams = [o for o in sc.objects if o.type == "CAMERA"]
    sc.camera = cams[0]
    sc.render.engine = "CYCLES"
    c = sc.cycles
    c.device = "CPU"
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.max_bounces = c.diffuse_bounces = c.glossy_bounces = c.transmission_bounces = 64
    c.transparent_max_bounces = 64
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.pixel_filter_type = "BOX"
    c.filter_width = 1.0
    c.caustics_reflective = True
    c.caustics_refractive = True
    c.blur_glossy = 0.0
    sc.render.resolution_x = width
    sc.render.resolution_y = height
    sc.render.resolution_percentage = 100
    sc.render.image_settings.file_format = "OPEN_EXR"
    sc.render.image_settings.color_depth = "32"
    sc.view_settings.view_transform = "Standard"
    for m in bpy.data.materials:
        if not m.use_nodes or "Principled BSDF" not in m.node_tree.nodes:
            continue
        nt = m.node_tree
        p = nt.nodes["Principled BSDF"]
        if p.inputs["Emission Strength"].default_value > 0:
            out = nt.nodes["Material Output"]
            geo = nt.nodes.new("ShaderNodeNewGeometry")
            mix = nt.nodes.new("ShaderNodeMixShader")
            black = nt.nodes.new("ShaderNodeBsdfDiffuse")
            black.inputs["Color"].default_value = (0, 0, 0, 1)
            nt.links.new(geo.outputs["Backfacing"], mix.inputs["Fac"])
            nt.links.new(p.outputs["BSDF"], mix.inputs[1])
            nt.links.new(black.outputs["BSDF"], mix.inputs[2])
            nt.links.new(mix.outputs["Shader"], out.inputs["Surface"])
            m.cycles.emission_sampling = "FRONT"
    world = bpy.data.worlds.new("world")
    sc.world = world
    world.use_nodes = True
    nt = world.node_tree
    bg = nt.nodes["Background"]
    if env is None:
        bg.inputs["Strength"].default_value = 0.0
    else:
        tex = nt.nodes.new("ShaderNodeTexEnvironment")
        tex.image = bpy.data.images.load(env)
        tex.interpolation = "Closest"
        coord = nt.nodes.new("ShaderNodeTexCoord")
        mapping = nt.nodes.new("ShaderNodeMapping")
        rz = ENV_ROTATION_Z if env_rotation_z is None else env_rotation_z
        mapping.inputs["Rotation"].default_value = (0.0, 0.0, math.radians(rz))
        nt.links.new(coord.outputs["Generated"], mapping.inputs["Vector"])
        nt.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
        nt.links.new(tex.outputs["Color"], bg.inputs["Color"])
        bg.inputs["Strength"].default_value = 1.0
        world.cycles.sampling_method = "MANUAL"
        world.cycles.sample_map_resolution = 1024
    return sc


class CyclesScene:
    def __init__(self, gltf_path, width, height, env=None, env_rotation_z=None):
        self.sc = _load(gltf_path, width, height, env, env_rotation_z)
        self.tmp = tempfile.mkdtemp()

    def render(self, spp, seed=0):
        """Returns (seconds, image HxWx3 float64)."""
        import bpy
        import mitsuba as mi
        self.sc.cycles.samples = spp
        self.sc.cycles.seed = seed
        out = os.path.join(self.tmp, "cycles.exr")
        self.sc.render.filepath = out
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        seconds = time.perf_counter() - t0
        img = np.array(mi.Bitmap(out), dtype=np.float64)[:, :, :3]
        return seconds, img
