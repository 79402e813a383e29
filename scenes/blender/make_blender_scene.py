#!/usr/bin/env python3
"""Blender round trip (issue 12): builds a small scene in Blender 4.5 (bpy), exports it with Blender's own
glTF exporter at its defaults (plus "Punctual Lights" and "Cameras", off by default), and renders it with Cycles, so Tessera can be compared with what the user
saw in Blender.

    pip install bpy==4.5.4
    python3 scenes/blender/make_blender_scene.py      # writes lights.glb and lights_cycles.exr here

The scene: a grey floor and a box (Principled BSDF, roughness 1, so the two renderers' BRDF models differ
least), a 300 W point light and a 2 W/m² sun (radius and angle 0: delta lights in both renderers), a
black world, 160x120, 1024 spp, 8 bounces, box filter, no denoising. The exporter writes the lights in
photometric units (W·683/4π cd and W/m²·683 lux); Tessera's `--light-units auto` recognises the exporter
by `asset.generator` and converts back, so the brightness matches Cycles.
"""
import os
import sys

import bpy

HERE = os.path.dirname(os.path.abspath(__file__))
W, H, SPP, BOUNCES = 160, 120, 1024, 8


def main():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene

    def material(name, rgb):
        m = bpy.data.materials.new(name)
        m.use_nodes = True
        p = m.node_tree.nodes["Principled BSDF"]
        p.inputs["Base Color"].default_value = (*rgb, 1.0)
        p.inputs["Roughness"].default_value = 1.0
        p.inputs["Metallic"].default_value = 0.0
        return m

    bpy.ops.mesh.primitive_plane_add(size=10.0, location=(0, 0, 0))
    bpy.context.object.data.materials.append(material("floor", (0.5, 0.5, 0.5)))
    bpy.ops.mesh.primitive_cube_add(size=1.2, location=(0.3, 0.2, 0.6), rotation=(0, 0, 0.4))
    bpy.context.object.data.materials.append(material("box", (0.8, 0.3, 0.2)))

    point = bpy.data.lights.new("point", type="POINT")
    point.energy = 300.0
    point.shadow_soft_size = 0.0
    o = bpy.data.objects.new("point", point)
    o.location = (-1.5, -1.0, 2.5)
    scene.collection.objects.link(o)
    sun = bpy.data.lights.new("sun", type="SUN")
    sun.energy = 2.0
    sun.angle = 0.0
    o = bpy.data.objects.new("sun", sun)
    o.rotation_euler = (0.6, 0.3, 0.8)
    scene.collection.objects.link(o)

    cam = bpy.data.cameras.new("camera")
    cam.lens_unit = "FOV"
    cam.angle = 0.9
    o = bpy.data.objects.new("camera", cam)
    o.location = (4.0, -5.0, 3.2)
    scene.collection.objects.link(o)
    direction = -o.location.normalized()
    o.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()
    scene.camera = o

    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    scene.world = world

    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = SPP
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = BOUNCES
    scene.cycles.diffuse_bounces = BOUNCES
    scene.cycles.glossy_bounces = BOUNCES
    scene.cycles.sample_clamp_direct = 0.0
    scene.cycles.sample_clamp_indirect = 0.0
    scene.cycles.filter_type = "BOX"
    scene.cycles.pixel_filter_type = "BOX"
    scene.render.resolution_x, scene.render.resolution_y = W, H
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = os.path.join(HERE, "lights_cycles.exr")

    # Defaults, but for the two boxes a user ticks to take lights and camera along (both off by default).
    bpy.ops.export_scene.gltf(filepath=os.path.join(HERE, "lights.glb"), export_lights=True, export_cameras=True)
    import time
    t = time.time()
    bpy.ops.render.render(write_still=True)
    print(f"cycles: {W}x{H} {SPP} spp in {time.time() - t:.1f}s -> {scene.render.filepath}", file=sys.stderr)


if __name__ == "__main__":
    main()
